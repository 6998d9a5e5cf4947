"""Selection geometry: extended frusta against a brute-force clip-space test, block index box queries
against a brute-force scan, and the reach rules for moving instances."""
import numpy as np
import pytest

from psao.scene.camera import look_at, perspective
from psao.server.tick.selection import (INSIDE_CHANGE, BlockIndex, MotionInput, NearCache, frustum_planes, in_any_view,
                                   in_box, in_frustum, reach_boxes, rigid_in_company, sorted_union, static_points_near,
                                   merge_disjoint, occlusion_change, sum_by_index)


def random_points(n, seed=0, scale=20.0):
    return np.random.default_rng(seed).uniform(-scale, scale, size=(n, 3))


def clip_inside(points, view, proj):
    """Brute force: inside the frustum without its near plane, in clip space."""
    h = np.c_[points, np.ones(len(points))] @ (proj @ view).T
    x, y, z, w = h.T
    return (np.abs(x) <= w) & (np.abs(y) <= w) & (z <= w)


@pytest.mark.parametrize("fov,aspect", [(60.0, 16 / 9), (35.0, 1.0), (90.0, 0.5)])
def test_frustum_matches_clip_space(fov, aspect):
    view = look_at((3.0, 2.0, 5.0), (0.0, 0.5, -1.0))
    proj = perspective(fov, aspect, 0.1, 30.0)
    pts = random_points(20000)
    got = in_frustum(pts, frustum_planes(view, proj), 0.0)
    want = clip_inside(pts, view, proj)
    assert got.sum() > 100 and (~got).sum() > 100
    np.testing.assert_array_equal(got, want)


def test_fov_margin_widens_by_degrees():
    view = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    proj = perspective(60.0, 1.0, 0.1, 100.0)
    # points at 10 m in front, at horizontal angles from the axis: the half fov is 30 degrees
    angles = np.radians([25.0, 29.0, 31.0, 34.0, 36.0, 45.0])
    pts = np.c_[10 * np.sin(angles), np.zeros(len(angles)), -10 * np.cos(angles)]
    np.testing.assert_array_equal(in_frustum(pts, frustum_planes(view, proj, 0.0)), [1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(in_frustum(pts, frustum_planes(view, proj, 10.0)), [1, 1, 1, 1, 0, 0])


def test_distance_margin_takes_points_just_outside():
    view = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    proj = perspective(60.0, 1.0, 0.1, 100.0)
    planes = frustum_planes(view, proj)
    behind = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 3.0]])  # behind the eye, 0.5 m and 3 m
    # distance from the right plane through the eye: z * sin(30 deg)
    assert not in_frustum(behind, planes, 0.0).any()
    np.testing.assert_array_equal(in_frustum(behind, planes, 1.0), [True, False])
    far = np.array([[0.0, 0.0, -100.5], [0.0, 0.0, -102.0]])
    np.testing.assert_array_equal(in_frustum(far, planes, 1.0), [True, False])


def test_any_view_is_the_union_and_no_view_is_everything():
    pts = random_points(5000, seed=1)
    proj = perspective(50.0, 1.5, 0.1, 40.0)
    a = frustum_planes(look_at((0, 0, 10), (0, 0, 0)), proj)
    b = frustum_planes(look_at((10, 0, 0), (0, 0, 0)), proj)
    np.testing.assert_array_equal(in_any_view(pts, [a, b], 0.5), in_frustum(pts, a, 0.5) | in_frustum(pts, b, 0.5))
    assert in_any_view(pts, [], 0.5).all() and in_any_view(pts, None, 0.5).all()


@pytest.mark.parametrize("block", [0.3, 1.5, 7.0])
def test_block_index_box_query_matches_scan(block):
    pts = random_points(30000, seed=2, scale=10.0)
    index = BlockIndex(pts, block)
    rng = np.random.default_rng(3)
    for _ in range(30):
        c = rng.uniform(-12, 12, 3)
        h = rng.uniform(0.01, 5.0, 3)
        box = (c - h, c + h)
        np.testing.assert_array_equal(np.sort(index.query_box(box)), np.flatnonzero(in_box(pts, box)))
    assert len(BlockIndex(np.zeros((0, 3)), 1.0).query_box((np.zeros(3), np.ones(3)))) == 0


def box(lo, hi):
    return np.array(lo, float), np.array(hi, float)


