"""Which points the server tick re-traces (DESIGN.md, server tick step 3).

A point's AO can only change when geometry within the AO distance of it changes. So a tick re-traces
  - points on deforming (skinned) geometry,
  - points within the AO distance of a moving instance, at its bounds now or at the previous tick
    (the box expanded by the AO distance; the previous box catches the points it has just left),
  - all points of a rigidly moving instance whose expanded box (now or before) touches any other
    instance's box: its points see changed surroundings; alone in space its AO cannot change,
and of those only the points inside some client's extended view (fov widened by a margin in degrees,
planes pushed out by a distance). A point that should have been re-traced but was outside every view is
remembered as stale (by the tick) and re-traced when it comes into view. With no camera known every
point counts as visible.

Static points are found through a block index (points sorted by a coarse world block), so a tick costs
in proportion to the points near moving things, not to the scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from psao.server.arrays import rows
from psao.server.tick.select_constants import INSIDE_CHANGE  # (tests/test_selection.py imports it from here)


# ---------------------------------------------------------------------------------------- views

def frustum_planes(view: np.ndarray, proj: np.ndarray, fov_margin: float = 0.0) -> np.ndarray:
    """(5, 4) world-space planes (a, b, c, d) with unit normals pointing inwards: left, right, bottom,
    top, far (the near plane is left out: points just in front of the eye matter). For a perspective
    projection the field of view is widened by `fov_margin` degrees first (half on each side).
    `view` and `proj` may also be stacks (..., 4, 4): planes (..., 5, 4), one numpy pass for all."""
    p = np.array(proj, np.float64)  # (a copy: widened in place)
    v = np.asarray(view, np.float64)
    if fov_margin:
        persp = (p[..., 3, 2] != 0) & (p[..., 3, 3] == 0)
        for k in (0, 1):  # (where not perspective, worked out and not used: no warning for it)
            with np.errstate(divide="ignore", invalid="ignore"):
                half = np.arctan(1.0 / p[..., k, k]) + np.radians(fov_margin) / 2
                widened = 1.0 / np.tan(np.minimum(half, np.radians(89.0)))
            p[..., k, k] = np.where(persp, widened, p[..., k, k])
    m = p @ v
    r0, r1, r2, r3 = m[..., 0, :], m[..., 1, :], m[..., 2, :], m[..., 3, :]
    planes = np.stack([r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 - r2], axis=-2)
    norms = np.sqrt((planes[..., :3] ** 2).sum(axis=-1, keepdims=True))
    return planes / np.maximum(norms, 1e-300)


def in_frustum(points: np.ndarray, planes: np.ndarray, distance_margin: float = 0.0) -> np.ndarray:
    """Bool (P,): points whose signed distance to every plane is >= -distance_margin."""
    # One multiply-add pass per plane over the coordinates: no `@` (OpenBLAS threads on a (P, 3) x (3, 5)
    # product are ~10x slower on busy cores) and no einsum (4x slower than this for a (P, 3) x (3, 5) product)
    p = np.asarray(points, np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    inside = np.ones(len(p), dtype=bool)
    for a, b, c, d in planes:
        inside &= x * a + y * b + z * c + d >= -distance_margin
    return inside


def camera_planes(view, proj, fov_margin: float) -> np.ndarray | None:
    """frustum_planes of a client's camera, or None (sees everything) for matrices that do not make
    a frustum (not 4x4, not finite, singular): a bad camera costs tracing, never a missed update."""
    return cameras_planes([(view, proj)], fov_margin)[0]


def cameras_planes(cameras, fov_margin: float) -> list[np.ndarray | None]:
    """camera_planes of each (view, projection) pair, worked out in one numpy pass for all."""
    out: list[np.ndarray | None] = [None] * len(cameras)
    rows = [k for k, (v, p) in enumerate(cameras) if np.shape(v) == (4, 4) and np.shape(p) == (4, 4)]
    if not rows:
        return out
    v = np.array([cameras[k][0] for k in rows], np.float64)
    p = np.array([cameras[k][1] for k in rows], np.float64)
    finite = np.isfinite(v).all(axis=(1, 2)) & np.isfinite(p).all(axis=(1, 2))
    with np.errstate(all="ignore"):
        planes = frustum_planes(v, p, fov_margin)
    ok = finite & np.isfinite(planes).all(axis=(1, 2)) & (np.abs(planes[..., :3]).sum(axis=2) > 0.5).all(axis=1)
    for k, pl, good in zip(rows, planes, ok):
        if good:
            out[k] = pl
    return out


def in_any_view(points: np.ndarray, planes_list: list[np.ndarray | None] | None, distance_margin: float) -> np.ndarray:
    """Bool (P,): inside at least one extended frustum; all True when no view is known (None or []) or
    when one of them is None (a camera that could not be turned into a frustum)."""
    if not planes_list or any(pl is None for pl in planes_list):
        return np.ones(len(points), dtype=bool)
    out = np.zeros(len(points), dtype=bool)
    for planes in planes_list:
        todo = np.flatnonzero(~out)
        if len(todo) == 0:
            break
        out[todo] = in_frustum(points[todo], planes, distance_margin)
    return out


# ---------------------------------------------------------------------------------------- boxes

def expand(box: tuple[np.ndarray, np.ndarray], d: float) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(box[0], np.float64) - d, np.asarray(box[1], np.float64) + d


def in_box(points: np.ndarray, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Bool (P,): lo <= point <= hi in every coordinate. Tested column by column into one mask: numpy's
    all(axis=1) over a (P, 3) array costs several times the comparisons (a refill of a mover's nearby
    points tests every point of its box's block rows)."""
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    p = np.asarray(points)
    out = p[:, 0] >= lo[0]
    for k in range(3):
        if k:
            out &= p[:, k] >= lo[k]
        out &= p[:, k] <= hi[k]
    return out


