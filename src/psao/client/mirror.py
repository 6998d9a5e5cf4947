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

from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, EMPTY, FREE_CELL, INSTANCE_DTYPE
from psao.protocol.limits import Limits
from psao.protocol.messages import Welcome
from psao.protocol.updates import GridDelta, state_digest

from psao.client.errors import MirrorError


class Mirror:
    """Eager by default (arrays at their full size at once). With `limits` (a mirror fed from the
    network) it is lazy: the arrays grow to the highest bucket and cell slot received so far, and to the
    sizes the server claims only when the snapshot is complete (`complete()`); every growth must fit the
    budget limits.mirror_base_bytes + limits.mirror_bytes_per_received_byte x bytes received
    (`received()`), so a tiny message claiming a huge grid allocates nothing big."""

    def __init__(self, instances: np.ndarray, n_buckets: int, cell_capacity: int, limits: Limits | None = None):
        self.instances = np.array(instances, dtype=INSTANCE_DTYPE)
        self.n_buckets = int(n_buckets)  # the server's table size (claimed until the snapshot is complete)
        self._capacity = int(cell_capacity)  # the server's latest cell capacity
        self.limits = limits
        self.received_bytes = 0
        self.lazy = limits is not None
        rows = 0 if self.lazy else self.n_buckets
        self.buckets = np.full((rows, BUCKET_ENTRIES, 2), EMPTY, dtype=np.uint32)
        self.cells = np.tile(FREE_CELL, (0 if self.lazy else self._capacity, 1))
        self.transforms = np.tile(np.eye(4, dtype=np.float32), (len(self.instances), 1, 1))
        self.tick = -1  # last Update applied
        # seconds: the scene time of that Update (skinned meshes are posed at it); None before the first,
        # when the snapshot of a static server holds points of the rest pose
        self.server_time: float | None = None
        self.version = 0
        # per bucket and cell row: changed since the renderer last took them (as long as the arrays)
        self._dirty_buckets = np.zeros(len(self.buckets), bool)
        self._dirty_cells = np.zeros(len(self.cells), bool)
        self._fresh = True  # a new mirror (a new connection): everything differs from any older copy
        self._check_instances()

    @classmethod
    def from_welcome(cls, welcome: Welcome, limits: Limits | None = None) -> "Mirror":
        return cls(welcome.instances, welcome.n_buckets, welcome.cell_capacity, limits)

    def _check_instances(self) -> None:
        inst = self.instances
        end = inst["bucket_offset"].astype(np.int64) + inst["bucket_count"].astype(np.int64)
        if len(inst) and int(end.max()) > self.n_buckets:
            raise MirrorError(f"instance table refers to bucket {int(end.max()) - 1} of {self.n_buckets}")

    @property
    def cell_capacity(self) -> int:
        return len(self.cells)

    # ------------------------------------------------------------------ allocation
    def received(self, nbytes: int) -> None:
        """Count bytes received from the server: they pay for the mirror's growth."""
        self.received_bytes += int(nbytes)

    def _afford(self, buckets: int, cells: int) -> None:
        if self.limits is None:
            return
        need = buckets * BUCKET_ENTRIES * 2 * 4 + cells * CELL_WORDS * 4
        allowed = self.limits.mirror_base_bytes + self.limits.mirror_bytes_per_received_byte * self.received_bytes
        if need > allowed:
            raise MirrorError(f"the server's grid ({buckets} buckets, {cells} cells: {need / 2**20:.0f} MiB) is out of "
                              f"proportion to the {self.received_bytes} bytes received (allowed {allowed / 2**20:.0f} MiB)")

    def _grow_buckets(self, rows: int) -> None:
        n = len(self.buckets)
        if rows > n:
            self._afford(rows, len(self.cells))
            grown = np.full((rows, BUCKET_ENTRIES, 2), EMPTY, dtype=np.uint32)
            grown[:n] = self.buckets
            self.buckets = grown
            self._dirty_buckets = _resized(self._dirty_buckets, rows)

    def resize_cells(self, capacity: int) -> None:
        """Grow with free cells or cut to the capacity a message carries (the protocol allows a smaller one;
        psao serve's pool only grows)."""
        n = len(self.cells)
        if capacity > n:
            self._afford(len(self.buckets), capacity)
            self.cells = np.concatenate([self.cells, np.tile(FREE_CELL, (capacity - n, 1))])
        elif capacity < n:
            self.cells = self.cells[:capacity].copy()
        if len(self._dirty_cells) != len(self.cells):
            self._dirty_cells = _resized(self._dirty_cells, len(self.cells))

    def complete(self) -> None:
        """The snapshot is complete: the arrays take the server's full sizes (digests compare them)."""
        self._grow_buckets(self.n_buckets)
        self.resize_cells(self._capacity)
        self.lazy = False

    def apply(self, delta: GridDelta) -> None:
        """Write a delta's transforms, buckets and cells; indices are checked against the mirror first."""
        if len(delta.transform_ids) and int(delta.transform_ids[-1]) >= len(self.instances):
            raise MirrorError(f"transform of instance {int(delta.transform_ids[-1])} of {len(self.instances)}")
        top_bucket = int(delta.bucket_ids[-1]) if len(delta.bucket_ids) else -1
        if top_bucket >= self.n_buckets:
            raise MirrorError(f"bucket {top_bucket} outside the table of {self.n_buckets}")
        top_cell = int(delta.cell_slots[-1]) if len(delta.cell_slots) else -1
        if top_cell >= delta.cell_capacity:
            raise MirrorError(f"cell slot {top_cell} outside the capacity {delta.cell_capacity}")
        self._capacity = int(delta.cell_capacity)
        if self.lazy:  # grow (geometrically) to what this delta writes, within the claimed sizes
            if top_bucket >= len(self.buckets):
                self._grow_buckets(min(self.n_buckets, max(top_bucket + 1, 2 * len(self.buckets))))
            want = min(self._capacity, max(top_cell + 1, 2 * len(self.cells))) if top_cell >= len(self.cells) else len(self.cells)
            self.resize_cells(min(want, self._capacity))
        elif delta.cell_capacity != len(self.cells):
            self.resize_cells(delta.cell_capacity)
        self.transforms[delta.transform_ids] = delta.transforms
        self.buckets[delta.bucket_ids] = delta.buckets
        self.cells[delta.cell_slots] = delta.cells
        self._dirty_buckets[delta.bucket_ids] = True
        self._dirty_cells[delta.cell_slots] = True
        self.version += 1

    def take_dirty(self) -> tuple[np.ndarray, np.ndarray]:
        """(bucket indices, cell slots) changed since the last call, sorted; for partial GPU uploads.
        The first call on a new mirror returns every bucket and cell: after a reconnect the new mirror
        replaces the old one entirely (the resync snapshot only carries what is allocated)."""
        if self._fresh:
            b = np.arange(len(self.buckets), dtype=np.uint32)
            c = np.arange(len(self.cells), dtype=np.uint32)
        else:
            b = np.flatnonzero(self._dirty_buckets).astype(np.uint32)
            c = np.flatnonzero(self._dirty_cells).astype(np.uint32)
        self._fresh = False
        self._dirty_buckets[:] = False
        self._dirty_cells[:] = False
        return b, c

    def allocated_cells(self) -> int:
        return int(np.count_nonzero(self.cells[:, CELL_WORDS - 1] != EMPTY))

    def allocated_buckets(self) -> int:
        return int(np.count_nonzero(np.any(self.buckets[:, :, 0] != EMPTY, axis=1)))

    def digest(self) -> str:
        return state_digest(self.instances, self.buckets, self.cells, self.transforms)


def _resized(mask: np.ndarray, rows: int) -> np.ndarray:
    """A per-row mask cut or grown (False) to `rows`."""
    if rows <= len(mask):
        return mask[:rows].copy()
    return np.concatenate([mask, np.zeros(rows - len(mask), bool)])
