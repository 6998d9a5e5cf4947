"""Densify: more points where the AO varies faster than the even sampling follows.

Weighted sample elimination spreads points evenly by area (paper section 3.1), so a moulding, a column's
fluting or the foot of a wall, whose AO changes within one lookup radius, gets as few points as a flat
open floor, and small faces get none of their own. There the lookup (paper eq. 2-4) blends points whose
AO differs from the fragment's. After the bake's first trace this stage draws a pool of candidate points
over each instance it applies to (uniform by area, `ratio` per kept point, none on buried surfaces),
leaves out the quiet ones (below), traces the rest once, and in each of `rounds` rounds adds the candidates where the client's lookup over the
current grid (psao.protocol.reconstruct, the shader's oracle) misses the candidate's traced AO by more than
`threshold`: largest misses first, no two added in one round closer than `spacing` lookup radii. Each
round looks at the candidates not yet added against the grid the last round left.

A candidate is quiet where the lookup cannot be far off: a kept point of its own face (the lookup's first
step: normal within FIRST_T_N, offset within FIRST_T_D) lies within r, and the traced AO of every kept
point within `quiet_reach` lookup radii spans at most `quiet_spread`. The lookup blends points of those
AO values, so there it misses only detail that falls between all of them. Most of an open scene is quiet
(Sponza, busy with mouldings: about half of the candidates), and tracing the rest is what densify costs.

The grid keeps its radius and cells: added points go into the cells of their keys (a key takes up to
KEY_CELLS cells). A candidate whose key has no room left is not added, so densifying never drops a
point. The client's lookup is unchanged; it only finds more points where the AO varies.

It needs AO precise enough to tell variation from noise: below `min_rays` rays per point (the server's
quick first traces, which the tick refines later) it does not run. It applies to static one-sided
instances: what varies at rest may not where an instance moves, and a double-sided instance would need
each addition on both sides.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from psao.protocol import pointword as pw
from psao.protocol.reconstruct import reconstruct_ao
from psao.protocol.gridformat import in_first_step
from psao.scene.model import Scene
from psao.server.geometry import scene_point_ids, to_world
from psao.server.points.buried import is_static
from psao.server.points.gapfill import Candidates, append_points, surface_candidates, thin, visible_candidates
from psao.server.grid import NO_POINT, Grid
from psao.server.points.generate import PointSet
from psao.server.settings import DensifySettings, TraceSettings
from psao.server.tracer.grid_trace import trace_grid_points

# Stable ids of the candidates while they are traced and looked at (the ids of probes start at 2^30):
# decorrelated rays, apart from every point's and probe's. Added points get their final ids afterwards.
POOL_ID_BASE = 3 << 30
# Candidates per call of the lookup's oracle: its arrays grow with a chunk's fragments times the points of
# their 2x2x2 blocks (fandisk's bake peaked at 683 MB with the oracle's default of 65,536, at 400 MB with
# this; 330 MB without densify).
ORACLE_CHUNK = 16384
# Candidates per k-d query of the quiet test, and the nearest kept points it looks at per candidate
# (about 10 lie within 1.5 r on a flat face).
QUIET_CHUNK = 131072
QUIET_NEIGHBOURS = 16


@dataclass
class Pool:
    """One instance's traced candidates."""

    instance: int
    cand: Candidates
    ao_code: np.ndarray  # (C,) uint32, traced visibility quantised as the grid stores it
    ids: np.ndarray  # (C,) int64, the ids they were traced with
    open: np.ndarray  # (C,) bool: neither added nor refused for want of room yet
    stale: np.ndarray  # (C,) bool: the grid changed near it since the lookup was last asked there


def applies(scene: Scene, i: int) -> bool:
    return is_static(scene, i) and not scene.meshes[scene.instances[i].mesh].double_sided


