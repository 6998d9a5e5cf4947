"""The time-budgeted tick: it always makes progress, converges and then sends nothing, resets history
only where the geometry changed, keeps its queue bounded, and agrees with a full re-trace once settled.
Nothing here depends on speed: budgets are set so small that every tick traces its minimum batch, or
the test counts ticks until the queue is empty."""
import math
import time

import numpy as np
import pytest

from psao.protocol import pointword as pw
from psao.scene import load_scene
from psao.server.bake import bake_scene
from psao.server.tick.budget import TICK_HZ_RANGE, BudgetSettings, RefineQueue, TraceBudget
from psao.server.errors import ConfigError
from psao.server.settings import BakeSettings, ServeSettings, TickSettings
from psao.server.tick.server_tick import ServerTick


SLOWEST_HZ = TICK_HZ_RANGE[0]
LONGEST_MS = 1e3 / SLOWEST_HZ  # the longest budget a tick may have: the period at the slowest tick rate


@pytest.fixture
def budgeted_tick(make_tick):
    """The server tick with a budget so small that every tick traces its minimum batch (`min_points`): one
    ray a tick, not a time (a time's rays follow the tracer's measured speed, and with them how many whole
    traces from static hits fit), unless `budget_ms` is given (at the slowest tick rate, whose period allows
    the longest budget)."""
    def make(name, density, bake_rays, rays, round_rays, min_points, budget_ms=None):
        budget = BudgetSettings(budget_ms=1e-3 if budget_ms is None else budget_ms, round_rays=round_rays,
                                min_points=min_points, rays_per_tick=1.0 if budget_ms is None else 0.0)
        return make_tick(name, density, rays, bake_rays=bake_rays, budget=budget,
                         tick_hz=60.0 if budget_ms is None else SLOWEST_HZ)[0]
    return make


def test_progressive_refinement_converges_then_sends_nothing(budgeted_tick):
    # a static scene baked with 2 rays refines to 8 in rounds of 2 while the budget allows only the
    # minimum batch: each tick makes progress, and once every point holds 8 rays nothing moves
    tick = budgeted_tick("cornell", 24, bake_rays=2, rays=8, round_rays=2, min_points=100)
    try:
        n = int(tick.tracked.sum())
        first = tick(tick.grid, 0.0)
        assert first.traced == 100 and first.batch == 100 and first.budget_used > 1 and first.queue == n
        ticks = 1
        while (s := tick(tick.grid, 0.0)).queue > 0:
            assert s.traced == 100
            ticks += 1
            assert ticks < 4 * n // 100 + 8, "the queue does not drain"
        tick.grid.take_dirty()
        assert (tick.queue.rays[tick.tracked] >= 8).all()
        for t in (0.0, 1.0, 2.0):
            s = tick(tick.grid, t)
            assert s.traced == 0 and s.changed == 0 and s.queue == 0
            b, c = tick.grid.take_dirty()
            assert len(b) == 0 and len(c) == 0
    finally:
        tick.close()


def estimates(tick, ids):
    """The queue's AO codes of `ids` (their accumulated rays) and the codes a full trace gives now."""
    total, unocc = tick.queue._blend(ids)
    pos, nrm = tick.world_points(tick.last_frame, ids)
    tick.pose_tracer(tick.last_frame)
    full = tick.tracer.visibility(pos, nrm, ids, tick.trace_settings)
    return pw.quantise_ao(unocc / total), pw.quantise_ao(full)


def test_refined_ao_is_exactly_a_full_trace(budgeted_tick):
    # rounds are interleaved slices of the one 64-ray set: once a point has all 16, its AO is that set's
    tick = budgeted_tick("cornell", 24, bake_rays=4, rays=64, round_rays=4, min_points=100000)
    try:
        while tick(tick.grid, 0.0).queue > 0:
            pass
        ids = np.flatnonzero(tick.present())
        assert (tick.queue.done[ids] == 16).all() and (tick.queue.rays[ids] == 64).all()
        accumulated, full = estimates(tick, ids)
        np.testing.assert_array_equal(accumulated, full)
        stored = (tick.grid.cells[tick.slot[ids], tick.index[ids]] & 0xFF).astype(np.int64)
        assert np.abs(stored - full.astype(np.int64)).max() <= tick.settings.threshold
    finally:
        tick.close()


