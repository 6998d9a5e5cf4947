"""The client's mirror of the server's grid: numpy arrays shaped exactly like the server's.

    instances   INSTANCE_DTYPE (n,)          from Welcome
    buckets     uint32 (n_buckets, 8, 2)     all EMPTY until the snapshot fills them
    cells       uint32 (capacity, 8)         all FREE_CELL until filled; grows and shrinks with the
                                             capacity carried by every Snapshot chunk and Update
    transforms  float32 (n, 4, 4)            last received local-to-world transforms (identity until
                                             the first snapshot chunk, which carries all of them)

Applying a GridDelta is plain assignment of whole buckets and cells, so after every message the mirror
equals the server's arrays for everything sent. `version` counts applied deltas, so a renderer can see
whether its GPU copy is stale; `dirty_*` accumulate what changed since the renderer last took them.
"""
from __future__ import annotations

import numpy as np

from protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, EMPTY, FREE_CELL, INSTANCE_DTYPE
from protocol.messages import Welcome
from protocol.updates import GridDelta, state_digest

from .errors import MirrorError


class Mirror:
    def __init__(self, instances: np.ndarray, n_buckets: int, cell_capacity: int):
        self.instances = np.array(instances, dtype=INSTANCE_DTYPE)
        self.buckets = np.full((n_buckets, BUCKET_ENTRIES, 2), EMPTY, dtype=np.uint32)
        self.cells = np.tile(FREE_CELL, (cell_capacity, 1))
        self.transforms = np.tile(np.eye(4, dtype=np.float32), (len(self.instances), 1, 1))
        self.tick = -1  # last Update applied
        # seconds: the scene time of that Update (skinned meshes are posed at it); None before the first,
        # when the snapshot of a static server holds points of the rest pose
        self.server_time: float | None = None
        self.version = 0
        self.dirty_buckets: set[int] = set()
        self.dirty_cells: set[int] = set()
        self._fresh = True  # a new mirror (a new connection): everything differs from any older copy
        self._check_instances()

    @classmethod
    def from_welcome(cls, welcome: Welcome) -> "Mirror":
        return cls(welcome.instances, welcome.n_buckets, welcome.cell_capacity)

    def _check_instances(self) -> None:
        inst = self.instances
        end = inst["bucket_offset"].astype(np.int64) + inst["bucket_count"].astype(np.int64)
        if len(inst) and int(end.max()) > len(self.buckets):
            raise MirrorError(f"instance table refers to bucket {int(end.max()) - 1} of {len(self.buckets)}")

    @property
    def cell_capacity(self) -> int:
        return len(self.cells)

    def resize_cells(self, capacity: int) -> None:
        """Grow with free cells or cut to the server's new capacity (after a compaction)."""
        n = len(self.cells)
        if capacity > n:
            self.cells = np.concatenate([self.cells, np.tile(FREE_CELL, (capacity - n, 1))])
        elif capacity < n:
            self.cells = self.cells[:capacity].copy()

    def apply(self, delta: GridDelta) -> None:
        """Write a delta's transforms, buckets and cells; indices are checked against the mirror first."""
        if len(delta.transform_ids) and int(delta.transform_ids[-1]) >= len(self.instances):
            raise MirrorError(f"transform of instance {int(delta.transform_ids[-1])} of {len(self.instances)}")
        if len(delta.bucket_ids) and int(delta.bucket_ids[-1]) >= len(self.buckets):
            raise MirrorError(f"bucket {int(delta.bucket_ids[-1])} outside the table of {len(self.buckets)}")
        if delta.cell_capacity != len(self.cells):
            self.resize_cells(delta.cell_capacity)
        if len(delta.cell_slots) and int(delta.cell_slots[-1]) >= len(self.cells):
            raise MirrorError(f"cell slot {int(delta.cell_slots[-1])} outside the capacity {len(self.cells)}")
        self.transforms[delta.transform_ids] = delta.transforms
        self.buckets[delta.bucket_ids] = delta.buckets
        self.cells[delta.cell_slots] = delta.cells
        self.dirty_buckets.update(delta.bucket_ids.tolist())
        self.dirty_cells.update(delta.cell_slots.tolist())
        self.version += 1

    def take_dirty(self) -> tuple[np.ndarray, np.ndarray]:
        """(bucket indices, cell slots) changed since the last call, sorted; for partial GPU uploads.
        The first call on a new mirror returns every bucket and cell: after a reconnect the new mirror
        replaces the old one entirely (the resync snapshot only carries what is allocated)."""
        if self._fresh:
            b = np.arange(len(self.buckets), dtype=np.uint32)
            c = np.arange(len(self.cells), dtype=np.uint32)
        else:
            b = np.array(sorted(self.dirty_buckets), dtype=np.uint32)
            c = np.array(sorted(i for i in self.dirty_cells if i < len(self.cells)), dtype=np.uint32)
        self._fresh = False
        self.dirty_buckets.clear()
        self.dirty_cells.clear()
        return b, c

    def allocated_cells(self) -> int:
        return int(np.count_nonzero(self.cells[:, CELL_WORDS - 1] != EMPTY))

    def allocated_buckets(self) -> int:
        return int(np.count_nonzero(np.any(self.buckets[:, :, 0] != EMPTY, axis=1)))

    def digest(self) -> str:
        return state_digest(self.instances, self.buckets, self.cells, self.transforms)