def test_reach_uses_current_and_previous_boxes():
    motion = MotionInput({0: box([0, 0, 0], [1, 1, 1])}, {0: box([5, 0, 0], [6, 1, 1])}, rigid=[0], skinned=[])
    reach = reach_boxes(motion, 0.5)[0]
    assert len(reach) == 2  # far apart: two boxes
    np.testing.assert_allclose(reach[0][0], [-0.5, -0.5, -0.5])
    np.testing.assert_allclose(reach[1][1], [6.5, 1.5, 1.5])
    pts = np.array([[1.4, 0.5, 0.5], [3.0, 0.5, 0.5], [4.6, 0.5, 0.5], [6.6, 0.5, 0.5]])
    near = static_points_near(BlockIndex(pts, 1.0), reach_boxes(motion, 0.5))
    np.testing.assert_array_equal(np.flatnonzero(near), [0, 2])
    # unmoved: one box only
    still = MotionInput({0: box([0, 0, 0], [1, 1, 1])}, {0: box([0, 0, 0], [1, 1, 1])}, rigid=[0], skinned=[])
    assert len(reach_boxes(still, 0.5)[0]) == 1
    # a small step: one union box covering both
    step = MotionInput({0: box([0, 0, 0], [1, 1, 1])}, {0: box([0.1, 0, 0], [1.1, 1, 1])}, rigid=[0], skinned=[])
    (u,) = reach_boxes(step, 0.5)[0]
    np.testing.assert_allclose(u[0], [-0.5, -0.5, -0.5])
    np.testing.assert_allclose(u[1], [1.6, 1.5, 1.5])


def moving_spheres(rng, ticks, movers, step):
    """Per tick, MotionInput of `movers` spheres wandering by up to `step` per tick (with the odd jump)."""
    centre = rng.uniform(-8, 8, (movers, 3))
    radius = rng.uniform(0.3, 1.5, movers)
    before = None
    for t in range(ticks):
        centre = centre + rng.uniform(-step, step, centre.shape)
        if t % 9 == 8:
            centre[t % movers] = rng.uniform(-8, 8, 3)  # a jump: leaves the gathered candidates
        boxes = {i: (centre[i] - radius[i], centre[i] + radius[i]) for i in range(movers)}
        spheres = {i: (centre[i].copy(), float(radius[i])) for i in range(movers)}
        yield MotionInput(boxes, before[0] if before else {}, list(range(movers)), [], spheres,
                          before[1] if before else None)
        before = boxes, spheres