def draw_pools(scene: Scene, pointsets: list[PointSet], grid: Grid, settings: DensifySettings, buried=None) -> list[Pool]:
    """Untraced candidate pools of the instances densify applies to, quiet candidates left out."""
    rng = np.random.default_rng(settings.seed)
    pools, next_id = [], POOL_ID_BASE
    table = grid.point_table()
    for i, ps in enumerate(pointsets):
        if not applies(scene, i) or len(ps) == 0:
            continue
        cand = surface_candidates(scene, i, settings.ratio, len(ps), rng)
        mine = table.instance == i  # the quiet test first: it is cheaper than the buried one
        cand = cand.subset(~quiet(table.local_pos[mine], table.local_normal[mine], pw.dequantise_ao(table.ao_code[mine]),
                                  cand.local_pos, cand.local_normal, float(grid.instances[i]["radius"]), settings))
        if buried is not None and buried.applies_to(i):
            cand = visible_candidates(cand, buried, scene.instances[i].transform)
        n = len(cand.faces)
        pools.append(Pool(i, cand, np.zeros(n, np.uint32), np.arange(next_id, next_id + n, dtype=np.int64),
                          np.ones(n, bool), np.ones(n, bool)))
        next_id += n
    return pools


def quiet(points_pos: np.ndarray, points_nrm: np.ndarray, points_ao: np.ndarray, pos: np.ndarray, nrm: np.ndarray,
          radius: float, settings: DensifySettings) -> np.ndarray:
    """Bool (C,): a kept point of each candidate's own face lies within `radius` (r), and the AO of the kept
    points within settings.quiet_reach * r (the QUIET_NEIGHBOURS nearest) spans at most settings.quiet_spread."""
    out = np.zeros(len(pos), bool)
    if len(points_pos) == 0 or len(pos) == 0 or settings.quiet_spread <= 0:
        return out
    tree = cKDTree(points_pos)
    k = min(QUIET_NEIGHBOURS, len(points_pos))
    for s in range(0, len(pos), QUIET_CHUNK):
        x, n = pos[s:s + QUIET_CHUNK], nrm[s:s + QUIET_CHUNK]
        dist, idx = tree.query(x, k=k, distance_upper_bound=settings.quiet_reach * radius, workers=-1)
        dist, idx = dist.reshape(len(x), k), idx.reshape(len(x), k)
        found = idx < len(points_pos)
        safe = np.where(found, idx, 0)
        ao = points_ao[safe]
        spread = np.where(found, ao, -np.inf).max(axis=1) - np.where(found, ao, np.inf).min(axis=1)
        n_p = points_nrm[safe]
        d_vec = points_pos[safe] - x[:, None, :]
        ddot = np.einsum("ckj,ckj->ck", n_p, d_vec)
        dist2 = np.einsum("ckj,ckj->ck", d_vec, d_vec)
        own = found & in_first_step(np.einsum("ckj,cj->ck", n_p, n), ddot, dist2, radius)
        out[s:s + len(x)] = own.any(axis=1) & (spread <= settings.quiet_spread)
    return out


def trace_pools(pools: list[Pool], scene: Scene, tracer, trace_settings: TraceSettings) -> None:
    """Trace every pool's candidates in one call (fills Pool.ao_code)."""
    if not pools:
        return
    world = [to_world(scene.instances[p.instance].transform, p.cand.local_pos, p.cand.local_normal) for p in pools]
    vis = tracer.visibility(np.concatenate([w[0] for w in world]), np.concatenate([w[1] for w in world]),
                            np.concatenate([p.ids for p in pools]), trace_settings)
    codes = pw.quantise_ao(vis)
    first = 0
    for p in pools:
        p.ao_code = codes[first:first + len(p.ids)].astype(np.uint32)
        first += len(p.ids)