def test_after_motion_stops_every_point_converges_to_a_full_trace_at_the_final_pose(budgeted_tick):
    """Motion resets the history of every point whose AO it may change: once still and drained, each
    point's accumulated AO equals a full trace of the scene as it now stands (a point the selection missed
    would keep AO of the old pose)."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=2000)
    try:
        for t in (0.1, 0.2, 0.3, 0.9, 1.7):  # the movers travel, resetting what they pass
            tick(tick.grid, t)
        while tick(tick.grid, 1.7).queue > 0:
            pass
        ids = np.flatnonzero(tick.present())
        accumulated, full = estimates(tick, ids)
        np.testing.assert_array_equal(accumulated, full)
    finally:
        tick.close()


def test_motion_resets_history_near_the_mover_only_and_queue_stays_bounded(budgeted_tick):
    tick = budgeted_tick("courtyard", 16, bake_rays=4, rays=4, round_rays=4, min_points=64)
    try:
        n = int(tick.tracked.sum())
        assert len(tick.queue.waiting(tick.tracked)) == 0  # the bake holds every point's target already
        rays_before = tick.queue.rays.copy()
        s = tick(tick.grid, 0.5)  # the movers jump half a second along their paths
        reset = tick.queue.rays < rays_before
        assert 0 < reset.sum() < n // 2  # a neighbourhood, not the scene
        # one round of 4 rays completes a traced point; static points near the movers traced whole wait no more
        # (the rounds' budget reaches at least min_points, more where static points cost an exact trace)
        assert s.batch >= 64 and s.traced == s.batch + s.exact and s.queue == reset.sum()
        lengths = []
        for k in range(60):  # fast motion (a second of scene time per tick) with a tiny budget
            s = tick(tick.grid, 1.0 + k)
            lengths.append(s.queue)
            assert s.queue <= n and s.batch >= 64 and s.traced == s.batch + s.exact
        assert len(tick.stats_history) <= tick.settings.history
        assert tick.queue.rays.shape == (len(tick.tracked),)
        # motion stops: the queue drains (nothing was dropped, it waited) and no point is left short
        t_end = 60.0
        ticks = 0
        while tick(tick.grid, t_end).queue > 0:
            ticks += 1
            assert ticks < n // 64 + 10
        assert (tick.queue.rays[tick.tracked] >= 4).all()
        assert max(lengths) <= n
    finally:
        tick.close()


def test_priority_visible_then_reset_then_oldest():
    q = RefineQueue(6, target_rays=8, slices=2)
    q.rays[:] = [0, 4, 0, 4, 0, 8]
    q.done[:] = [0, 1, 0, 1, 0, 2]
    q.waiting_since[:] = [5.0, 1.0, 3.0, 2.0, 1.0, 0.0]
    ids = q.waiting(np.ones(6, bool))
    assert list(ids) == [0, 1, 2, 3, 4]
    visible = np.array([True, True, True, True, False])
    assert list(q.pick(ids, visible, 5)) == [2, 0, 1, 3, 4]
    assert list(q.pick(ids, visible, 2)) == [2, 0]

    # a point only in a view's margins (not in its core) after the core's of its kind, whatever its wait
    q = RefineQueue(4, target_rays=8, slices=2)
    q.rays[:], q.done[:] = [0, 0, 0, 4], [0, 0, 0, 1]
    q.waiting_since[:] = [1.0, 2.0, 3.0, 0.0]
    ids, visible = np.arange(4), np.ones(4, bool)
    assert list(q.pick(ids, visible, 4)) == [0, 1, 2, 3]
    assert list(q.pick(ids, visible, 4, np.array([False, True, True, True]))) == [1, 2, 0, 3]


def test_compiled_priority_key_equals_the_queue_key_of_the_views(budgeted_tick):
    # the tick's pick (select_kernels.priority_kernel: world positions, views, key in one pass) against
    # RefineQueue.key of in_any_view of world_points, over moving and static points, none/one/two views
    from psao.client.connection import scene_camera_feed
    from psao.server.tick.select_kernels import PriorityKey
    from psao.server.tick.selection import camera_planes, in_any_view

    tick = budgeted_tick("courtyard", 16, bake_rays=4, rays=8, round_rays=4, min_points=64)
    try:
        feed = scene_camera_feed(tick.scene)
        rng = np.random.default_rng(3)
        for k, t in enumerate((0.3, 1.1, 2.7)):
            tick(tick.grid, t)
            frame = tick.last_frame
            ids = np.sort(rng.choice(len(tick.tracked), 5000, replace=False))
            ids = ids[tick.tracked[ids]]
            assert tick.moving_point[ids].any() and not tick.moving_point[ids].all()
            views = [[], [feed(t)], [feed(t), feed(t + 2.0)]][k]
            tick.set_cameras(views)
            planes = np.stack(tick.cameras) if tick.cameras else None
            cores = np.stack(tick.core_cameras) if tick.core_cameras else None
            margin = tick.settings.view.distance_margin
            base = float(tick.queue.waiting_since[ids].min())
            priority = PriorityKey()
            got = priority(ids, tick.world_pos, tick.local_pos, tick.inst_of, tick.moving_point, frame.transforms,
                            planes, margin, tick.queue.rays, tick.queue.waiting_since, tick.queue.change, base,
                            core_planes=cores)
            pos = tick.world_points(frame, ids)[0]
            visible = in_any_view(pos, tick.cameras, margin)
            # the views without margins: their own planes (fov margin 0), no distance margin
            core = visible & in_any_view(pos, [camera_planes(*c, 0.0) for c in views], 0.0)
            assert 0 < visible.sum() and (k == 0 or not visible.all())
            assert k == 0 or 0 < (visible & ~core).sum()  # some points only in the margins
            np.testing.assert_array_equal(got, tick.queue.key(ids, visible, base, core))
            np.testing.assert_array_equal(priority.visible, visible)
            np.testing.assert_array_equal(priority.core, core)  # the view the whole traces choose from
            _, seen, in_core = tick.priority(frame, ids)
            np.testing.assert_array_equal(seen, visible)
            np.testing.assert_array_equal(in_core, core)
        assert camera_planes(np.full((4, 4), np.nan), np.eye(4), 0.0) is None  # such a view: tick passes planes=None
    finally:
        tick.close()


@pytest.mark.parametrize("budget_ms,tick_hz", [(None, 0.0), (None, math.inf), (None, math.nan),
                                               (None, TICK_HZ_RANGE[1] + 1), (None, TICK_HZ_RANGE[0] - 1),
                                               (1e3 / 60.0 + 0.01, 60.0), (LONGEST_MS + 0.01, SLOWEST_HZ)])
def test_a_tick_rate_out_of_range_or_shorter_than_the_budget_is_refused(budget_ms, tick_hz):
    budget = BudgetSettings(budget_ms=budget_ms)
    with pytest.raises(ConfigError, match="tick rate|tick budget"):
        budget.check_rate(tick_hz)
    with pytest.raises(ConfigError, match="tick rate|tick budget"):
        TraceBudget(budget, tick_hz=tick_hz)
    BudgetSettings(budget_ms=budget_ms and 1.0).check_rate(TICK_HZ_RANGE[1])  # in range: no error


@pytest.mark.parametrize("field,value", [("budget_ms", math.nan), ("budget_ms", -1.0), ("budget_ms", 0.0),
                                         ("round_rays", 0), ("round_rays", 3),
                                         ("round_rays", 2 * TickSettings.rays), ("min_points", 0),
                                         ("exact_share", 1.5), ("exact_share", -0.1), ("exact_share", math.nan),
                                         ("exact_points", -1), ("exact_cost", 0.0), ("exact_cost", -0.5),
                                         ("exact_cost", math.nan), ("refill_points", -1), ("rays_per_tick", -1.0),
                                         ("rays_per_tick", math.nan), ("rays_per_tick", math.inf), ("window", 0),
                                         ("calls", 0), ("local_rays", 0), ("motion_hz", -1.0),
                                         ("motion_hz", math.nan), ("motion_hz", math.inf)])
def test_bad_budget_settings_are_refused(field, value):
    budget = BudgetSettings(**{field: value})
    with pytest.raises(ConfigError):
        TickSettings(budget=budget).check()


def test_a_dead_tracer_worker_is_replaced_and_the_tick_goes_on(caplog):
    import os
    import signal

    bake = bake_scene(load_scene("builtin:courtyard"), BakeSettings(density=8, rays=4, workers=2), show_progress=False)
    tick = ServerTick(bake, TickSettings(rays=4, workers=2, selection=False))
    try:
        tick.tracer.warm_up()
        victim = tick.tracer.worker_pids[0]
        os.kill(victim, signal.SIGKILL)
        s = tick(tick.grid, 0.5)  # selection off: every point traced, through the pool
        assert s.traced > 0 and "restarting its workers" in caplog.text
        assert victim not in tick.tracer.worker_pids
    finally:
        tick.close()


def run_budget(b, fixed: float, rate: float, ticks: int, told: bool = True, slow: dict | None = None) -> list[float]:
    """Seconds of `ticks` trace calls of the batches TraceBudget `b` sizes on a tracer taking `fixed` seconds
    a call besides its rays at `rate` rays a second (which it tells apart: `told`); slow: {call index:
    factor} calls whose fixed part something else slowed that many times."""
    spent = []
    for k in range(ticks):
        rays = 8 * b.points(8)
        spent.append(fixed * (slow or {}).get(k, 1.0) + rays / rate)
        b.observe_trace(rays, spent[-1], rays / rate if told else None)
    return spent


@pytest.mark.parametrize("believed", [2e4, 2e6, 2e8])
@pytest.mark.parametrize("told", [True, False])
def test_trace_budget_settles_where_the_trace_takes_the_budget(believed, told):
    """From a rate believed a hundred times too low or too high, on a tracer paying a fixed cost a call
    (a third of the budget), the calls come to take the budget (budget used 1): after one call where the
    tracer tells its rays' seconds apart, within 25 where it does not."""

    b = TraceBudget(BudgetSettings(budget_ms=6.0, round_rays=8, exact_share=0.0), rays_per_second=believed)
    spent = run_budget(b, 2e-3, 2e6, 40, told)
    assert np.array(spent[1 if told else 25:]) / b.budget_s() == pytest.approx(1.0, abs=0.02)