def _ranges(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Concatenation of arange(lo[k], hi[k]) over k, without a Python loop."""
    counts = np.maximum(hi - lo, 0)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return starts + np.arange(total)


def sorted_union(parts: list[np.ndarray]) -> np.ndarray:
    """The sorted distinct values of sorted int arrays (a merge of sorted runs, no hashing)."""
    if not parts:
        return np.zeros(0, np.int64)
    c = np.concatenate(parts)
    c.sort(kind="stable")  # sorted runs: timsort merges them
    return c[np.concatenate([[True], c[1:] != c[:-1]])] if len(c) else c


def sum_by_index(parts: list[np.ndarray], values: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(sorted_union(parts), the values of each index summed over the parts, in float32, in the parts'
    order: ((0 + first) + second) + ...). The plain reference of the tick's merges (merge_disjoint,
    NearCache.near), which are tested equal to it."""
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    c = np.concatenate(parts)
    v = np.concatenate(values).astype(np.float32)
    ids, at = np.unique(c, return_inverse=True)
    total = np.zeros(len(ids), np.float32)
    np.add.at(total, at, v)  # unbuffered, in element order: the parts' order per index
    return ids, total


def merge_disjoint(base: np.ndarray, base_values: np.ndarray | None, runs: list[np.ndarray],
                   run_values: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """sum_by_index([base, *runs], [base_values, *run_values]) (values None: sorted_union alone) when
    `base` (sorted, distinct) and the runs (each sorted, distinct and non-empty) share no index and no
    index of `base` lies within a run's span (a moving instance's points: consecutive ids): each run is
    slotted into `base` whole, with no sort and nothing to sum."""
    if not runs:
        return base, None if base_values is None else np.asarray(base_values, np.float32)
    order = sorted(range(len(runs)), key=lambda k: int(runs[k][0]))
    at = np.searchsorted(base, [int(runs[k][0]) for k in order])
    cuts = np.concatenate([[0], at, [len(base)]])
    ids, vals = [], []
    for j, k in enumerate(order):
        ids += [base[cuts[j]:cuts[j + 1]], runs[k]]
        if base_values is not None:
            vals += [base_values[cuts[j]:cuts[j + 1]], run_values[k]]
    ids.append(base[cuts[-2]:])
    if base_values is None:
        return np.concatenate(ids), None
    vals.append(base_values[cuts[-2]:])
    return np.concatenate(ids), np.concatenate(vals).astype(np.float32)


class BlockIndex:
    """Points (fixed world positions) sorted by a coarse world block, for box queries."""

    def __init__(self, positions: np.ndarray, block: float):
        self.positions = np.asarray(positions, np.float64)
        self.block = float(block)
        if len(self.positions) == 0:
            self.lo = np.zeros(3)
            self.dims = np.ones(3, np.int64)
        else:
            self.lo = self.positions.min(axis=0)
            self.dims = np.floor((self.positions.max(axis=0) - self.lo) / self.block).astype(np.int64) + 1
        keys = self._keys(self._coords(self.positions))
        self.order = np.argsort(keys, kind="stable")
        self.sorted_keys = keys[self.order]
        # the positions in block order: a box's blocks are runs of it, read in sequence rather than
        # gathered from all over the point set
        self.sorted_positions = self.positions[self.order]

    def _coords(self, p: np.ndarray) -> np.ndarray:
        return np.floor((np.asarray(p, np.float64).reshape(-1, 3) - self.lo) / self.block).astype(np.int64)

    def _keys(self, c: np.ndarray) -> np.ndarray:
        return c[:, 0] + self.dims[0] * (c[:, 1] + self.dims[1] * c[:, 2])

    def query_box(self, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Indices (into the positions given at construction) of the points inside the box, unordered."""
        return self.order[self.query_box_sorted(box)]

    def query_box_sorted(self, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """query_box as places in the block order (indices into `sorted_positions` and `order`)."""
        if len(self.positions) == 0:
            return np.zeros(0, np.int64)
        c0 = np.maximum(self._coords(box[0])[0], 0)
        c1 = np.minimum(self._coords(box[1])[0], self.dims - 1)
        if np.any(c1 < c0):
            return np.zeros(0, np.int64)
        nx = c1[0] - c0[0] + 1
        y, z = np.meshgrid(np.arange(c0[1], c1[1] + 1), np.arange(c0[2], c1[2] + 1), indexing="ij")
        # a row of blocks along x is one contiguous key range
        starts = c0[0] + self.dims[0] * (y.ravel() + self.dims[1] * z.ravel())
        lo = np.searchsorted(self.sorted_keys, starts, side="left")
        hi = np.searchsorted(self.sorted_keys, starts + nx, side="left")
        k = _ranges(lo, hi)
        return k[in_box(rows(self.sorted_positions, k), box)]


# ---------------------------------------------------------------------------------------- policy

@dataclass
class MotionInput:
    """What moved this tick, in world space."""
    boxes_now: dict[int, tuple[np.ndarray, np.ndarray]]  # moving instance -> AABB at this tick
    boxes_before: dict[int, tuple[np.ndarray, np.ndarray]]  # moving instance -> AABB at the previous tick
    rigid: list[int]
    skinned: list[int]
    spheres_now: dict[int, tuple[np.ndarray, float]] | None = None  # bounding spheres (centre, radius)
    spheres_before: dict[int, tuple[np.ndarray, float]] | None = None


def may_see_sphere(points: np.ndarray, normals: np.ndarray, centre: np.ndarray, radius: float,
                   ao_distance: float) -> np.ndarray:
    """Bool (P,): can a ray of length ao_distance in the hemisphere about a point's normal reach the
    sphere? Never when the sphere is farther than ao_distance, or wholly behind the point's tangent
    plane (every ray goes into the half-space n . (q - p) >= 0). Conservative: True may still miss."""
    d = np.asarray(centre, np.float64) - points
    dist2 = np.einsum("pi,pi->p", d, d)
    ahead = np.einsum("pi,pi->p", d, np.asarray(normals, np.float64))
    return (dist2 <= (radius + ao_distance) ** 2) & (ahead >= -radius)


def occlusion_change(points: np.ndarray, normals: np.ndarray, spheres: list[tuple[np.ndarray, float]],
                     ao_distance: float) -> np.ndarray:
    """Float (P,): how much a mover's bounding sphere changed its share of each point's cosine-weighted
    hemisphere, |o(now) - o(before)| with spheres [now, before] ([now]: o(now); none: 1, unknown), where
    o = (r / d)^2 max(0, cos angle to the normal), 1 inside the sphere and 0 beyond the AO distance: a
    cheap measure of how much the point's AO may have changed, for the order of re-tracing. A point
    inside the sphere now or before counts at least INSIDE_CHANGE: the mover's surface there (a robot's
    feet over the floor) moves around it while o stays 1."""
    if not spheres:
        return np.ones(len(points))

    def o(c, r):
        d = np.asarray(c, np.float64) - points
        dist = np.sqrt(np.einsum("pi,pi->p", d, d))
        with np.errstate(all="ignore"):
            cos = np.maximum(np.einsum("pi,pi->p", d, np.asarray(normals, np.float64)) / dist, 0.0)
            v = np.minimum((r / dist) ** 2 * cos, 1.0)
        return np.where(dist <= r, 1.0, np.where(dist <= r + ao_distance, v, 0.0)), dist <= r

    now, inside = o(*spheres[0])
    if len(spheres) == 1:
        return now
    before, was_inside = o(*spheres[1])
    change = np.abs(now - before)
    return np.where(inside | was_inside, np.maximum(change, INSIDE_CHANGE), change)


def reach_boxes(motion: MotionInput, ao_distance: float, merge_slack: float = 0.25) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """Per moving instance, its boxes now and before expanded by the AO distance. When the two overlap
    so much that their union box is at most `merge_slack` larger in volume than the two together (the
    usual small step per tick), the union box replaces them: one query instead of two."""
    out = {}
    for i, box in motion.boxes_now.items():
        now = expand(box, ao_distance)
        before = motion.boxes_before.get(i)
        if before is None or (np.array_equal(before[0], box[0]) and np.array_equal(before[1], box[1])):
            out[i] = [now]
            continue
        was = expand(before, ao_distance)
        union = (np.minimum(now[0], was[0]), np.maximum(now[1], was[1]))
        volume = lambda b: float(np.prod(np.maximum(b[1] - b[0], 0.0)))  # noqa: E731
        out[i] = [union] if volume(union) <= (1 + merge_slack) * max(volume(now), volume(was)) else [now, was]
    return out


def rigid_in_company(motion: MotionInput, reach: dict, static_boxes: dict[int, tuple]) -> list[int]:
    """Rigid moving instances whose reach touches another instance's box (static, or moving now)."""
    others = list(static_boxes.items()) + list(motion.boxes_now.items())
    if not others:
        return []
    ids = np.array([j for j, _ in others])
    lo = np.array([b[0] for _, b in others], np.float64)
    hi = np.array([b[1] for _, b in others], np.float64)
    out = []
    for i in motion.rigid:
        for r in reach[i]:
            touch = np.all((r[0] <= hi) & (lo <= r[1]), axis=1) & (ids != i)
            if touch.any():
                out.append(i)
                break
    return out


def static_points_near(index: BlockIndex, reach: dict, motion: MotionInput | None = None,
                       normals: np.ndarray | None = None, ao_distance: float = 0.0) -> np.ndarray:
    """Bool mask over the block index's points: within reach of any moving instance. With the movers'
    bounding spheres (motion) and the points' normals, points that cannot see a mover's sphere now or
    before (may_see_sphere) are left out."""
    out = np.zeros(len(index.positions), dtype=bool)
    for i, boxes in reach.items():
        spheres = []
        if motion is not None and normals is not None and motion.spheres_now:
            spheres = [sp[i] for sp in (motion.spheres_now, motion.spheres_before) if sp and i in sp]
        for b in boxes:
            idx = index.query_box(b)
            if spheres and len(idx):
                p, n = index.positions[idx], normals[idx]
                keep = np.zeros(len(idx), dtype=bool)
                for c, r in spheres:
                    keep |= may_see_sphere(p, n, c, r, ao_distance)
                idx = idx[keep]
            out[idx] = True
    return out


class NearCache:
    """static_points_near over time: the same answer, found among a candidate set kept per mover.

    A mover's reach changes a little from tick to tick, so the block index is queried for its reach
    grown by `margin` (world units; up to four times that for a mover that moves farther per tick), and the candidates (ids, positions and normals, gathered once into
    contiguous arrays in index order; with the movers' spheres, only those within a ball that bounds every point that may
    see them) serve every following tick whose reach stays inside that grown box and ball. Each tick
    then tests only those candidates (in a reach box, may see the mover's sphere now or before: one pass
    of select_kernels.near_kernel), never the block index or the whole point set. The tests mark and sum
    into work arrays over every static point (allocated once, cleared where a tick marked them), so a
    mover's refill touches its own candidates alone; each test lists the points it marked first (in
    index order), and the tick's answer is the merge of those sorted lists."""

    def __init__(self, index: BlockIndex, normals: np.ndarray, ao_distance: float, margin: float):
        self.index = index
        self.normals = np.asarray(normals, np.float64)
        self.sorted_normals = self.normals[index.order]  # in the block order, as index.sorted_positions
        self.ao_distance = float(ao_distance)
        self.margin = float(margin)
        self._held: dict[int, tuple] = {}  # mover -> (query box lo, hi, ball centre, radius, candidate indices,
        # select_kernels.NearTest over their positions and normals)
        self._last: dict[int, tuple] = {}  # mover -> its reach (lo, hi) at the last call
        # per static point: marked by this call's tests, and the movers' change estimates summed (zero again
        # after each call)
        self._hit = np.zeros(len(index.positions), np.uint8)
        self._total = np.zeros(len(index.positions), np.float32)
        self.queries = 0  # block-index queries made (each a cache refill)

    def _candidates(self, i: int, boxes: list[tuple[np.ndarray, np.ndarray]], spheres: list) -> tuple:
        if len(boxes) == 1:
            lo, hi = boxes[0]
        else:
            lo, hi = np.minimum(boxes[0][0], boxes[1][0]), np.maximum(boxes[0][1], boxes[1][1])
        held = self._held.get(i)
        last = self._last.get(i)
        self._last[i] = lo, hi
        # a point that may see a sphere (c, r) is within r + ao of c, so within R of the held ball's
        # centre while |c - centre| + r + ao <= R: the ball bounds the candidates as well as the box
        if held is not None:
            ok = not ((lo < held[0]).any() or (hi > held[1]).any())
            for c, r in spheres if ok else ():
                d = c - held[2]
                if math.sqrt(float(d @ d)) + r + self.ao_distance > held[3]:
                    ok = False
                    break
            if ok:
                return held[4:]
        # grown by the margin, or by a few of the mover's last steps when it moves farther per tick
        # (a slow tick rate): the candidates then still serve several ticks
        step = 0.0 if last is None else float(max(np.abs(lo - last[0]).max(), np.abs(hi - last[1]).max()))
        grow = max(self.margin, min(4.0 * step, 4.0 * self.margin))
        q = (lo - grow, hi + grow)
        k = self.index.query_box_sorted(q)  # block order: positions and normals read in runs
        pos = rows(self.index.sorted_positions, k)
        centre, radius = 0.5 * (lo + hi), np.inf
        if spheres:
            centre = spheres[0][0]
            radius = max(float(np.linalg.norm(c - centre)) + r for c, r in spheres) + self.ao_distance + grow
            d = pos - centre
            # (slack: the per-tick test's own rounding must never reach past the ball)
            ball = np.einsum("pi,pi->p", d, d) <= (radius * (1 + 1e-9)) ** 2
            k, pos = k[ball], np.compress(ball, pos, axis=0)  # (as rows: a mask costs more)
        ids = self.index.order[k]
        by_id = np.argsort(ids)  # sorted by index: what a test marks comes out sorted
        ids, k, pos = ids[by_id], k[by_id], rows(pos, by_id)
        from psao.server.tick.select_kernels import NearTest  # (Warp: imported when something first moves)
        held = self._held[i] = (q[0], q[1], np.asarray(centre, np.float64), radius, ids,
                                NearTest(pos, rows(self.sorted_normals, k), ids, self._hit, self._total))
        self.queries += 1
        return held[4:]

    def near(self, reach: dict, motion: MotionInput, with_change: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Sorted indices (into the block index's points) of static_points_near(index, reach, motion,
        normals, ao_distance), and per index the occlusion_change of the movers' spheres, summed over the
        movers (None without `with_change`: the indices alone, merged without summing)."""
        marked = []
        # sum_by_index of the movers' parts: summed in the movers' order, each mover's test marking and
        # adding in place (select_kernels.near_kernel)
        try:
            for i, boxes in reach.items():
                spheres = [sp[i] for sp in (motion.spheres_now, motion.spheres_before) if sp and i in sp] if motion.spheres_now else []
                test = self._candidates(i, boxes, spheres)[1]
                first = test(boxes, spheres, self.ao_distance)
                if len(first):
                    marked.append(first.copy())
        except BaseException:
            # the movers tested before the failure left marks: a point left marked would never be listed
            # again, so every mark goes (a failure is rare; clearing all of it is cheap beside it)
            self._hit.fill(0)
            self._total.fill(0.0)
            raise
        if not marked:
            return np.zeros(0, np.int64), np.zeros(0, np.float32) if with_change else None
        ids = marked[0] if len(marked) == 1 else np.sort(np.concatenate(marked), kind="stable")  # (sorted runs: merged)
        change = self._total[ids] if with_change else None
        self._hit[ids] = 0
        self._total[ids] = 0.0
        return ids, change