def densify_round(grid: Grid, pools: list[Pool], settings: DensifySettings) -> list[np.ndarray]:
    """One round: per pool, the indices of the candidates it inserted into the grid (with their traced AO
    and pool ids). Candidates without room in their key's cells are closed, not counted as drops. Only
    candidates whose lookup can have changed since the last round are asked again (the lookup reads the
    cells within one of the fragment's own, so a candidate no added point came near keeps its answer)."""
    added = []
    for p in pools:
        idx = np.flatnonzero(p.open & p.stale)
        p.stale[:] = False
        if len(idx) == 0:
            added.append(idx)
            continue
        c = p.cand
        ao, _ = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.full(len(idx), p.instance),
                               c.local_pos[idx], c.local_normal[idx], chunk=ORACLE_CHUNK,
                               back=np.zeros(len(idx), bool))  # one-sided: the front keys alone, half the scan
        miss = np.abs(ao - pw.dequantise_ao(p.ao_code[idx]))
        over = miss > settings.threshold
        pick = idx[over][np.argsort(-miss[over], kind="stable")]  # thin keeps the first of each close pair
        pick = pick[thin(c.local_pos[pick], settings.spacing * float(grid.instances[p.instance]["radius"]))]
        stats = grid.stats
        before = (stats.dropped_cell_full, stats.dropped_bucket_full, stats.dropped_outside)
        kept = grid.insert_points(p.instance, c.local_pos[pick], c.local_normal[pick], p.ao_code[pick], p.ids[pick])
        stats.dropped_cell_full, stats.dropped_bucket_full, stats.dropped_outside = before  # not added, not dropped
        p.open[pick] = False
        added.append(pick[kept])
        p.stale |= near_cells(grid, p.instance, c.local_pos, c.local_pos[pick[kept]])
    return added


def near_cells(grid: Grid, inst: int, pos: np.ndarray, added: np.ndarray) -> np.ndarray:
    """Bool (len(pos),): positions whose cell is within one cell (each axis) of an added point's cell."""
    if len(added) == 0:
        return np.zeros(len(pos), bool)
    dims = grid.instances[inst]["dims"].astype(np.int64)
    cell, _ = grid.cell_of(inst, added)
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    around = (cell[:, None, :] + offsets[None]).reshape(-1, 3)
    touched = np.unique(around[:, 0] + dims[0] * (around[:, 1] + dims[1] * around[:, 2]))
    mine, _ = grid.cell_of(inst, pos)
    return np.isin(mine[:, 0] + dims[0] * (mine[:, 1] + dims[1] * mine[:, 2]), touched)


def densify(scene: Scene, pointsets: list[PointSet], grid: Grid, tracer, trace_settings: TraceSettings,
            settings: DensifySettings, buried=None, progress=None) -> tuple[list[PointSet], int]:
    """Densify a traced grid in place; returns the point sets with the added points appended (per instance,
    after its own) and how many were added. The grid's point ids are renumbered to match
    (geometry.scene_point_ids of the returned sets) and the points whose id changed (every added one, and the
    points of later instances) are traced again, so every point's AO comes from the rays of its own id,
    as the server's later traces of it do."""
    pools = draw_pools(scene, pointsets, grid, settings, buried)
    trace_pools(pools, scene, tracer, trace_settings)
    chosen = [np.zeros(0, np.int64) for _ in pools]
    for k in range(settings.rounds):
        picks = densify_round(grid, pools, settings)
        chosen = [np.concatenate([c, a]) for c, a in zip(chosen, picks)]
        if progress is not None:
            progress(k + 1, settings.rounds)
        if sum(len(a) for a in picks) == 0:
            break
    old_ids = scene_point_ids(pointsets)
    out = list(pointsets)
    traced_with = list(old_ids)
    for p, sel in zip(pools, chosen):
        if len(sel):
            out[p.instance] = append_points(pointsets[p.instance], p.cand, sel, None)
            traced_with[p.instance] = np.concatenate([old_ids[p.instance], p.ids[sel]])
    old, new = np.concatenate(traced_with), np.concatenate(scene_point_ids(out))
    renumber(grid, old, new)
    trace_grid_points(grid, scene, tracer, trace_settings, point_ids=new[old != new])
    return out, int(sum(len(s) for s in chosen))


def renumber(grid: Grid, old: np.ndarray, new: np.ndarray) -> None:
    """Give the grid's points the ids `new` in place of `old` (every stored id appears once in `old`)."""
    used = grid.point_id != NO_POINT
    order = np.argsort(old)
    where = np.searchsorted(old[order], grid.point_id[used])
    grid.point_id[used] = new[order[where]]