def test_trace_budget_is_not_thrown_by_slow_calls():
    """Two calls in a row slowed by something else (a first call's set-up, a busy core: 40 times their
    fixed cost) change no batch; three shrink the next ones, never enlarge any; then the batches come
    back to the budget."""

    settled = run_budget(TraceBudget(BudgetSettings(budget_ms=6.0, exact_share=0.0), 2e6), 1e-3, 2e6, 10)[-1]
    b = TraceBudget(BudgetSettings(budget_ms=6.0, exact_share=0.0), 2e6)
    slow = {10: 40.0, 11: 40.0, 20: 40.0, 21: 40.0, 22: 40.0}
    spent = run_budget(b, 1e-3, 2e6, 40, slow=slow)
    calm = [s for k, s in enumerate(spent) if k >= 2 and k not in slow]
    assert max(calm) <= settled * 1.001  # no batch grows from a slow call
    assert spent[12] == pytest.approx(settled) and spent[23] < settled  # two: nothing; three: a smaller batch
    assert spent[-1] == pytest.approx(settled)


def test_trace_budget_traces_half_a_budget_beyond_a_fixed_cost_above_it():
    """A call's fixed cost above the budget: each tick still traces half a budget's worth of rays, not
    min_points."""

    b = TraceBudget(BudgetSettings(budget_ms=4.0, round_rays=8, exact_share=0.0), rays_per_second=2e6)
    spent = run_budget(b, 5e-3, 2e6, 10)
    assert spent[-1] == pytest.approx(5e-3 + 2e-3, rel=0.01)


def test_trace_budget_keeps_a_share_when_late_and_progresses_below_one_point():

    b = TraceBudget(BudgetSettings(), rays_per_second=2e6, tick_hz=60.0)
    for _ in range(100):
        b.observe_other(0.8)  # the other stages alone take 0.8 s: the tick cannot hold 60 Hz
    assert b.budget_s() == pytest.approx(0.2 / 0.8 * b.other_stages_s)
    b.observe_other(10.0)  # one slow tick: the median of the recent ones stands
    assert b.other_stages_s == pytest.approx(0.8)
    tiny = TraceBudget(BudgetSettings(budget_ms=1e-3, min_points=7), rays_per_second=1e3)
    assert tiny.points(8) == 7


def test_trace_budget_leaves_room_for_what_the_service_spends_a_tick():
    """The automatic budget is the period's headroom less the tick's other stages and less the median of
    what its service spent on the recent ticks besides them (observe_service)."""

    b = TraceBudget(BudgetSettings(headroom=0.85), rays_per_second=2e6, tick_hz=60.0)
    b.observe_other(4e-3)
    alone = b.budget_s()
    assert alone == pytest.approx(0.85 / 60 - 4e-3)
    for s in (3e-3, 2e-3, 3e-3, 0.5, math.nan):  # one slow tick and a bad reading change nothing
        b.observe_service(s)
    assert b.service_s == pytest.approx(3e-3)
    assert b.budget_s() == pytest.approx(alone - 3e-3)


def test_budgeted_tick_reports_the_room_it_leaves_the_service(budgeted_tick):
    """What the service reports spending a tick besides the stages (ServerTick.observe_service) is in the
    next tick's statistics as service_ms (the median the automatic budget takes off the period)."""
    tick = budgeted_tick("cornell", 8, bake_rays=2, rays=8, round_rays=2, min_points=10)
    try:
        assert tick(tick.grid, 0.0).service_ms == 0.0
        for s in (2e-3, 4e-3, 3e-3):
            tick.observe_service(s)
        assert tick(tick.grid, 0.0).service_ms == pytest.approx(3.0)
    finally:
        tick.close()


def test_budgeted_tick_traces_its_calls_in_its_own_process_below_local_rays():
    """A budgeted tick's call of more rays than the tracer's own in-process limit (TraceSettings.local_rays)
    but fewer than BudgetSettings.local_rays is traced in the tick's process, not handed to the workers."""
    from psao.server.settings import TraceSettings

    budget = BudgetSettings(rays_per_tick=3 * TraceSettings.local_rays, exact_share=0.0)
    bake = bake_scene(load_scene("builtin:courtyard"), BakeSettings(density=16, rays=4, workers=2), show_progress=False)
    tick = ServerTick(bake, TickSettings(rays=32, workers=2, budget=budget))
    try:
        tick.set_cameras([])
        here = []
        trace_here = tick.tracer._trace_here
        tick.tracer._trace_here = lambda jobs: here.append(len(jobs)) or trace_here(jobs)
        pool = tick.tracer._ensure_pool()
        submitted = []
        submit = pool.submit
        pool.submit = lambda *a, **k: submitted.append(a) or submit(*a, **k)
        s = tick(tick.grid, 0.0)  # a 4-ray bake refined to 32 rays: a long queue, a full batch
        assert s.traced * 8 > TraceSettings.local_rays and here and not submitted
    finally:
        tick.close()


