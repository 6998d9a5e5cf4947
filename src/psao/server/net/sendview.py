"""Which grid cells lie in a client's extended view: the test behind per-client culling of sends.

A client's extended view is the frustum of its last camera widened as the tick's view selection widens
it (settings.ViewSettings: field-of-view margin in degrees, planes pushed out by a distance margin),
tested against each cell's centre in world space with the margin grown by the cell's half diagonal, so
a cell any part of which is in the extended view counts as in it. Cells whose place is unknown (free
slots, slots without an instance) are always in view: sending them costs little and a freed cell must
reach the mirror like any other change.
"""
from __future__ import annotations

import numpy as np

from psao.protocol import gridformat as gf

from psao.server.tick.selection import camera_planes, cameras_planes
from psao.server.settings import ViewSettings

BLOCK = 1 << 16  # (camera, cell) pairs a plane test works on at once: each temporary a few MB


class CellPlaces:
    """World-space centres and reach (half diagonal) of a set of cell slots under given transforms. After
    `defer` (instances moved) a row's attributes are current once it is settled: the plane tests settle
    the rows they test, `settle()` all of them."""

    def __init__(self, grid, slots: np.ndarray, transforms: np.ndarray):
        slots = np.asarray(slots, np.int64)
        n = len(slots)
        # where each slot's cell is in its instance's space (owner -1: a slot whose place is unknown)
        self.owner = np.full(n, -1, np.int64)
        self.local = np.zeros((n, 3))
        self.half_diagonal = np.zeros(n)  # in the instance's units
        inst = grid.cell_instance[slots] if n else np.zeros(0, np.int64)
        keys = grid.cells[slots, gf.KEY_WORD] if n else np.zeros(0, np.uint32)
        self.key = np.array(keys, np.uint32)  # the cell key each place was worked out from
        placed = np.flatnonzero((inst >= 0) & (keys != gf.EMPTY))
        placed = placed[np.argsort(inst[placed], kind="stable")]
        owners, starts = np.unique(inst[placed], return_index=True)
        for i, rows in zip(owners, np.split(placed, starts[1:])):
            rec = grid.instances[i]
            xyz = gf.key_to_cell(keys[rows], rec["dims"])
            self.local[rows] = rec["origin"].astype(np.float64) + (xyz + 0.5) * float(rec["cell_size"])
            self.half_diagonal[rows] = 0.5 * np.sqrt(3.0) * float(rec["cell_size"])
            self.owner[rows] = i
        self.centres = np.full((n, 3), np.nan)
        self.reach = np.zeros(n)
        # The same, laid out for in_view (it runs per client and send): coordinates as 3 rows, 0 where the
        # place is unknown, and the slack each plane test allows, infinite where unknown (always in view).
        self.xyz = np.zeros((3, n))
        self.slack = np.full(n, np.inf)
        # Rows whose instance moved (`defer`) are placed again, under the latest transforms, only when they
        # are next tested (`settle`): a tick tests a few cells, its dirty ones. Versions tell which: per
        # instance the defer that last moved it (the extra last entry: owner -1, never moves), per row the
        # version it was placed at.
        self.version = 0
        self.moved_at = np.zeros(len(transforms) + 1, np.int64)
        self.placed_at = np.zeros(n, np.int64)
        self.matrices = np.array(transforms, np.float64)
        self.stretch = _stretch(self.matrices)
        self._place(placed)

    def _place(self, rows: np.ndarray) -> None:
        """World centres and reach of these rows (slots with a known place) under the latest transforms:
        what an instance's move changes (its cells' places in its own space stay)."""
        if not len(rows):
            return
        at = self.owner[rows]
        m = self.matrices[at]  # each row's instance's
        loc = self.local[rows]
        # per coordinate multiply-adds (no einsum, no BLAS): the same numbers however many rows
        world = loc[:, 0:1] * m[:, :3, 0] + loc[:, 1:2] * m[:, :3, 1] + loc[:, 2:3] * m[:, :3, 2] + m[:, :3, 3]
        self.centres[rows] = world
        self.xyz[:, rows] = world.T
        self.reach[rows] = self.slack[rows] = self.half_diagonal[rows] * self.stretch[at]
        self.placed_at[rows] = self.version

    def defer(self, instances: np.ndarray, transforms: np.ndarray) -> None:
        """These instances moved (`transforms`: every instance's now): their cells are placed again when
        they are next tested."""
        self.version += 1
        self.moved_at[instances] = self.version
        self.matrices = np.array(transforms, np.float64)
        self.stretch = self.stretch.copy()
        self.stretch[instances] = _stretch(self.matrices[instances])

    def settle(self, rows: np.ndarray | None = None) -> None:
        """Place the rows among these (all: None) whose instance moved since they were placed."""
        rows = np.arange(len(self.owner)) if rows is None else np.asarray(rows, np.int64)
        self._place(rows[self.placed_at[rows] < self.moved_at[self.owner[rows]]])

    def refresh(self, grid, slots: np.ndarray, transforms: np.ndarray) -> None:
        """Work the places of these slots out again where their cell changed (another key or instance:
        a cell whose AO alone changed keeps its place); the slots here are all of the grid's, 0..n-1."""
        slots = np.asarray(slots, np.int64)
        inst, keys = grid.cell_instance[slots], grid.cells[slots, gf.KEY_WORD]
        owner = np.where((inst >= 0) & (keys != gf.EMPTY), inst, -1)
        slots = slots[(owner != self.owner[slots]) | (keys != self.key[slots])]
        if not len(slots):
            return
        part = CellPlaces(grid, slots, transforms)
        for name in ("owner", "local", "half_diagonal", "centres", "reach", "slack", "key"):
            getattr(self, name)[slots] = getattr(part, name)
        self.xyz[:, slots] = part.xyz
        self.placed_at[slots] = self.version  # (placed under `transforms`: the latest)

    def in_view(self, planes: np.ndarray | None, view: ViewSettings, rows: np.ndarray | None = None) -> np.ndarray:
        """Bool per slot (or per one of `rows`, indices into the slots): in the extended view of a camera's
        planes (None: a camera that sees all). A cell is in when, for every plane, its centre's signed
        distance is at least -(distance margin + reach); a slot whose place is unknown always is."""
        if planes is None:
            return np.ones(len(self.slack) if rows is None else len(rows), dtype=bool)
        return self.in_views(planes[None], view, rows)[0]

    def in_views(self, planes: np.ndarray, view: ViewSettings, rows: np.ndarray | None = None) -> np.ndarray:
        """in_view for several cameras' planes (C, 5, 4) at once: bool (C, slots or rows), in blocks of
        cameras and rows of about BLOCK pairs each (the plane test's temporaries stay a few MB however many
        clients and cells)."""
        self.settle(rows)
        n = len(self.slack) if rows is None else len(rows)
        out = np.empty((len(planes), n), bool)
        step = max(1, BLOCK // max(1, len(planes)))  # rows a block: every camera at once where they fit
        cams = max(1, BLOCK // max(1, min(step, n)))
        for lo in range(0, n, step):
            at = slice(lo, lo + step) if rows is None else rows[lo:lo + step]
            xyz, slack = self.xyz[:, at], self.slack[at]
            for c0 in range(0, len(planes), cams):
                p = planes[c0:c0 + cams, :, :, None]  # (cameras, planes, coefficient, cells)
                out[c0:c0 + cams, lo:lo + step] = _inside(p[:, :, 0], p[:, :, 1], p[:, :, 2], p[:, :, 3],
                                                          xyz[0], xyz[1], xyz[2], slack, view)
        return out

    def in_view_each(self, planes: np.ndarray, camera: np.ndarray, view: ViewSettings, rows: np.ndarray) -> np.ndarray:
        """Bool per one of `rows`, each tested against the planes (C, 5, 4) of its own camera (`camera`:
        an index into them per row): the cells of many clients in one pass, in blocks of BLOCK rows."""
        self.settle(rows)
        out = np.empty(len(rows), bool)
        for lo in range(0, len(rows), BLOCK):
            p = np.ascontiguousarray(planes[camera[lo:lo + BLOCK]].transpose(2, 1, 0))  # (coefficient, plane, cell)
            at = rows[lo:lo + BLOCK]
            xyz = self.xyz[:, at]
            out[lo:lo + BLOCK] = _inside(p[0], p[1], p[2], p[3], xyz[0], xyz[1], xyz[2], self.slack[at], view)
        return out


def _stretch(transforms: np.ndarray) -> np.ndarray:
    """Per (4, 4) transform: the largest stretch of its linear part, shear included (spectral norm)."""
    if not len(transforms):
        return np.zeros(0)
    return np.linalg.svd(transforms[:, :3, :3], compute_uv=False)[:, 0]  # (descending: the largest first)


def _inside(a, b, c, d0, x, y, z, slack, view: ViewSettings) -> np.ndarray:
    """The plane test, broadcast over its arguments (the planes' axis second to last): per cell, whether
    every plane's signed distance a x + b y + c z + d0 is at least -(distance margin + slack). Multiply-adds
    over coordinates kept as rows: no BLAS call, no per-cell Python, the same numbers however batched."""
    d = a * x + b * y
    d += c * z
    d += d0 + view.distance_margin
    d += slack
    return (d >= 0).all(axis=-2)


def client_planes(camera, view: ViewSettings) -> np.ndarray | None:
    """The extended frustum's planes of a client's (view, projection), or None: no camera yet, or
    matrices that make no frustum (then it sees everything, as the tick's selection treats it)."""
    if camera is None:
        return None
    return camera_planes(camera[0], camera[1], view.fov_margin)


def clients_planes(cameras: list, view: ViewSettings) -> list[np.ndarray | None]:
    """client_planes of each camera (None: none yet), worked out in one pass."""
    known = [k for k, c in enumerate(cameras) if c is not None]
    out: list[np.ndarray | None] = [None] * len(cameras)
    for k, planes in zip(known, cameras_planes([cameras[k] for k in known], view.fov_margin)):
        out[k] = planes
    return out
