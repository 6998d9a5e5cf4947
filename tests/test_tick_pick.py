"""The budgeted tick's look at the waiting points (RefineQueue.looked_at: the sweep's window and the
points just reset put where they fall) picks what a sort of their union picked: the same ids and AO
codes, tick for tick, on a moving scene with deterministic clocks; RefineQueue.unstarted (the rounds'
points due their whole ray set) says what rays, done and first_grid say."""
import types

import numpy as np
import pytest

import psao.server.tick.budget as budget_module
import psao.server.tick.server_tick as tick_module
from psao.server.tick.budget import BudgetSettings
from psao.server.tick.selection import sorted_union


def sorted_looked_at(tick, changed: np.ndarray, scan: int, among: np.ndarray | None = None) -> np.ndarray:
    """ServerTick._looked_at with the sorted union of the sweep's candidates and `changed` (`among`, the
    best of the last full look for a tick between motion tests: as _looked_at)."""
    q = tick.queue
    n_list = q.listed
    if among is None and len(changed) == 0 and tick._swept_empty >= n_list:
        return changed
    looked = sorted_union([q.candidates(scan), changed]) if among is None else among
    looked = looked[tick.tracked[looked] & (q.done[looked] < q.slices)]
    if tick.refiner is not None:
        looked = looked[~tick.refiner.busy[looked] & ~(tick.refiner.static[looked] & q.first_grid(looked))]
    if among is None:
        tick._swept_empty = 0 if len(looked) or len(changed) else tick._swept_empty + min(scan, n_list)
    return looked


def recording(call, out: list):
    """`call`, its answers appended to `out`."""
    def recorded(*args, **kwargs):
        out.append(call(*args, **kwargs))
        return out[-1]
    return recorded


@pytest.mark.parametrize("scan_points,bake_rays", [(200, 8), (100_000, 8), (300, 2)])
def test_looking_at_the_window_and_the_changed_picks_what_their_sorted_union_picks(make_tick, monkeypatch,
                                                                                    scan_points, bake_rays):
    # a sweep over a long queue (wrapping round it), or the whole queue each tick; a bake of the tick's rays
    # (the motion's resets and their whole traces) or a few-ray first grid (refined in rounds)
    from psao.client.connection import scene_camera_feed

    clock = types.SimpleNamespace(now=1000.0)  # perf_counter of both ticks and their queues: the test's time
    fake = types.SimpleNamespace(perf_counter=lambda: clock.now, thread_time=lambda: 0.0)
    monkeypatch.setattr(tick_module, "time", fake)
    monkeypatch.setattr(budget_module, "time", fake)
    settings = dict(round_rays=2, rays_per_tick=3000.0, scan_points=scan_points, exact_points=40)
    new, old = (make_tick("robots", 24, rays=8, bake_rays=bake_rays, budget=BudgetSettings(**settings))[0]
                for _ in range(2))
    looked_new, looked_old = [], []
    new._looked_at = recording(new._looked_at, looked_new)
    old._looked_at = recording(lambda changed, scan, among=None: sorted_looked_at(old, changed, scan, among), looked_old)
    try:
        feed = scene_camera_feed(new.scene)
        seen = {"traced": 0, "left": 0, "swept": 0, "wrapped": 0}
        for k in range(90):
            t = k / 60 if k < 70 else 1.5  # moving (a motion test every other tick), then at rest
            views = [feed(t)] if k % 3 else [feed(t), feed(t + 1.5)]  # one view, and a union of two
            clock.now = 1000.0 + k / 60
            cursor = new.queue._cursors[0]
            looks = len(looked_new)
            plans = []
            for tick in (new, old):
                tick.set_cameras(views)
                plans.append(tick.prepare(t))
            plan, old_plan = plans
            assert len(looked_new) == len(looked_old)  # (a tick that pools its trace into the next looks at none)
            if len(looked_new) > looks:
                np.testing.assert_array_equal(looked_new[-1], looked_old[-1], err_msg=f"tick {k}")
            np.testing.assert_array_equal(plan.ids, old_plan.ids, err_msg=f"tick {k}")
            np.testing.assert_array_equal(plan.codes, old_plan.codes, err_msg=f"tick {k}")
            np.testing.assert_array_equal(new.queue._list, old.queue._list, err_msg=f"tick {k}")
            assert new.queue._cursors == old.queue._cursors
            q, every = new.queue, np.arange(len(new.tracked))  # the rounds' whole ray sets: as first_grid says
            np.testing.assert_array_equal(q.unstarted(every), (q.rays == 0) & (q.done == 0) & ~q.first_grid(every))
            seen["traced"] += len(plan.ids)
            seen["left"] += len(looked_new) > looks and len(looked_new[-1]) > len(plan.ids)  # the budget left points waiting
            seen["swept"] += new.queue.listed > scan_points
            seen["wrapped"] += new.queue._cursors[0] < cursor
            new.apply(plan)
            old.apply(old_plan)
        assert seen["traced"] > 0 and seen["left"] > 0, seen
        assert (seen["swept"] > 0 and seen["wrapped"] > 0) == (scan_points < 1000), seen
        assert new.queue.count == old.queue.count
    finally:
        new.close()
        old.close()