def test_skinned_instances_count_as_moved_between_frames():
    """Frames keep their own copy of the skinned vertices, so a deforming mesh is seen to move (and its
    points join the queue)."""
    from psao.server.tick.animate import SceneAnimator

    scene = load_scene("builtin:robots")
    anim = SceneAnimator(scene)
    a, b = anim.frame(0.2), anim.frame(0.7)
    m = scene.instances[anim.kinds.skinned[0]].mesh
    assert not np.array_equal(a.mesh_vertices[m], b.mesh_vertices[m])


def test_kept_history_blends_until_as_many_fresh_rays_have_come():
    q = RefineQueue(1, target_rays=32, keep_rays=24, slices=4)
    ids = np.array([0])
    q.seed_from_codes(ids, np.array([255]), 32)  # converged at AO 1.0
    q.reset(ids, 0.0)
    assert list(q.waiting(np.ones(1, bool))) == [0]
    code = q.add(ids, np.array([0.0]), 8, 1.0)  # one dark round: 24 kept rays of 1.0, 8 fresh of 0.0
    assert code[0] == pw.quantise_ao(np.array([24 / 32]))[0]
    q.add(ids, np.array([0.0]), 8, 2.0)
    code = q.add(ids, np.array([0.0]), 8, 3.0)  # 24 fresh rays: the kept estimate is dropped
    assert code[0] == 0
    q.add(ids, np.array([0.0]), 8, 4.0)
    assert len(q.waiting(np.ones(1, bool))) == 0


@pytest.mark.parametrize("rays, tick_rays, round_rays", [(128, None, 8), (12, None, 6), (7, None, 7), (5, None, 5),
                                                         (32, 4, 4)])
def test_serve_rounds_divide_the_target_rays(rays, tick_rays, round_rays):
    """Without --tick-rays a round is the default 8 rays or the largest divisor of --rays below it."""
    import psao
    from psao.server.startup import budget

    settings = psao.ServerSettings(serve=ServeSettings(port=0, tick_hz=60.0), bake=BakeSettings(rays=rays),
                                   tick_rays=tick_rays)
    b = budget(settings)
    assert b.round_rays == round_rays
    TickSettings(rays=rays, budget=b).check()


