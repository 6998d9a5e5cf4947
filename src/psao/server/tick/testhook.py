"""Random grid edits for tests (`psao serve --test-edits K`): AO changes, moves, frees and allocations.

Both are ticks on the service's event loop (psao.server.tick.base.Tick: `tick(grid, t) -> None`) and edit the grid only
through its public edit API, so everything the streaming layer sees (dirty cells and buckets, cells
allocated and freed, capacity growth) is what real ticks produce.

- `RandomEdits`: each tick, k points around a random point of a random instance: most get a new AO
  value, some move (many leave their cell: cells are freed and allocated), some are removed and new
  points inserted nearby. For the streaming tests (`psao serve --test-edits K`).
- `MovingOccluder`: a sphere travels through the scene on a closed loop and darkens the AO of the points
  within its reach, smoothly with distance; points it has left return to their baked AO. Spatially and
  temporally coherent like a real moving occluder, so it stands in for the animated courtyard in the
  bandwidth benchmark.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.scene.model import Scene
from psao.protocol import gridformat as gf
from psao.server.grid import NO_POINT, Grid, PointTable
from psao.server.tick.base import Tick


@dataclass
class EditMix:
    ao: float = 0.7  # fraction of the k points whose AO changes
    move: float = 0.2  # fraction moved by about a cell (most leave their cell)
    replace: float = 0.1  # fraction removed, with as many new points inserted nearby


def _cluster(grid: Grid, rng: np.random.Generator, k: int):
    """A point table of the points around one random point and the indices in it of the k points of the
    same instance nearest to that point (ties in point order).

    Only the cells within a box of R cells around the seed's cell are read, R doubling until the k-th
    nearest distance is shorter than R - 1 cells (every point closer lies inside the box then): the
    same points as a search over the whole grid, at a cost that follows k rather than the grid (the hook
    runs on the server's event loop every tick)."""
    occupied = grid.point_id != NO_POINT
    flat = np.flatnonzero(occupied)
    if len(flat) == 0:
        return grid.point_table(), np.zeros(0, np.int64)
    seed_slot, seed_index = divmod(int(flat[int(rng.integers(len(flat)))]), gf.POINTS_PER_CELL)
    inst = int(grid.cell_instance[seed_slot])
    rec = grid.instances[inst]
    cells = np.flatnonzero((grid.cell_instance == inst) & occupied[:, 0])  # a cell's points come first
    offset = np.abs(gf.key_to_cell(grid.cells[cells, gf.KEY_WORD], rec["dims"])
                    - gf.key_to_cell(grid.cells[seed_slot, gf.KEY_WORD], rec["dims"]))
    reach = np.maximum(np.maximum(offset[:, 0], offset[:, 1]), offset[:, 2])  # cells, along the farthest axis
    seed_pos = grid.point_local[seed_slot, seed_index]
    size = float(rec["cell_size"])
    r = 2
    while True:
        box = cells[reach <= r]  # ascending slots: point order as in the whole grid's table
        rows, index = np.nonzero(occupied[box])
        slot = box[rows]
        d = np.linalg.norm(grid.point_local[slot, index] - seed_pos, axis=1)
        near = np.argsort(d, kind="stable")[:k]
        if len(box) == len(cells) or (len(near) == k and (k == 0 or d[near[-1]] < (r - 1) * size)):
            break
        r *= 2
    table = PointTable(slot=slot.astype(np.uint32), index=index.astype(np.int64), instance=grid.cell_instance[slot],
                       point_id=grid.point_id[slot, index], local_pos=grid.point_local[slot, index],
                       local_normal=grid.point_normal[slot, index], ao_code=grid.cells[slot, index] & np.uint32(0xFF))
    return table, near


def _inside(grid: Grid, inst: int, pos: np.ndarray) -> np.ndarray:
    """Clamp local positions into the instance's grid box (a cell-size hundredth inside its faces)."""
    rec = grid.instances[inst]
    s = float(rec["cell_size"])
    lo = rec["origin"].astype(np.float64) + 0.01 * s
    hi = rec["origin"].astype(np.float64) + rec["dims"].astype(np.float64) * s - 0.01 * s
    return np.clip(pos, lo, hi)


class RandomEdits(Tick):
    def __init__(self, k: int, seed: int = 0, mix: EditMix | None = None):
        self.k = int(k)
        self.rng = np.random.default_rng(seed)
        self.mix = mix or EditMix()

    def __call__(self, grid: Grid, t: float) -> None:
        random_edits(grid, self.rng, self.k, self.mix)


def random_edits(grid: Grid, rng: np.random.Generator, k: int, mix: EditMix | None = None) -> None:
    mix = mix or EditMix()
    if k <= 0:
        return
    # AO changes: a smooth bump around the cluster centre, plus noise.
    table, near = _cluster(grid, rng, max(1, int(round(k * mix.ao))))
    if len(near):
        ao = table.ao_code[near].astype(np.int64) + rng.integers(-40, 41, len(near))
        grid.set_ao(table.slot[near], table.index[near], np.clip(ao, 0, 255).astype(np.uint32))
    # Moves: about one cell in a random direction; the point keeps its AO and id.
    table, near = _cluster(grid, rng, int(round(k * mix.move)))
    if len(near):
        inst = int(table.instance[near[0]])
        s = float(grid.instances[inst]["cell_size"])
        new_pos = _inside(grid, inst, table.local_pos[near] + rng.normal(scale=0.8 * s, size=(len(near), 3)))
        grid.move_points(table.slot[near], table.index[near], new_pos, table.local_normal[near])
    # Replacements: remove points, insert as many new ones scattered around where they were.
    table, near = _cluster(grid, rng, int(round(k * mix.replace)))
    if len(near):
        inst = int(table.instance[near[0]])
        s = float(grid.instances[inst]["cell_size"])
        pos = _inside(grid, inst, table.local_pos[near] + rng.normal(scale=2.0 * s, size=(len(near), 3)))
        normals = table.local_normal[near].copy()
        grid.remove_points(table.slot[near], table.index[near])
        first_id = int(grid.point_id.max()) + 1
        ids = np.arange(first_id, first_id + len(near))
        grid.insert_points(inst, pos, normals, rng.integers(0, 256, len(near)).astype(np.uint32), ids)


class MovingOccluder(Tick):
    """A sphere of radius `radius` (world units) on a closed loop through the scene. It only changes AO,
    so the points' slots never change and their world positions are computed once."""

    def __init__(self, scene: Scene, grid: Grid, radius: float | None = None, period: float = 8.0,
                 threshold: int = 2):
        lo, hi = scene.world_bounds()
        self.center = 0.5 * (lo + hi)
        self.extent = 0.35 * (hi - lo)
        self.floor = lo[1]
        self.radius = float(radius if radius is not None else 2.0 * scene.ao_distance)
        self.period = float(period)
        self.threshold = int(threshold)  # AO codes: smaller changes are not sent (the server's threshold)
        self.slot, self.index = np.nonzero(grid.point_id != NO_POINT)
        self.baked = (grid.cells[self.slot, self.index] & 0xFF).astype(np.float64)  # AO before the sphere
        inst = grid.cell_instance[self.slot]
        local = grid.point_local[self.slot, self.index]
        self.world = np.empty_like(local)
        for i, sc_inst in enumerate(scene.instances):
            sel = inst == i
            m = np.asarray(sc_inst.transform, np.float64)
            self.world[sel] = local[sel] @ m[:3, :3].T + m[:3, 3]

    def position(self, t: float) -> np.ndarray:
        a = 2 * np.pi * t / self.period
        return np.array([self.center[0] + self.extent[0] * np.cos(a), self.floor + self.radius,
                         self.center[2] + self.extent[2] * np.sin(2 * a)])

    def __call__(self, grid: Grid, t: float) -> None:
        d = np.linalg.norm(self.world - self.position(t), axis=1)
        # Baked AO, darkened near the sphere: most at its surface, none beyond 2 radii.
        shade = np.clip(1.0 - (d - self.radius) / self.radius, 0.0, 1.0) ** 2
        ao = np.rint(self.baked * (1.0 - 0.8 * shade)).astype(np.int64)
        current = (grid.cells[self.slot, self.index] & 0xFF).astype(np.int64)
        # Like the server tick: a point is updated when its AO moved by at least the threshold, or
        # when it reaches its target exactly (so AO settles back to the baked value once the sphere left).
        go = (np.abs(ao - current) >= self.threshold) | ((ao == self.baked) & (ao != current))
        grid.set_ao(self.slot[go], self.index[go], ao[go].astype(np.uint32))
