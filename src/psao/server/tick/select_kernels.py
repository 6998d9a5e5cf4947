"""Warp CPU kernels of the tick's select stage: the per-candidate tests of selection.py in one pass.

`near_kernel` is selection.NearCache's per-tick test (inside one of a mover's reach boxes, and able to
see its bounding sphere now or before: selection.may_see_sphere) over a mover's gathered candidates;
`priority_kernel` is the budgeted tick's priority key over the waiting points (budget.RefineQueue.pick),
with each point's world position and its test against the union of the clients' extended views
(selection.in_any_view; by blocks of space classified once per call, so the test costs about one view's,
not one per client) computed on the way and written out beside the key (the budgeted tick chooses its
whole traces and its rounds from that one pass). They compute in float64 with the numpy versions'
formulas; tests/test_selection.py and tests/test_tick_budget.py check them equal to those.

Numpy would make ~30 passes over each array (one per comparison and logical operation), each with its
own temporary; at a 60 Hz tick over tens of thousands of candidates those passes were most of the tick.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from psao.server.tick.budget import CHANGE_CREDIT_S, CHANGE_S, HIDDEN_S, MARGIN_S, REFINING_S
from psao.server.tick.select_constants import INSIDE_CHANGE

wp.config.quiet = True
HIDDEN = wp.constant(HIDDEN_S)
MARGIN = wp.constant(MARGIN_S)
REFINING = wp.constant(REFINING_S)
CHANGE = wp.constant(CHANGE_S)
CHANGE_CREDIT = wp.constant(CHANGE_CREDIT_S)
INSIDE = wp.constant(INSIDE_CHANGE)
# priority_kernel's verdicts on a block of space against the union of the clients' extended views
UNKNOWN = wp.constant(0)  # not classified yet (this call)
SEEN = wp.constant(1)  # wholly inside some view
UNSEEN = wp.constant(2)  # wholly outside every view
SOME = wp.constant(3)  # cut by some views: its points are tested against those


@wp.func
def in_box(p: wp.vec3d, lo: wp.vec3d, hi: wp.vec3d) -> bool:
    return (p[0] >= lo[0] and p[0] <= hi[0] and p[1] >= lo[1] and p[1] <= hi[1]
            and p[2] >= lo[2] and p[2] <= hi[2])


@wp.func
def may_see(p: wp.vec3d, n: wp.vec3d, c: wp.vec3d, r: wp.float64, ao: wp.float64) -> bool:
    d0 = c[0] - p[0]
    d1 = c[1] - p[1]
    d2 = c[2] - p[2]
    reach = r + ao
    return (d0 * d0 + d1 * d1 + d2 * d2 <= reach * reach) and (d0 * n[0] + d1 * n[1] + d2 * n[2] >= -r)


@wp.func
def occlusion(p: wp.vec3d, n: wp.vec3d, c: wp.vec3d, r: wp.float64, ao: wp.float64) -> wp.float64:
    d0 = c[0] - p[0]
    d1 = c[1] - p[1]
    d2 = c[2] - p[2]
    d = wp.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    o = wp.float64(0.0)
    if d <= r:
        o = wp.float64(1.0)
    elif d <= r + ao:
        o = wp.min(wp.float64(1.0), (r / d) * (r / d) * wp.max(wp.float64(0.0), (d0 * n[0] + d1 * n[1] + d2 * n[2]) / d))
    return o


@wp.func
def inside_sphere(p: wp.vec3d, c: wp.vec3d, r: wp.float64) -> bool:
    d0 = c[0] - p[0]
    d1 = c[1] - p[1]
    d2 = c[2] - p[2]
    return wp.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= r  # (as occlusion's test: the same rounding)


@wp.kernel
def near_kernel(pos: wp.array(dtype=wp.vec3d), nrm: wp.array(dtype=wp.vec3d), q: wp.array(dtype=wp.float64),
                place: wp.array(dtype=wp.int64), hit: wp.array(dtype=wp.uint8), total: wp.array(dtype=wp.float32),
                out: wp.array(dtype=wp.int64), count: wp.array(dtype=wp.int32)):
    # q: box 0 lo, hi, box 1 lo, hi (12), sphere 0 centre, radius, sphere 1 centre, radius (8), AO distance,
    # boxes, spheres. One thread loops over every point: a CPU launch runs its threads one after another,
    # and each thread is a call that copies the arguments. A point that passes is marked in `hit` at its
    # place, and its change added to `total` there (float32, as numpy's +=); a place marked first by this
    # launch is appended to `out` (count[0] of them, in the points' order).
    lo0 = wp.vec3d(q[0], q[1], q[2])
    hi0 = wp.vec3d(q[3], q[4], q[5])
    lo1 = wp.vec3d(q[6], q[7], q[8])
    hi1 = wp.vec3d(q[9], q[10], q[11])
    c0 = wp.vec3d(q[12], q[13], q[14])
    r0 = q[15]
    c1 = wp.vec3d(q[16], q[17], q[18])
    r1 = q[19]
    ao = q[20]
    boxes = int(q[21])
    spheres = int(q[22])
    n = int(0)
    for j in range(pos.shape[0]):
        p = pos[j]
        inside = in_box(p, lo0, hi0)
        if boxes > 1 and not inside:
            inside = in_box(p, lo1, hi1)
        if inside and spheres > 0:
            nj = nrm[j]
            see = may_see(p, nj, c0, r0, ao)
            if spheres > 1 and not see:
                see = may_see(p, nj, c1, r1, ao)
            inside = see
        if inside:
            # selection.occlusion_change: how much the sphere's share of the point's hemisphere changed
            dc = wp.float64(1.0)
            if spheres > 0:
                dc = occlusion(p, nrm[j], c0, r0, ao)
                if spheres > 1:
                    dc = wp.abs(dc - occlusion(p, nrm[j], c1, r1, ao))
                    if inside_sphere(p, c0, r0) or inside_sphere(p, c1, r1):
                        dc = wp.max(dc, wp.float64(INSIDE))
            k = place[j]
            if hit[k] == wp.uint8(0):
                hit[k] = wp.uint8(1)
                out[n] = k
                n = n + 1
            total[k] = total[k] + wp.float32(dc)
    count[0] = wp.int32(n)


class NearTest:
    """near_kernel over one candidate set (positions and normals (P, 3) float64, kept alive here) whose
    places in the work arrays are `places` (int64 (P,), increasing), launched as a recorded command: a
    call writes the boxes and spheres into the launch's parameter array and returns the places it marked
    first (increasing)."""

    def __init__(self, positions: np.ndarray, normals: np.ndarray, places: np.ndarray, hit: np.ndarray,
                 total: np.ndarray):
        self._pos_np = np.ascontiguousarray(positions, np.float64)
        self._nrm_np = np.ascontiguousarray(normals, np.float64)
        self._places = np.ascontiguousarray(places, np.int64)
        self._out = np.empty(len(self._places), np.int64)
        self._count = np.zeros(1, np.int32)
        self.q = np.zeros(23, np.float64)
        self._work = (hit, total)  # (kept alive here)
        self._launch = None
        if len(self._pos_np):
            self._launch = wp.launch(near_kernel, dim=1, device="cpu", record_cmd=True, inputs=[
                wp.array(self._pos_np, dtype=wp.vec3d, device="cpu", copy=False),
                wp.array(self._nrm_np, dtype=wp.vec3d, device="cpu", copy=False),
                wp.array(self.q, dtype=wp.float64, device="cpu", copy=False),
                wp.array(self._places, dtype=wp.int64, device="cpu", copy=False),
                wp.array(hit, dtype=wp.uint8, device="cpu", copy=False),
                wp.array(total, dtype=wp.float32, device="cpu", copy=False),
                wp.array(self._out, dtype=wp.int64, device="cpu", copy=False),
                wp.array(self._count, dtype=wp.int32, device="cpu", copy=False)])

    def __len__(self) -> int:
        return len(self._pos_np)

    def __call__(self, boxes: list[tuple[np.ndarray, np.ndarray]], spheres: list[tuple[np.ndarray, float]],
                 ao_distance: float) -> np.ndarray:
        """Mark the candidates inside one of `boxes` (1 or 2) and, with spheres (at most 2), able to see
        one: hit[place] = 1, and their occlusion change (1 without spheres) added to total[place]. Returns
        the places this call marked that were not marked before (a view, valid until the next call)."""
        if not 1 <= len(boxes) <= 2 or len(spheres) > 2:
            raise ValueError(f"near_kernel tests 1 or 2 boxes and up to 2 spheres, not {len(boxes)} and {len(spheres)}")
        if self._launch is None:
            return self._out[:0]
        q = self.q
        for k, (lo, hi) in enumerate(boxes):
            q[6 * k:6 * k + 3], q[6 * k + 3:6 * k + 6] = lo, hi
        for k, (c, r) in enumerate(spheres):
            q[12 + 4 * k:15 + 4 * k], q[15 + 4 * k] = c, r
        q[20:23] = ao_distance, len(boxes), len(spheres)
        self._launch.launch()
        return self._out[:int(self._count[0])]


@wp.func
def in_camera(p: wp.vec3d, planes: wp.array(dtype=wp.vec4d), c: int, margin: wp.float64) -> bool:
    """selection.in_frustum of one point and camera c's 5 planes (the same sums, in the same order)."""
    for k in range(5):
        pl = planes[c * 5 + k]
        if p[0] * pl[0] + p[1] * pl[1] + p[2] * pl[2] + pl[3] < -margin:
            return False
    return True


