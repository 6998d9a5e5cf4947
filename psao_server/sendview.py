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

from protocol import gridformat as gf

from .selection import camera_planes
from .settings import ViewSettings


class CellPlaces:
    """World-space centres and reach (half diagonal) of a set of cell slots under given transforms."""

    def __init__(self, grid, slots: np.ndarray, transforms: np.ndarray):
        slots = np.asarray(slots, np.int64)
        self.centres = np.full((len(slots), 3), np.nan)
        self.reach = np.zeros(len(slots))
        inst = grid.cell_instance[slots] if len(slots) else np.zeros(0, np.int64)
        keys = grid.cells[slots, gf.KEY_WORD] if len(slots) else np.zeros(0, np.uint32)
        placed = np.flatnonzero((inst >= 0) & (keys != gf.EMPTY))
        placed = placed[np.argsort(inst[placed], kind="stable")]
        owners, starts = np.unique(inst[placed], return_index=True)
        for i, rows in zip(owners, np.split(placed, starts[1:])):
            rec = grid.instances[i]
            xyz = gf.key_to_cell(keys[rows], rec["dims"])
            local = rec["origin"].astype(np.float64) + (xyz + 0.5) * float(rec["cell_size"])
            m = np.asarray(transforms[i], np.float64)
            self.centres[rows] = np.einsum("pj,kj->pk", local, m[:3, :3]) + m[:3, 3]  # einsum: no BLAS threads
            scale = float(np.linalg.norm(m[:3, :3], axis=0).max())
            self.reach[rows] = 0.5 * np.sqrt(3.0) * float(rec["cell_size"]) * scale
        # The same, laid out for in_view (it runs per client and send): coordinates as 3 rows, 0 where the
        # place is unknown, and the slack each plane test allows, infinite where unknown (always in view).
        known = np.isfinite(self.centres).all(axis=1)
        self.xyz = np.ascontiguousarray(np.where(known[:, None], self.centres, 0.0).T)
        self.slack = np.where(known, self.reach, np.inf)

    def refresh(self, grid, slots: np.ndarray, transforms: np.ndarray) -> None:
        """Work the places of these slots out again (their cells changed, or their instance moved); the
        slots here are all of the grid's, 0..n-1."""
        part = CellPlaces(grid, slots, transforms)
        self.centres[slots] = part.centres
        self.reach[slots] = part.reach
        self.xyz[:, slots] = part.xyz
        self.slack[slots] = part.slack

    def in_view(self, planes: np.ndarray | None, view: ViewSettings, rows: np.ndarray | None = None) -> np.ndarray:
        """Bool per slot (or per one of `rows`, indices into the slots): in the extended view of a camera's
        planes (None: a camera that sees all). A cell is in when, for every plane, its centre's signed
        distance is at least -(distance margin + reach); a slot whose place is unknown always is."""
        n = len(self.slack) if rows is None else len(rows)
        if planes is None:
            return np.ones(n, dtype=bool)
        xyz = self.xyz if rows is None else self.xyz[:, rows]
        slack = self.slack if rows is None else self.slack[rows]
        # (planes, cells) signed distances as three multiply-adds: no BLAS call, no per-cell Python
        d = planes[:, 0:1] * xyz[0] + planes[:, 1:2] * xyz[1]
        d += planes[:, 2:3] * xyz[2]
        d += (planes[:, 3] + view.distance_margin)[:, None]
        d += slack
        return (d >= 0).all(axis=0)


def client_planes(camera, view: ViewSettings) -> np.ndarray | None:
    """The extended frustum's planes of a client's (view, projection), or None: no camera yet, or
    matrices that make no frustum (then it sees everything, as the tick's selection treats it)."""
    if camera is None:
        return None
    return camera_planes(camera[0], camera[1], view.fov_margin)