def near_setup(rng, n: int, seed: int, ao: float = 1.2):
    """(points, unit normals, their BlockIndex, a NearCache) of `n` random points in a 20-unit cube."""
    pts = random_points(n, seed=seed, scale=10.0)
    nrm = rng.normal(size=pts.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    index = BlockIndex(pts, ao)
    return pts, nrm, index, NearCache(index, nrm, ao, margin=0.25 * ao)


def test_near_cache_matches_static_points_near_over_a_motion():
    rng = np.random.default_rng(7)
    ao = 1.2
    pts, nrm, index, cache = near_setup(rng, 60000, 5, ao)
    for motion in moving_spheres(rng, 40, 3, 0.1):
        reach = reach_boxes(motion, ao)
        want = np.flatnonzero(static_points_near(index, reach, motion, nrm, ao))
        got, change = cache.near(reach, motion)
        np.testing.assert_array_equal(got, want)
        alone, none = cache.near(reach, motion, with_change=False)  # the same points, no estimate
        assert none is None
        np.testing.assert_array_equal(alone, want)
        # the change estimate: occlusion_change of each mover's spheres, summed over the movers that reach a point
        expect = np.zeros(len(pts))
        for i, boxes in reach.items():
            sp = [s[i] for s in (motion.spheres_now, motion.spheres_before) if s and i in s]
            mine = np.flatnonzero(static_points_near(index, {i: boxes}, motion, nrm, ao))
            expect[mine] += occlusion_change(pts[mine], nrm[mine], sp, ao)
        np.testing.assert_allclose(change, expect[want], rtol=1e-5, atol=1e-6)
        assert (change > 0).any()
        # the movers' candidates merged once and reused: bit for bit what a cache made afresh gives
        fresh_ids, fresh_change = NearCache(index, nrm, ao, margin=0.25 * ao).near(reach, motion)
        np.testing.assert_array_equal(got, fresh_ids)
        np.testing.assert_array_equal(change, fresh_change)
    assert 3 <= cache.queries < 40 * 3  # candidates are reused between ticks, refilled when a mover leaves them
    # without spheres: the boxes alone
    motion = MotionInput({0: box([0, 0, 0], [1, 1, 1])}, {}, [0], [])
    reach = reach_boxes(motion, ao)
    got, change = cache.near(reach, motion)
    np.testing.assert_array_equal(got, np.flatnonzero(static_points_near(index, reach)))
    assert (change == 1).all()  # no spheres: the change is unknown, counted as whole


def test_a_point_inside_a_movers_sphere_counts_as_changed():
    """A point inside the mover's bounding sphere before or now (o is 1 there, so |o(now) - o(before)| is 0
    for one inside at both times) counts at least INSIDE_CHANGE: the mover's surface moves around it (a
    robot's feet over the floor). Elsewhere the estimate is |o(now) - o(before)|; the near test's compiled
    estimate is the same."""
    rng = np.random.default_rng(11)
    ao, r = 1.0, 0.8
    before, now = np.array([0.0, 0.75, 0.0]), np.array([0.02, 0.75, 0.0])  # a small step: both spheres overlap
    pts = rng.uniform(-2.5, 2.5, size=(20000, 3))
    nrm = rng.normal(size=pts.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    inside_now = np.linalg.norm(pts - now, axis=1) <= r
    inside_before = np.linalg.norm(pts - before, axis=1) <= r
    assert (inside_now & inside_before).sum() > 100
    change = occlusion_change(pts, nrm, [(now, r), (before, r)], ao)
    assert (change[inside_now | inside_before] >= INSIDE_CHANGE).all()
    out = ~(inside_now | inside_before)
    np.testing.assert_array_equal(change[out], np.abs(occlusion_change(pts[out], nrm[out], [(now, r)], ao)
                                                      - occlusion_change(pts[out], nrm[out], [(before, r)], ao)))
    # the near test (select_kernels.near_kernel) over the same points
    motion = MotionInput({0: (now - r, now + r)}, {0: (before - r, before + r)}, [], [0], {0: (now, r)}, {0: (before, r)})
    index = BlockIndex(pts, 0.25 * ao)
    got, got_change = NearCache(index, nrm, ao, margin=0.25 * ao).near(reach_boxes(motion, ao), motion)
    assert inside_now[got].sum() == inside_now.sum()  # every point inside is near
    np.testing.assert_allclose(got_change, change[got], rtol=1e-6, atol=1e-7)


def test_sum_by_index_sums_the_values_of_each_index():
    ids, vals = sum_by_index([np.array([1, 4, 7]), np.array([], np.int64), np.array([0, 4])],
                             [np.array([1.0, 2.0, 3.0]), np.array([]), np.array([5.0, 0.5])])
    assert list(ids) == [0, 1, 4, 7] and list(vals) == [5.0, 1.0, 2.5, 3.0]


def test_sum_by_index_adds_in_the_order_of_the_parts():
    a, b, c = np.float32(0.9746484), np.float32(0.031535614), np.float32(0.92544216)
    _, vals = sum_by_index([np.array([3]), np.array([3]), np.array([3])], [np.array([a]), np.array([b]), np.array([c])])
    assert vals[0] == (a + b) + c


def test_merge_disjoint_is_sum_by_index_of_disjoint_runs():
    rng = np.random.default_rng(4)
    for trial in range(200):
        n = int(rng.integers(0, 400))
        owner = rng.integers(0, 6, n)  # 0: base; k > 0: run k (its ids consecutive: one instance's)
        owner = np.sort(owner) if trial % 3 == 0 else owner
        blocks = np.split(np.arange(n), np.flatnonzero(np.diff(owner)) + 1) if n else []
        base, runs = [], []
        for blk in blocks:  # a run is one block of equal owners, never split by base ids
            (base if owner[blk[0]] == 0 else runs).append(blk)
        base = np.concatenate(base) if base else np.zeros(0, np.int64)
        base = np.sort(rng.choice(base, int(rng.integers(0, len(base) + 1)), replace=False)) if len(base) else base
        runs = [r for r in runs if len(r)]
        rng.shuffle(runs)
        bv = rng.random(len(base)).astype(np.float32)
        rv = [rng.random(len(r)).astype(np.float32) for r in runs]
        ids, vals = merge_disjoint(base, bv, runs, rv)
        want_ids, want_vals = sum_by_index([base, *runs], [bv, *rv])
        np.testing.assert_array_equal(ids, want_ids)
        np.testing.assert_array_equal(vals, want_vals)
        alone, none = merge_disjoint(base, None, runs)
        assert none is None
        np.testing.assert_array_equal(alone, sorted_union([base, *runs]))


def test_block_index_query_box_is_the_points_in_the_box():
    pts = random_points(5000, seed=3, scale=4.0)
    index = BlockIndex(pts, 0.7)
    for lo in ([-1.0, -2.0, 0.0], [0.5, 0.5, 0.5], [-9.0, -9.0, -9.0]):
        b = box(lo, np.asarray(lo) + [1.5, 2.5, 1.0])
        got = index.query_box(b)
        np.testing.assert_array_equal(np.sort(got), np.flatnonzero(in_box(pts, b)))
        np.testing.assert_array_equal(index.sorted_positions[index.query_box_sorted(b)], pts[got])


def test_sorted_union_is_unique_of_the_parts():
    rng = np.random.default_rng(1)
    parts = [np.unique(rng.integers(0, 500, n)) for n in (0, 40, 300, 7)]
    np.testing.assert_array_equal(sorted_union(parts), np.unique(np.concatenate(parts)))
    assert len(sorted_union([])) == 0 and len(sorted_union([np.zeros(0, np.int64)])) == 0


def test_near_cache_after_a_failed_call_lists_every_point_again():
    """A call that fails after some movers were tested leaves no marks behind: the next call lists and sums
    exactly what a fresh cache does (a point left marked would never be listed again)."""
    rng = np.random.default_rng(8)
    ao = 1.2
    _, nrm, index, cache = near_setup(rng, 20000, 6, ao)
    motion = next(m for t, m in enumerate(moving_spheres(rng, 3, 2, 0.1)) if t == 2)
    reach = reach_boxes(motion, ao)
    assert len(cache.near({0: reach[0]}, motion)[0])  # the first mover marks points before the second fails
    with pytest.raises(ValueError):
        cache.near({0: reach[0], 1: reach[1] * 3}, motion)  # three boxes: the near test refuses them
    got, change = cache.near(reach, motion)
    want, want_change = NearCache(index, nrm, ao, margin=0.25 * ao).near(reach, motion)
    assert len(want)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(change, want_change)


def test_rigid_instance_in_company_only_when_near_another_box():
    static = {1: box([10, 0, 0], [11, 1, 1])}
    lonely = MotionInput({0: box([0, 0, 0], [1, 1, 1])}, {}, rigid=[0], skinned=[])
    assert rigid_in_company(lonely, reach_boxes(lonely, 1.0), static) == []
    near = MotionInput({0: box([8.5, 0, 0], [9.5, 1, 1])}, {}, rigid=[0], skinned=[])
    assert rigid_in_company(near, reach_boxes(near, 1.0), static) == [0]
    left = MotionInput({0: box([0, 0, 0], [1, 1, 1])}, {0: box([8.5, 0, 0], [9.5, 1, 1])}, rigid=[0], skinned=[])
    assert rigid_in_company(left, reach_boxes(left, 1.0), static) == [0]  # it just left: AO changes


def test_bad_camera_sees_everything():
    from psao.server.tick.selection import camera_planes
    pts = random_points(100, seed=4)
    good = camera_planes(look_at((0, 0, 10), (0, 0, 0)), perspective(50.0, 1.0, 0.1, 40.0), 10.0)
    assert good is not None and not in_any_view(pts, [good], 0.0).all()
    nan = np.full((4, 4), np.nan)
    assert camera_planes(nan, perspective(50.0, 1.0, 0.1, 40.0), 10.0) is None
    assert camera_planes(np.eye(4), np.zeros((4, 4)), 10.0) is None
    assert in_any_view(pts, [good, None], 0.0).all()


def test_may_see_sphere_is_conservative():
    """Brute force: from every point the filter rejects, no hemisphere ray of length d meets the sphere;
    and the filter does reject points behind their tangent plane and far away."""
    from psao.server.tick.selection import may_see_sphere
    rng = np.random.default_rng(5)
    centre, radius, d = np.array([0.3, -0.2, 0.5]), 0.8, 1.5
    pts = rng.uniform(-2.5, 2.5, size=(4000, 3))
    nrm = rng.normal(size=(4000, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    outside = np.linalg.norm(pts - centre, axis=1) > radius
    pts, nrm = pts[outside], nrm[outside]
    ok = may_see_sphere(pts, nrm, centre, radius, d)
    assert 0.2 < ok.mean() < 0.8
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for p, n in zip(pts[~ok][:300], nrm[~ok][:300]):
        hemi = np.where((dirs @ n)[:, None] >= 0, dirs, -dirs)
        # ray-sphere: closest approach along each ray within [0, d]
        t = np.clip((centre - p) @ hemi.T, 0.0, d)
        closest = p + t[:, None] * hemi
        assert (np.linalg.norm(closest - centre, axis=1) > radius).all()


@pytest.mark.parametrize("n_views", [1, 2, 7, 40, 70])
def test_union_of_views_equals_each_view_tested(n_views):
    # select_kernels.PriorityKey (through ViewUnion's blocks) tests points against the union of the views by
    # blocks of a box: its visibility must be in_any_view's exactly, also for points on a plane's margin,
    # on block faces and outside the box
    from psao.server.tick.budget import HIDDEN_S, MARGIN_S
    from psao.server.tick.select_kernels import PriorityKey

    rng = np.random.default_rng(n_views)
    cams = [(look_at(rng.uniform(-25, 25, 3), rng.uniform(-8, 8, 3)),
             perspective(rng.uniform(5, 40), 16 / 9, 0.01, rng.uniform(3, 30))) for _ in range(n_views)]
    views = [frustum_planes(v, p, 20.0) for v, p in cams]
    cores = [frustum_planes(v, p, 0.0) for v, p in cams]  # the same views without margins
    margin = 1.0
    pts = [rng.uniform(-30, 30, (6000, 3))]
    for planes in views[:10]:  # on a plane's margin: n.p + d = -margin
        n, d = planes[rng.integers(0, 5, 200), :3], planes[rng.integers(0, 5, 200), 3]
        pts.append(n * (-margin - d)[:, None])
    lo, hi = np.full(3, -20.0), np.full(3, 20.0)
    pts.append(lo + np.round(rng.uniform(0, 12, (500, 3))) * (hi - lo).max() / 12)  # on block faces
    world = np.concatenate(pts)
    n = len(world)
    ids = np.arange(n)
    key = PriorityKey()
    for box in ((lo, hi), (world.min(axis=0), world.max(axis=0)), None):
        got = key(ids, world, world, np.zeros(n, np.int64), np.zeros(n, bool), np.eye(4)[None], np.stack(views), margin,
                  np.zeros(n, np.int32), np.zeros(n), np.zeros(n, np.float32), 0.0, box, np.stack(cores))
        want = in_any_view(world, views, margin)
        assert 0 < want.sum() < n
        np.testing.assert_array_equal(got < HIDDEN_S / 2, want)
        np.testing.assert_array_equal(key.visible, want)  # the visibility it leaves beside the key
        core = want & in_any_view(world, cores, 0.0)
        assert 0 < core.sum() < want.sum()
        np.testing.assert_array_equal(key.core, core)  # and whether in a view without its margins
        np.testing.assert_array_equal(got < MARGIN_S / 2, core)  # those first


def test_in_box_equals_the_plain_test_on_faces_and_nan():
    # in_box (column by column) against all(lo <= p <= hi) over the coordinates, with points on the faces
    rng = np.random.default_rng(4)
    lo, hi = np.array([-1.0, 0.5, 2.0]), np.array([3.0, 0.5, 7.5])  # a flat box: y on its face only
    pts = rng.uniform(-3, 9, (4000, 3))
    pts[::7, 1] = 0.5
    pts[::11, 0] = lo[0]
    pts[::13, 2] = hi[2]
    pts[5, 1] = np.nan
    want = np.all((pts >= lo) & (pts <= hi), axis=1)
    assert 0 < want.sum() < len(pts)
    np.testing.assert_array_equal(in_box(pts, (lo, hi)), want)
    np.testing.assert_array_equal(in_box(pts[:0], (lo, hi)), want[:0])


def test_priority_key_called_again_answers_as_a_fresh_one_and_records_its_launch_once(monkeypatch):
    # PriorityKey keeps its launch recorded on buffers across calls: calls of other sizes (growing and
    # shrinking), views (none, one, several), boxes and changed point data answer as a fresh PriorityKey
    # each time, and wp.launch is called again (the launch recorded anew) only when an array it reads is
    # replaced or grown
    import warp as wp

    from psao.server.tick.select_kernels import PriorityKey

    records = []
    launch = wp.launch

    def counting(*args, **kwargs):
        records.append(kwargs.get("record_cmd", False))
        return launch(*args, **kwargs)

    monkeypatch.setattr(wp, "launch", counting)
    rng = np.random.default_rng(11)
    n = 5000
    world = rng.uniform(-25, 25, (n, 3))
    local = rng.uniform(-1, 1, (n, 3))
    instance = rng.integers(0, 3, n).astype(np.int64)
    moving = instance == 2
    rays = rng.integers(0, 3, n).astype(np.int32)
    since = rng.uniform(0, 10, n)
    change = rng.uniform(0, 1, n).astype(np.float32)
    cameras = [(look_at(rng.uniform(-25, 25, 3), rng.uniform(-8, 8, 3)),
                perspective(rng.uniform(5, 40), 16 / 9, 0.01, rng.uniform(3, 30))) for _ in range(5)]
    views = [frustum_planes(v, p, 20.0) for v, p in cameras]
    cores = [frustum_planes(v, p, 0.0) for v, p in cameras]  # the same views without margins
    kept = PriorityKey()
    for call, (size, cams) in enumerate([(3000, 1), (40, 0), (4500, 5), (700, 2), (4999, 1), (1, 3)]):
        ids = np.sort(rng.choice(n, size, replace=False))
        transforms = np.tile(np.eye(4), (3, 1, 1))
        transforms[2, :3, 3] = rng.uniform(-5, 5, 3)
        planes = np.stack(views[:cams]) if cams else None
        box = (world.min(axis=0), world.max(axis=0)) if call % 2 else None
        since[ids[:10]] += 1.0  # the queue's arrays change in place between ticks
        core = np.stack(cores[:cams]) if cams and call % 3 else None
        args = (ids, world, local, instance, moving, transforms, planes, 0.5, rays, since, change, float(since[ids].min()),
                box, core)
        got = kept(*args)
        fresh = PriorityKey()
        np.testing.assert_array_equal(got, fresh(*args))
        np.testing.assert_array_equal(kept.visible, fresh.visible)
        np.testing.assert_array_equal(kept.core, fresh.core)
        assert 0 < kept.visible.sum() and (cams == 0 or not kept.visible.all()) or size < 50
    recorded, replayed = [], []
    for size in (4999, 3000, 200, 4999):  # the same views: after the largest call, the calls replay the launch
        ids = np.sort(rng.choice(n, size, replace=False))
        args = (ids, world, local, instance, moving, transforms, planes, 0.5, rays, since, change, 0.0, box, core)
        replayed.append((args, kept(*args).copy(), kept.visible.copy()))
        recorded.append(len(records))  # wp.launch calls (each a packing of every argument)
    assert recorded[1:] == recorded[:1] * 3
    for args, got, visible in replayed:  # and the replays answer as a fresh one
        fresh = PriorityKey()
        np.testing.assert_array_equal(got, fresh(*args))
        np.testing.assert_array_equal(visible, fresh.visible)


def test_rows_equals_fancy_indexing_of_rows():
    # psao.server.arrays.rows (np.take along the first axis, for speed) gives a[index] exactly: 2-D and 1-D
    # arrays of several dtypes, repeated, unsorted, negative and empty indices
    from psao.server.arrays import rows

    rng = np.random.default_rng(12)
    for a in (rng.random((500, 3)), rng.random((500, 3)).astype(np.float32), rng.integers(0, 255, (500, 4), np.uint8),
              rng.random(500)):
        for index in (rng.integers(0, 500, 300), np.sort(rng.choice(500, 200, replace=False)), np.arange(-5, 5),
                      np.zeros(0, np.int64)):
            got = rows(a, index)
            assert got.dtype == a.dtype and got.shape == a[index].shape
            np.testing.assert_array_equal(got, a[index])