@wp.func
def classify_block(b: int, lo: wp.vec3d, size: wp.float64, nx: int, ny: int, planes: wp.array(dtype=wp.vec4d),
                   cameras: int, margin: wp.float64, state: wp.array(dtype=wp.int32), first: wp.array(dtype=wp.int32),
                   count: wp.array(dtype=wp.int32), listed: wp.array(dtype=wp.int32),
                   used: wp.array(dtype=wp.int32)) -> int:
    """The union's verdict for every point of block b: SEEN (wholly inside some camera's extended frustum),
    UNSEEN (wholly outside each), else SOME, with the cameras that cut the block listed (first[b], count[b]).
    The block's box is grown by a millionth of its side and each box test keeps a relative slack: a point
    near a plane, or rounded into the block, is left to the exact per-camera test."""
    z = b / (nx * ny)
    y = (b / nx) % ny
    x = b % nx
    half = wp.float64(0.5) * size
    cx = lo[0] + (wp.float64(x) + wp.float64(0.5)) * size
    cy = lo[1] + (wp.float64(y) + wp.float64(0.5)) * size
    cz = lo[2] + (wp.float64(z) + wp.float64(0.5)) * size
    h = half * wp.float64(1.000001)
    start = used[0]
    n = int(0)
    verdict = int(UNSEEN)
    for c in range(cameras):
        inside = True
        outside = False
        for k in range(5):
            pl = planes[c * 5 + k]
            d = cx * pl[0] + cy * pl[1] + cz * pl[2] + pl[3] + margin
            r = h * (wp.abs(pl[0]) + wp.abs(pl[1]) + wp.abs(pl[2]))
            tol = wp.float64(1e-9) * (wp.abs(cx * pl[0]) + wp.abs(cy * pl[1]) + wp.abs(cz * pl[2]) + wp.abs(pl[3])
                                      + margin + r)
            if d + r < -tol:
                outside = True
            if d - r < tol:
                inside = False
        if inside:
            verdict = int(SEEN)
            n = 0
            break
        if not outside:
            listed[start + n] = c
            n = n + 1
    if verdict != SEEN and n > 0:
        verdict = int(SOME)
    first[b] = start
    count[b] = n
    used[0] = start + n
    state[b] = verdict
    return verdict