def test_waiting_set_follows_every_change_of_the_history():
    # the queue keeps its waiting ids up to date through seed, reset and add: always done < slices
    rng = np.random.default_rng(3)
    n = 500
    q = RefineQueue(n, target_rays=16, keep_rays=4, slices=4)
    q.compact_min = 8  # compacted often, as a long queue is
    every = np.ones(n, bool)
    q.seed_from_codes(np.arange(0, n, 2), rng.integers(0, 256, n // 2).astype(np.uint32), 16)
    q.seed_from_codes(np.arange(1, n, 4), rng.integers(0, 256, len(range(1, n, 4))).astype(np.uint32), 4)
    for step in range(60):
        np.testing.assert_array_equal(q.waiting(every), np.flatnonzero(q.done < q.slices))
        assert q.count == np.count_nonzero(q.done < q.slices)
        # a sweep in parts of 37 looks at every waiting point
        seen = np.unique(np.concatenate([q.candidates(37) for _ in range(-(-len(q._list) // 37))]))
        np.testing.assert_array_equal(seen, q.waiting())
        q.reset(rng.choice(n, rng.integers(0, 40), replace=True), float(step))
        w = q.waiting(every)
        picked = np.unique(rng.choice(w, min(len(w), 60), replace=False)) if len(w) else w
        q.add(picked, rng.uniform(0, 1, len(picked)).astype(np.float32), 4, float(step), slices=int(rng.integers(1, 3)))
    eligible = rng.uniform(size=n) < 0.5
    np.testing.assert_array_equal(q.waiting(eligible), np.flatnonzero(eligible & (q.done < q.slices)))


def test_few_ray_first_grid_blends_until_the_whole_ray_set():
    """A few-ray first grid (same geometry) stays in the estimate beside the fresh slices until the point
    holds its whole target set, which then alone gives its AO (as a full bake would)."""
    q = RefineQueue(1, target_rays=32, slices=4)
    ids = np.array([0])
    q.seed_from_codes(ids, np.array([255]), 8)  # 8 rays, all unoccluded
    code = q.add(ids, np.array([0.0]), 8, 1.0)
    assert code[0] == pw.quantise_ao(np.array([8 / 16]))[0]
    code = q.add(ids, np.array([0.0]), 8, 2.0)  # 16 fresh rays, still with the first grid's 8
    assert code[0] == pw.quantise_ao(np.array([8 / 24]))[0]
    q.add(ids, np.array([0.0]), 8, 3.0)
    code = q.add(ids, np.array([0.0]), 8, 4.0)  # the whole set: the first grid's rays are gone
    assert code[0] == 0 and len(q.waiting(np.ones(1, bool))) == 0
    # reset before any fresh ray (a mover came near): the first grid's estimate is of other geometry now and
    # blends only until as many fresh rays as it stands for have come
    q = RefineQueue(1, target_rays=32, keep_rays=24, slices=4)
    q.seed_from_codes(ids, np.array([255]), 8)
    q.reset(ids, 1.0)
    assert q.add(ids, np.array([0.0]), 8, 2.0)[0] == 0


def test_reset_again_without_new_rays_changes_nothing():
    rng = np.random.default_rng(2)
    n = 300
    q = RefineQueue(n, target_rays=32, keep_rays=24, slices=4)
    q.seed_from_codes(np.arange(0, n, 3), rng.integers(0, 256, len(range(0, n, 3))).astype(np.uint32), 32)
    q.seed_from_codes(np.arange(1, n, 3), rng.integers(0, 256, len(range(1, n, 3))).astype(np.uint32), 16)
    picked = np.arange(0, n, 7)
    q.add(picked, rng.uniform(0, 1, len(picked)).astype(np.float32), 8, 1.0)
    ids = np.arange(n)
    q.reset(ids, 2.0)
    assert (q.rays == 0).all() and (q.done == 0).all() and (q.old_rays <= 24).all()
    state = [a.copy() for a in (q.rays, q.done, q.unoccluded, q.old_rays, q.old_unoccluded, q.waiting_since)]
    q.reset(ids, 3.0)
    for before, after in zip(state, (q.rays, q.done, q.unoccluded, q.old_rays, q.old_unoccluded, q.waiting_since)):
        np.testing.assert_array_equal(before, after)
    # a few-ray estimate standing for more rays than keep_rays is capped at the first reset
    q2 = RefineQueue(1, target_rays=64, keep_rays=8, slices=8)
    q2.seed_from_codes(np.array([0]), np.array([128], np.uint32), 16)
    q2.reset(np.array([0]), 1.0)
    assert q2.old_rays[0] == 8


def test_rounds_of_a_point_reset_every_tick_go_through_its_whole_ray_set():
    """A reset does not send a point back to its first slice: in a neighbourhood that changes every tick
    its rounds still trace every slice in turn, so the blend of recent rounds averages different rays, and
    any `slices` rounds in a row after the last reset are its whole ray set."""
    q = RefineQueue(3, target_rays=32, keep_rays=24, slices=4)
    ids = np.arange(3)
    q.seed_from_codes(ids, np.full(3, 255, np.uint32), 32)
    traced = []
    for step in range(6):
        q.reset(ids, float(step))
        traced.append(q.next_slice[ids].copy())
        q.add(ids, np.ones(3, np.float32), 8, float(step))
    np.testing.assert_array_equal(np.array(traced)[:, 0], [0, 1, 2, 3, 0, 1])
    for _ in range(3):  # motion stops after the round of slice 1: slices 2, 3, 0 complete the set
        assert len(q.waiting()) == 3
        q.add(ids, np.ones(3, np.float32), 8, 9.0)
    assert len(q.waiting()) == 0 and (q.next_slice == 1).all()


def test_static_points_near_movers_traced_whole_hold_the_full_trace(budgeted_tick):
    """Static points near the movers whose AO changed most are traced whole at once from their kept static
    hits (only the rays the static scene lets through, against the movers): each holds exactly the full
    trace of the scene as it stands at that tick, and waits no more; at most exact_points a tick."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=50, budget_ms=LONGEST_MS)
    tick.settings.budget.exact_points = 300
    tick.settings.budget.exact_share = 0.5
    try:
        exact_total = 0
        for t in (0.1, 0.2, 0.3):
            plan = tick.prepare(t)
            exact = plan.ids[len(plan.ids) - plan.exact:] if plan.exact else plan.ids[:0]
            exact_total += plan.exact
            assert plan.exact <= 300 and not tick.moving_point[exact].any()
            stats = tick.apply(plan)
            assert stats.exact == plan.exact
            if len(exact):
                assert (tick.queue.done[exact] == tick.queue.slices).all() and (tick.queue.rays[exact] == 8).all()
                accumulated, full = estimates(tick, exact)
                np.testing.assert_array_equal(accumulated, full)
                np.testing.assert_array_equal(plan.codes[len(plan.ids) - plan.exact:], full)
        assert exact_total > 0
    finally:
        tick.close()


def test_whole_traces_resume_after_an_edit_voids_the_static_hits(budgeted_tick):
    """An edit that makes a static instance a mover voids every kept static hit; the ticks after it trace
    a few static points near the movers whole with their hits kept again (at most refill_points a tick),
    and from those hits whole traces resume: every one still holds exactly the full trace."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=50, budget_ms=LONGEST_MS)
    tick.settings.budget.exact_points = 300
    tick.settings.budget.refill_points = 40
    try:
        tick(tick.grid, 0.1)
        edited = [inst.name for inst in tick.scene.instances].index("boulder3")  # static, on the floor
        assert edited in tick.kinds.static
        placed = np.array(tick.scene.instances[edited].transform, np.float64)
        placed[1, 3] += 0.5
        tick.edit(edited, placed)
        refilled = exact_after = 0
        for t in (0.2, 0.3, 0.4, 0.5, 0.6):
            plan = tick.prepare(t)
            whole = plan.exact + plan.refilled
            ids = plan.ids[len(plan.ids) - whole:] if whole else plan.ids[:0]
            assert plan.refilled <= 40 and not tick.moving_point[ids].any()
            assert not np.isin(ids, np.flatnonzero(tick.inst_of == edited)).any()
            refilled += plan.refilled
            exact_after += plan.exact if refilled > plan.refilled else 0  # from hits kept again after the edit
            stats = tick.apply(plan)
            assert stats.refilled == plan.refilled and stats.exact == plan.exact
            if whole:
                accumulated, full = estimates(tick, ids)
                np.testing.assert_array_equal(accumulated, full)
                np.testing.assert_array_equal(plan.codes[len(plan.ids) - whole:], full)
        assert refilled > 0 and exact_after > 0
        kept = np.flatnonzero(tick.static_hits.known)
        assert len(kept) == refilled and not tick.moving_point[kept].any()
        bits = tick.static_hits.of(kept)
        np.testing.assert_array_equal(bits, tick.tracer.static_occluded(tick.world_pos[kept], tick.world_nrm[kept],
                                                                        kept, tick.trace_settings))
    finally:
        tick.close()


def test_a_few_ray_bake_gives_the_tick_static_hits_it_keeps_as_it_traces(budgeted_tick):
    """The progressive start's bake traces fewer rays than the tick: its static hits are for other ray sets,
    so the tick starts with none known for its own and keeps them as it traces static points near the movers
    whole (refill); whole traces from those hits follow, each exactly the full trace, and the kept hits equal
    a trace of the static scene alone."""
    tick = budgeted_tick("courtyard", 16, bake_rays=2, rays=8, round_rays=2, min_points=50, budget_ms=LONGEST_MS)
    tick.settings.budget.exact_points = 300
    tick.settings.budget.refill_points = 40
    try:
        hits = tick.static_hits
        assert hits is not None and hits.fits(8, tick.settings.seed) and not hits.known.any()
        assert hits.static[tick.static_ids].all() and not hits.static[tick.moving_point].any()
        refilled = exact_after = 0
        for t in np.arange(0.1, 1.3, 0.1):
            plan = tick.prepare(t)
            whole = plan.exact + plan.refilled
            ids = plan.ids[len(plan.ids) - whole:] if whole else plan.ids[:0]
            assert plan.refilled <= 40 and not tick.moving_point[ids].any()
            refilled += plan.refilled
            exact_after += plan.exact if refilled > plan.refilled else 0
            tick.apply(plan)
            if whole:
                accumulated, full = estimates(tick, ids)
                np.testing.assert_array_equal(accumulated, full)
        assert refilled > 0 and exact_after > 0
        kept = np.flatnonzero(tick.static_hits.known)
        np.testing.assert_array_equal(tick.static_hits.of(kept),
                                      tick.tracer.static_occluded(tick.world_pos[kept], tick.world_nrm[kept], kept,
                                                                  tick.trace_settings))
    finally:
        tick.close()


def test_whole_traces_take_their_share_of_the_budget_and_the_rounds_the_rest():

    b = TraceBudget(BudgetSettings(budget_ms=10.0, exact_points=100000, exact_share=0.5, exact_cost=0.5),
                    rays_per_second=1e6)
    assert b.rays_in_budget() == pytest.approx(1e4)
    assert b.exact_points(32) == 312  # half of 10k rays, at 16 rays' cost a whole trace
    b.settings.exact_points = 200
    assert b.exact_points(32) == 200
    full, rest = b.points(8), b.points(8, spent_rays=200 * b.exact_rays(32))
    assert full == 1250 and rest == 850
    # whole traces that overran their share take nothing from the rest of the budget
    assert b.points(8, spent_rays=1e9) == b.points(8, spent_rays=6000) == 625
    b.settings.exact_share = 0.0
    assert b.exact_points(32) == 0


def test_a_set_number_of_rays_a_tick_holds_whatever_the_tracer_speed():
    """BudgetSettings.rays_per_tick: the batch is that many rays whatever rate the trace calls teach the
    budget (the quality study's load-independent budget)."""

    b = TraceBudget(BudgetSettings(budget_ms=10.0, rays_per_tick=8000.0, exact_share=0.5), rays_per_second=1e6)
    for rays, seconds in ((8000, 0.5), (8000, 0.01), (8000, 0.2)):  # alike calls, any speed
        b.observe_trace(rays, seconds)
        assert b.rays_in_budget() == 8000.0 and b.points(8) == 1000 and b.points(8, spent_rays=4000) == 500
    b.settings.rays_per_tick = 0.0  # back to the time budget: the learned rate decides
    assert b.rays_in_budget() != 8000.0


def test_a_tracer_without_visibility_parts_takes_no_static_hits(make_tick):
    """The warp tracer has no visibility_parts: the tick keeps no static hits for it (no whole traces from
    them), and a trace part that carries static hits, or asks to keep them, is refused rather than traced
    without them."""
    from psao.server.tracer.base import TracePart
    budget = BudgetSettings(budget_ms=LONGEST_MS, round_rays=2, min_points=50)
    tick, bake = make_tick("courtyard", 16, 8, budget=budget, tracer="warp", tick_hz=SLOWEST_HZ)
    try:
        assert bake.static_hits is not None and tick.static_hits is None
        assert not tick.tracer.supports_static_hits
        for t in (0.1, 0.2):
            assert tick(tick.grid, t).exact == 0
        ids = tick.static_ids[:4]
        for extra in ({"static_hit": np.zeros((4, 1), np.uint8)}, {"keep_static": True}):
            with pytest.raises(ConfigError, match="takes no static hits"):
                tick._trace_parts([TracePart(tick.world_pos[ids], tick.world_nrm[ids], ids, tick.trace_settings,
                                             **extra)])
    finally:
        tick.close()


def test_first_within_takes_the_key_order_while_the_costs_fit():
    from psao.server.tick.budget import first_within

    rng = np.random.default_rng(3)
    for _ in range(50):
        n = int(rng.integers(0, 40))
        ids = rng.permutation(1000)[:n]
        key = rng.permutation(n).astype(np.float64)
        cost = rng.choice([2.4, 4.0, 1.0], n)
        total, least = float(rng.uniform(0, 40)), int(rng.integers(0, 5))
        order = ids[np.argsort(key, kind="stable")]
        fits = int(np.searchsorted(np.cumsum(cost[np.argsort(key, kind="stable")]), total, side="right"))
        np.testing.assert_array_equal(first_within(ids, key, cost, total, least), order[:max(fits, min(least, n))])


def test_points_reset_by_motion_get_their_whole_ray_set_in_one_tick(budgeted_tick):
    """A point whose neighbourhood changed gets its whole ray set at once (static points with kept static
    hits as exact traces), not one slice blended with a history from before the change: with rays for
    all of them, every point holds exactly the full trace of the scene as it stands after each moving
    tick, and nothing waits."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=1)
    tick.settings.budget.rays_per_tick = 1e9
    tick.settings.budget.pool_traces = False  # (every tick traces: test_a_motion_test_tick_pools_its_trace)
    try:
        for t in (0.1, 0.2, 0.3):
            s = tick(tick.grid, t)
            assert s.batch > 0 and s.queue == 0
            assert (tick.queue.done[tick.tracked] == tick.queue.slices).all()
            ids = np.flatnonzero(tick.present())
            accumulated, full = estimates(tick, ids)
            np.testing.assert_array_equal(accumulated, full)
    finally:
        tick.close()


def test_motion_tests_run_at_motion_hz_and_miss_no_motion(budgeted_tick):
    """At ticks of 6 Hz of scene time and motion_hz 3 (steps long enough that a mover leaves points behind
    between two ticks), every other tick tests motion, comparing with the frame of the last test (not the
    last tick's): with rays for every waiting point, each tested tick leaves every point holding exactly
    the full trace of the scene as it stands, the motion of the untested tick before it included."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=1)
    tick.settings.budget.rays_per_tick = 1e9
    tick.settings.budget.motion_hz = 3.0
    tick.settings.budget.pool_traces = False
    tested = []
    try:
        for k in range(1, 8):
            t = 0.1 + k / 6
            s = tick(tick.grid, t)
            tested.append(tick._tested_frame.t == t)
            if tested[-1]:
                assert s.batch > 0 and s.queue == 0
                ids = np.flatnonzero(tick.present())
                accumulated, full = estimates(tick, ids)
                np.testing.assert_array_equal(accumulated, full)
            else:
                assert s.traced == 0  # nothing waits between the tests
        s = tick(tick.grid, t + 1 / 6)  # a skipped tick, then the scene stops: its motion is tested at once
        assert tick._tested_frame.t != t + 1 / 6
        tick(tick.grid, t + 1 / 6)
        assert tick._tested_frame.t == t + 1 / 6 and tick.queue.count == 0
        accumulated, full = estimates(tick, np.flatnonzero(tick.present()))
        np.testing.assert_array_equal(accumulated, full)
    finally:
        tick.close()
    assert tested == [True, False, True, False, True, False, True]


@pytest.mark.parametrize("step,every", [(0.3, 2), (0.7, 1)])
def test_motion_tests_are_not_made_twice_in_a_row_while_ticks_are_fast(budgeted_tick, step, every):
    """Ticks slower than motion_hz but faster than half of it (a loaded machine) still test every other
    tick, not every tick (the tick after a test is a cheap one); slower still, every tick tests."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=1)
    tick.settings.budget.motion_hz = 3.0
    tested = []
    try:
        for k in range(1, 7):
            tick(tick.grid, 0.1 + k * step)
            tested.append(tick._tested_frame.t == 0.1 + k * step)
    finally:
        tick.close()
    assert tested == [k % every == 0 for k in range(6)]


def test_a_tick_between_motion_tests_chooses_among_the_best_of_the_last_look(budgeted_tick):
    """The tick between two motion tests chooses among the best of the last full look still waiting (no
    sweep, no priority pass over every reset point), and traces as many points as a tick that looks at
    everything: min_points here (a budget of one ray), with far more waiting."""
    light = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=50)
    full = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=50)
    short = 0
    try:
        for k in range(1, 9):
            t = 0.1 + k / 60
            ahead = light._ahead
            full._ahead = None  # every tick a full look
            a, b = light.prepare(t), full.prepare(t)
            if light._tested_frame is not a.frame:  # no motion test: the short path
                short += 1
                assert ahead is not None and np.isin(a.ids, ahead).all()
            assert len(a.ids) == len(b.ids) == 50 and light.queue.count > 200
            light.apply(a)
            full.apply(b)
    finally:
        light.close()
        full.close()
    assert short == 4


def test_select_warm_up_leaves_the_ticks_answers_as_they_are(budgeted_tick, monkeypatch):
    """The budgeted tick pays the select stage's one-time costs when it is made (its kernels loaded, the
    movers' nearby static points gathered), and its moving ticks then pick and trace exactly what a tick
    made without that warm-up does. Every waiting point is traced each tick (min_points above the queue):
    the priority order weighs wall-clock waits, which differ between two ticks on a busy machine, so the
    plans are compared as sets of (id, AO code), and what motion reset decides them."""
    from psao.server.tick.server_tick import ServerTick

    warm = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=1_000_000)
    monkeypatch.setattr(ServerTick, "_warm_up_select", lambda self: None)
    cold = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=1_000_000)
    warm.settings.budget.motion_hz = cold.settings.budget.motion_hz = 0.0  # every tick tests motion
    try:
        assert warm._priority is not None and cold._priority is None
        for t in (0.05, 0.1, 0.15):
            a, b = warm.prepare(t), cold.prepare(t)
            assert len(a.ids) > 0 and warm.queue.count == 0  # motion reset points, and every one was traced
            ia, ib = np.argsort(a.ids, kind="stable"), np.argsort(b.ids, kind="stable")
            np.testing.assert_array_equal(a.ids[ia], b.ids[ib])
            np.testing.assert_array_equal(a.codes[ia], b.codes[ib])
            warm.apply(a)
            cold.apply(b)
    finally:
        warm.close()
        cold.close()


def test_first_tick_retraces_what_posing_the_skinned_meshes_changed(make_tick):
    """A bake traces skinned meshes in their bind pose; the tick's first frame poses them (here at the
    bake's own time), so its first tick re-traces what that changed: afterwards every point's stored AO
    is a full trace of the posed scene (within the store threshold), as it was not when the tick took the
    bake for the posed frame."""
    tick, _ = make_tick("robots", 8, 8)
    try:
        tick.set_cameras([])
        s = tick(tick.grid, 0.0)
        assert s.traced > 0
        ids = np.flatnonzero(tick.present())
        pos, nrm = tick.world_points(tick.last_frame, ids)
        tick.pose_tracer(tick.last_frame)
        full = pw.quantise_ao(tick.tracer.visibility(pos, nrm, ids, tick.trace_settings)).astype(np.int64)
        stored = (tick.grid.cells[tick.slot[ids], tick.index[ids]] & 0xFF).astype(np.int64)
        assert np.abs(stored - full).max() <= tick.settings.threshold
    finally:
        tick.close()


def test_budgeted_tick_starts_from_the_posed_scene(budgeted_tick):
    """A bake traces skinned meshes in their bind pose; the budgeted tick traces what posing them at the
    bake's time changes before its first tick (start-up), so with a budget of one ray a tick every stored
    AO is already a full trace of the posed scene (within the store threshold), nothing waits, and a
    first tick at the bake's time finds no motion."""
    tick = budgeted_tick("robots", 8, bake_rays=8, rays=8, round_rays=8, min_points=1)
    try:
        ids = np.flatnonzero(tick.present())
        frame = tick.animator.frame(0.0)
        pos, nrm = tick.world_points(frame, ids)
        tick.pose_tracer(frame)
        full = pw.quantise_ao(tick.tracer.visibility(pos, nrm, ids, tick.trace_settings)).astype(np.int64)
        stored = (tick.grid.cells[tick.slot[ids], tick.index[ids]] & 0xFF).astype(np.int64)
        assert np.abs(stored - full).max() <= tick.settings.threshold
        assert tick.queue.count == 0
        tick.set_cameras([])
        s = tick(tick.grid, 0.0)
        assert s.traced == 0 and s.queue == 0
    finally:
        tick.close()


def test_whole_traces_from_static_hits_go_to_points_in_a_view_itself(budgeted_tick):
    """The whole traces from static hits choose among the changed static points in a client's view without
    its margins: a point only in the margins (fov and distance margins) waits for the rounds."""
    from psao.client.connection import scene_camera_feed
    from psao.server.tick.selection import camera_planes, in_any_view

    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=50, budget_ms=LONGEST_MS)
    tick.settings.budget.exact_points = 300
    tick.settings.budget.exact_share = 0.5
    feed = scene_camera_feed(tick.scene)
    margin = tick.settings.view.distance_margin
    seen = {"exact": 0, "margin": 0}
    whole_static = tick._whole_static

    def checked(waiting, *args):
        """The tick's own _whole_static, its answer checked against the views (the plan's tail also holds
        the rounds' cheap whole traces, so it is checked here)."""
        exact, refill = whole_static(waiting, *args)
        frame, core = tick._frame_now, [camera_planes(*tick._view_now, 0.0)]
        chosen = np.concatenate([exact, refill])
        assert in_any_view(tick.world_points(frame, chosen)[0], core, 0.0).all()
        # the changed static points it could have taken had it chosen among every visible point
        could = waiting[(tick.queue.change[waiting] >= tick.settings.budget.exact_min_change)
                        & ~tick.moving_point[waiting]]
        pos = tick.world_points(frame, could)[0]
        seen["margin"] += int((in_any_view(pos, tick.cameras, margin) & ~in_any_view(pos, core, 0.0)).sum())
        seen["exact"] += len(chosen)
        return exact, refill

    tick._whole_static = checked
    try:
        for t in np.arange(0.1, 1.0, 0.1):
            view, proj = feed(t)
            proj = np.array(proj, np.float64)
            proj[0, 0] *= 4  # a narrow view: its margins (fov + 20 degrees) hold changed points it does not show
            proj[1, 1] *= 4
            tick._view_now = (view, proj)
            tick.set_cameras([tick._view_now])
            tick._frame_now = tick.animator.frame(t)
            tick.apply(tick.prepare(t))
        assert seen["exact"] > 0 and seen["margin"] > 0
    finally:
        tick.close()


def test_trace_budget_pools_the_budgets_of_ticks_that_left_their_trace():
    """A tick that leaves its trace to the next (pool) adds its budget to the next trace call's, in time
    and in rays (a set number of rays a tick too); the call after it has its own budget again."""

    b = TraceBudget(BudgetSettings(budget_ms=6.0, exact_share=0.0), rays_per_second=2e6)
    alone = b.rays_in_budget()
    assert alone == pytest.approx(6e-3 * 2e6)
    b.pool()
    assert b.trace_budget_s() == pytest.approx(12e-3) and b.rays_in_budget() == pytest.approx(2 * alone)
    b.observe_trace(2 * alone, 12e-3, 12e-3)
    assert b.pooled == 0 and b.trace_budget_s() == pytest.approx(6e-3) and b.rays_in_budget() == pytest.approx(alone)
    fixed = TraceBudget(BudgetSettings(rays_per_tick=5000.0), rays_per_second=2e6)
    fixed.pool()
    assert fixed.rays_in_budget() == 10000.0


def test_a_motion_test_tick_pools_its_trace(budgeted_tick):
    """At 60 ticks a second of scene time and motion_hz 30 (a test every other tick), a tick that tests
    motion traces nothing and leaves its budget to the next tick, which traces in one call with both
    budgets: the points the test reset wait one tick (all of them traced then, the budget allowing)."""
    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=1, budget_ms=LONGEST_MS)
    pooled = []
    try:
        tick(tick.grid, 0.1)  # the first moving tick traces (it tests motion after the bake's frame)
        for k in range(1, 9):
            s = tick(tick.grid, 0.1 + k / 60)
            tested = tick._tested_tick == tick.tick_count - 1
            pooled.append(tested)
            if tested:
                assert s.traced == 0 and s.batch == 0 and s.budget_ms == 0.0
                assert s.queue > 0 and s.queue == len(tick.queue.waiting(tick.tracked))
            else:  # its own budget, and the tick before's when that one pooled
                after_pool = pooled[-2:-1] == [True]
                assert s.budget_ms == pytest.approx(2 * LONGEST_MS if after_pool else LONGEST_MS)
                assert s.queue == 0 and (s.traced > 0 or not after_pool)
    finally:
        tick.close()
    assert pooled == [k % 2 == 1 for k in range(8)]


def test_view_waits_count_the_first_retrace_of_each_reset_point_in_view(budgeted_tick):
    """TickStats.view_waits: every point a tick re-traces for the first time since its reset (no slice of its
    ray set yet), inside a client's view itself, is counted once, its wait (reset to this trace) in the bin
    that brackets it: checked against the queue's state after the tick's motion reset and the view recomputed
    with numpy (in_any_view on the camera without margins)."""
    from psao.client.connection import scene_camera_feed
    from psao.server.tick.selection import camera_planes, in_any_view
    from psao.server.tick.summary import view_wait_counts

    tick = budgeted_tick("courtyard", 16, bake_rays=8, rays=8, round_rays=2, min_points=50, budget_ms=LONGEST_MS)
    feed = scene_camera_feed(tick.scene)
    after_reset = {}
    motion_reset = tick._motion_reset

    def reset(*args):
        changed = motion_reset(*args)
        after_reset.update(done=tick.queue.done.copy(), since=tick.queue.waiting_since.copy())
        return changed

    tick._motion_reset = reset
    counted = 0
    try:
        for t in np.arange(0.1, 1.5, 0.1):
            view, proj = feed(t)
            tick.set_cameras([(view, proj)])
            plan = tick.prepare(t)
            done_at = time.perf_counter()
            stats = tick.apply(plan)
            first = plan.ids[after_reset["done"][plan.ids] == 0]
            pos = tick.world_points(plan.frame, first)[0]
            seen = first[in_any_view(pos, [camera_planes(view, proj, 0.0)], 0.0)]
            assert sum(stats.view_waits) == len(seen)
            waited = after_reset["since"][seen]
            at_most = np.cumsum(view_wait_counts(1e3 * (done_at - waited)))  # every wait is within these bounds
            at_least = np.cumsum(view_wait_counts(np.zeros(len(seen))))
            assert (np.cumsum(stats.view_waits) >= at_most).all() and (np.cumsum(stats.view_waits) <= at_least).all()
            counted += len(seen)
        assert counted > 0
    finally:
        tick.close()