@wp.func
def in_union(p: wp.vec3d, planes: wp.array(dtype=wp.vec4d), cameras: int, margin: wp.float64, lo: wp.vec3d,
             size: wp.float64, nx: int, ny: int, nz: int, state: wp.array(dtype=wp.int32),
             first: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), listed: wp.array(dtype=wp.int32),
             used: wp.array(dtype=wp.int32)) -> bool:
    """selection.in_any_view of one point: through its block (nx, ny, nz cubes of side `size` from `lo`;
    none: nx = 0), classified against the views when a point first falls in it; a point outside the
    blocks is tested against every view. No view: every point counts as visible."""
    if cameras == 0:
        return True
    b = int(-1)
    if cameras > 1 and nx > 0 and size > wp.float64(0.0):
        fx = wp.floor((p[0] - lo[0]) / size)
        fy = wp.floor((p[1] - lo[1]) / size)
        fz = wp.floor((p[2] - lo[2]) / size)
        if (fx >= wp.float64(0.0) and fy >= wp.float64(0.0) and fz >= wp.float64(0.0) and fx < wp.float64(nx)
                and fy < wp.float64(ny) and fz < wp.float64(nz)):
            b = (int(fz) * ny + int(fy)) * nx + int(fx)
    if b >= 0:
        verdict = state[b]
        if verdict == UNKNOWN:
            verdict = classify_block(b, lo, size, nx, ny, planes, cameras, margin, state, first, count, listed, used)
        if verdict == SEEN:
            return True
        if verdict == SOME:
            for t in range(count[b]):
                if in_camera(p, planes, listed[first[b] + t], margin):
                    return True
        return False
    for c in range(cameras):
        if in_camera(p, planes, c, margin):
            return True
    return False


@wp.kernel
def priority_kernel(ids: wp.array(dtype=wp.int64), world: wp.array(dtype=wp.vec3d), local: wp.array(dtype=wp.vec3d),
                    instance: wp.array(dtype=wp.int64), moving: wp.array(dtype=wp.bool),
                    transforms: wp.array(dtype=wp.mat44d), planes: wp.array(dtype=wp.vec4d), cameras: int,
                    margin: wp.float64, rays: wp.array(dtype=wp.int32), since: wp.array(dtype=wp.float64),
                    change: wp.array(dtype=wp.float32), base: wp.float64, key: wp.array(dtype=wp.float64),
                    lo: wp.vec3d, size: wp.float64, nx: int, ny: int, nz: int, state: wp.array(dtype=wp.int32),
                    first: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), listed: wp.array(dtype=wp.int32),
                    used: wp.array(dtype=wp.int32), visible: wp.array(dtype=wp.uint8),
                    core_planes: wp.array(dtype=wp.vec4d), core_cameras: int, core_state: wp.array(dtype=wp.int32),
                    core_first: wp.array(dtype=wp.int32), core_count: wp.array(dtype=wp.int32),
                    core_listed: wp.array(dtype=wp.int32), core_used: wp.array(dtype=wp.int32),
                    in_core: wp.array(dtype=wp.uint8), n: int):
    # visibility: in_union (blocks of space classified against the views once per launch), also written out;
    # of the visible points, those in some view without its margins (core_cameras 0: all of them) likewise;
    # the first n of ids (the arrays are buffers kept across calls)
    for j in range(n):
        i = ids[j]
        p = world[i]
        if moving[i]:  # selection's world_positions: the local position through its transform
            m = transforms[instance[i]]
            q = local[i]
            p = wp.vec3d(m[0, 0] * q[0] + m[0, 1] * q[1] + m[0, 2] * q[2] + m[0, 3],
                         m[1, 0] * q[0] + m[1, 1] * q[1] + m[1, 2] * q[2] + m[1, 3],
                         m[2, 0] * q[0] + m[2, 1] * q[1] + m[2, 2] * q[2] + m[2, 3])
        seen = True
        if cameras == 1:  # in_camera written out: a call that takes the planes array costs ~40% of the kernel
            for k in range(5):
                pl = planes[k]
                if p[0] * pl[0] + p[1] * pl[1] + p[2] * pl[2] + pl[3] < -margin:
                    seen = False
        elif cameras > 1:
            seen = in_union(p, planes, cameras, margin, lo, size, nx, ny, nz, state, first, count, listed, used)
        core = seen
        if seen and core_cameras == 1:
            for k in range(5):
                pl = core_planes[k]
                if p[0] * pl[0] + p[1] * pl[1] + p[2] * pl[2] + pl[3] < wp.float64(0.0):
                    core = False
        elif seen and core_cameras > 1:
            core = in_union(p, core_planes, core_cameras, wp.float64(0.0), lo, size, nx, ny, nz, core_state, core_first,
                            core_count, core_listed, core_used)
        tier = wp.float64(0.0)
        visible[j] = wp.uint8(1) if seen else wp.uint8(0)
        in_core[j] = wp.uint8(1) if core else wp.uint8(0)
        if not seen:
            tier = wp.float64(HIDDEN)
        elif not core:
            tier = wp.float64(MARGIN)
        if rays[i] > 0:
            tier = tier + wp.float64(REFINING)
        key[j] = tier + ((since[i] - base) - wp.min(wp.float64(change[i]) * wp.float64(CHANGE), wp.float64(CHANGE_CREDIT)))


class Arrays:
    """Warp views (no copies) of numpy arrays, made again only when an array is replaced."""

    def __init__(self):
        self._held: dict[str, tuple] = {}

    def __call__(self, name: str, arr: np.ndarray, dtype) -> "wp.array":
        held = self._held.get(name)
        if held is None or held[0] is not arr:
            held = self._held[name] = (arr, wp.array(arr, dtype=dtype, device="cpu", copy=False))
        return held[1]


class Buffers:
    """Numpy buffers kept across calls with their Warp views, grown on demand (never shrunk)."""

    def __init__(self):
        self._held: dict[str, tuple] = {}

    def __call__(self, name: str, n: int, np_dtype, wp_dtype, shape=()) -> tuple[np.ndarray, "wp.array"]:
        """(numpy buffer of at least n (and 1) rows of `shape`, its Warp view)."""
        held = self._held.get(name)
        if held is None or len(held[0]) < n:
            a = np.zeros((max(n, 1), *shape), np_dtype)
            held = self._held[name] = (a, wp.array(a, dtype=wp_dtype, device="cpu", copy=False))
        return held


class ViewUnion:
    """The union of the clients' extended views, tested by blocks (in_union): a box around the points is
    cut into cubic blocks (`blocks` along its longest side) and a block is classified once per launch
    against every view (wholly inside one, outside all, or cut by a few), so a point costs a block look-up
    and the views that cut its block, not one test per view; the verdicts equal selection.in_any_view's
    (a point near a block's verdict is tested exactly). Keeps its work arrays across calls."""

    def __init__(self, blocks: int = 12):
        self.blocks = int(blocks)
        self._work = Buffers()

    def _scratch(self, name: str, n: int) -> tuple:
        """(int32 work array of at least n entries, its Warp view), kept across calls (not cleared)."""
        return self._work(name, n, np.int32, wp.int32)

    def inputs(self, planes: np.ndarray | None, margin: float, box: tuple[np.ndarray, np.ndarray] | None,
               points: int) -> tuple[np.ndarray, list]:
        """in_union's arguments for `points` points in `box` (lo, hi; None: no blocks, each view tested)
        and views `planes` ((C, 5, 4), or None: every point visible), with fresh block verdicts: the planes
        as (C * 5, 4) float64 (at least one row), and the arguments after them (cameras ... used)."""
        cams = 0 if planes is None else len(planes)
        flat = np.zeros((1, 4)) if cams == 0 else np.ascontiguousarray(planes, np.float64).reshape(-1, 4)
        lo, size, dims = np.zeros(3), 1.0, (0, 0, 0)
        if box is not None and cams > 1:
            lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
            size = float((hi - lo).max()) / self.blocks
            if np.isfinite(size) and size > 0:
                dims = tuple(int(d) for d in np.minimum(np.floor((hi - lo) / size) + 1, self.blocks))
        n_blocks = int(np.prod(dims))
        state = self._scratch("state", n_blocks)
        state[0][:n_blocks] = 0  # UNKNOWN: classified anew for these views
        used = self._scratch("used", 1)
        used[0][0] = 0  # entries of `listed` taken
        return flat, [cams, wp.float64(margin), wp.vec3d(*lo), wp.float64(size), *dims, state[1],
                      self._scratch("first", n_blocks)[1], self._scratch("count", n_blocks)[1],
                      self._scratch("listed", min(n_blocks, points) * max(cams, 1))[1], used[1]]


class PriorityKey:
    """priority_kernel over a tick's point arrays: world positions of static points, local positions
    (moving points), instance and moving flag per point id; visibility by ViewUnion's blocks of `box`.
    The launch is recorded once on buffers kept across calls (the ids, transforms and planes are copied in,
    the keys copied out) and the point arrays given, and recorded again only when one of those is replaced
    or grown: packing the kernel's arguments and wrapping its arrays cost more than the kernel over a few
    thousand points."""

    def __init__(self, blocks: int = 12):
        self.views = Arrays()
        self.union = ViewUnion(blocks)
        self.core_union = ViewUnion(blocks)
        self.buffers = Buffers()
        self.visible = np.zeros(0, bool)  # the last call's in_any_view per id (the key's visibility tier)
        self.core = np.zeros(0, bool)  # the last call's in_any_view of the views without margins per id
        self._launch = None  # priority_kernel recorded on the arrays of `_on`
        self._on: tuple = ()

    def __call__(self, ids: np.ndarray, world: np.ndarray, local: np.ndarray, instance: np.ndarray,
                 moving: np.ndarray, transforms: np.ndarray, planes: np.ndarray | None, margin: float,
                 rays: np.ndarray, since: np.ndarray, change: np.ndarray, base: float,
                 box: tuple[np.ndarray, np.ndarray] | None = None, core_planes: np.ndarray | None = None) -> np.ndarray:
        """Priority key (float64, per id; smaller first): RefineQueue.key with each point's visibility
        in_any_view of its world position, and its place in the views' cores: in_any_view of `core_planes`
        (the same views without their margins, (C, 5, 4) float64, distance margin 0; None: every visible
        point). `planes`: (C, 5, 4) float64, or None (every point visible); `box` (lo, hi): where the points
        are (world), for the unions' blocks (None: each view is tested). Each id's visibility is left in
        `visible`, and whether it is in a core in `core`."""
        n = len(ids)
        if n == 0:
            self.visible, self.core = np.zeros(0, bool), np.zeros(0, bool)
            return np.empty(0, np.float64)
        v, b = self.views, self.buffers
        flat, union = self.union.inputs(planes, margin, box, n)
        core_flat, core = self.core_union.inputs(core_planes if planes is not None else None, 0.0, box, n)
        ids_np, ids_wp = b("ids", n, np.int64, wp.int64)
        key_np, key_wp = b("key", n, np.float64, wp.float64)
        seen_np, seen_wp = b("seen", n, np.uint8, wp.uint8)
        in_core_np, in_core_wp = b("in_core", n, np.uint8, wp.uint8)
        tr_np, tr_wp = b("transforms", len(transforms), np.float64, wp.mat44d, (4, 4))
        planes_np, planes_wp = b("planes", len(flat), np.float64, wp.vec4d, (4,))
        core_np, core_wp = b("core_planes", len(core_flat), np.float64, wp.vec4d, (4,))
        ids_np[:n] = ids
        tr_np[:len(transforms)] = transforms
        planes_np[:len(flat)] = flat
        core_np[:len(core_flat)] = core_flat
        args = [ids_wp, v("world", world, wp.vec3d), v("local", local, wp.vec3d), v("instance", instance, wp.int64),
                v("moving", moving, wp.bool), tr_wp, planes_wp, *union[:2], v("rays", rays, wp.int32),
                v("since", since, wp.float64), v("change", change, wp.float32), wp.float64(base), key_wp,
                *union[2:], seen_wp, core_wp, core[0], *core[7:], in_core_wp, n]
        arrays = tuple(a for a in args if isinstance(a, wp.array))
        if self._launch is None or len(arrays) != len(self._on) or any(a is not h for a, h in zip(arrays, self._on)):
            self._launch = wp.launch(priority_kernel, dim=1, device="cpu", inputs=args, record_cmd=True)
            self._on = arrays
        else:
            for k, a in enumerate(args):
                if not isinstance(a, wp.array):  # the scalars: views, margin, base, blocks, n
                    self._launch.set_param_at_index(k, a)
        self._launch.launch()
        self.visible, self.core = seen_np[:n].view(bool).copy(), in_core_np[:n].view(bool).copy()
        return key_np[:n].copy()
