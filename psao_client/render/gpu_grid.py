"""The streamed grid on the GPU: instance records, buckets and cells in three storage buffers.

The layout is exactly protocol/gridformat.py's, so the mirror's arrays go up byte for byte. A CPU
shadow of buckets and cells lets `update` coalesce scattered dirty rows into a few contiguous writes
(rows between two dirty runs that are close together are rewritten from the shadow, which is cheaper
than one GL call per row) and lets the cell buffer grow without reading it back.
"""
from __future__ import annotations

import numpy as np

from protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, EMPTY_BUCKET, FREE_CELL, INSTANCE_DTYPE
from psao_client.errors import RenderError

INSTANCE_BINDING, BUCKET_BINDING, CELL_BINDING = 0, 1, 2
BUCKET_WORDS = BUCKET_ENTRIES * 2
MERGE_GAP_ROWS = 32  # dirty runs closer than this many rows are written as one range


def dirty_runs(indices: np.ndarray, max_gap: int = MERGE_GAP_ROWS) -> list[tuple[int, int]]:
    """Sorted unique row indices -> [(first, stop)) ranges covering them, merging gaps below max_gap."""
    idx = np.unique(np.asarray(indices, dtype=np.int64))
    if idx.size == 0:
        return []
    breaks = np.nonzero(np.diff(idx) > max_gap)[0]
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    stops = np.concatenate([idx[breaks], [idx[-1]]]) + 1
    return list(zip(starts.tolist(), stops.tolist()))


class GpuGrid:
    """Storage buffers of one grid. Call `bind()` before a pass that includes psao_common.glsl."""

    def __init__(self, ctx):
        self._ctx = ctx
        self.instances = np.zeros(0, dtype=INSTANCE_DTYPE)
        self.buckets = np.zeros((0, BUCKET_ENTRIES, 2), dtype=np.uint32)
        self.cells = np.zeros((0, CELL_WORDS), dtype=np.uint32)
        self._buffers: dict[str, object] = {}
        self.bytes_uploaded = 0  # running total, for bandwidth-on-bus checks
        self.upload(self.instances, self.buckets, self.cells)

    # -- full upload -------------------------------------------------------------------------------
    def upload(self, instances: np.ndarray, buckets: np.ndarray, cells: np.ndarray) -> None:
        """Replace everything (after a snapshot or when loading a baked grid)."""
        self.instances = _as_instances(instances)
        self.buckets = _as_rows(buckets, (BUCKET_ENTRIES, 2), "buckets").copy()
        self.cells = _as_rows(cells, (CELL_WORDS,), "cells").copy()
        self._replace("instances", self.instances.tobytes(), INSTANCE_DTYPE.itemsize)
        self._replace("buckets", self.buckets.tobytes(), BUCKET_WORDS * 4)
        self._replace("cells", self.cells.tobytes(), CELL_WORDS * 4)

    # -- incremental update --------------------------------------------------------------------------
    def update(self, bucket_idx, bucket_rows, cell_slots, cell_rows, cell_capacity: int | None = None) -> None:
        """Write only dirty buckets and cells; grow the cell buffer first when the capacity grew."""
        bucket_idx = np.asarray(bucket_idx, dtype=np.int64).reshape(-1)
        cell_slots = np.asarray(cell_slots, dtype=np.int64).reshape(-1)
        bucket_rows = _as_rows(bucket_rows, (BUCKET_ENTRIES, 2), "bucket rows")
        cell_rows = _as_rows(cell_rows, (CELL_WORDS,), "cell rows")
        if len(bucket_rows) != len(bucket_idx) or len(cell_rows) != len(cell_slots):
            raise RenderError("grid update: row counts do not match index counts")
        if cell_capacity is not None and int(cell_capacity) > len(self.cells):
            self._grow_cells(int(cell_capacity))
        _check_range(bucket_idx, len(self.buckets), "bucket")
        _check_range(cell_slots, len(self.cells), "cell slot")
        self.buckets[bucket_idx] = bucket_rows
        self.cells[cell_slots] = cell_rows
        self._write_runs("buckets", self.buckets, bucket_idx)
        self._write_runs("cells", self.cells, cell_slots)

    def set_instances(self, instances: np.ndarray) -> None:
        """Instance records changed (rare: a re-bake of one instance); rewrite the small table."""
        self.instances = _as_instances(instances)
        self._replace("instances", self.instances.tobytes(), INSTANCE_DTYPE.itemsize)

    def _grow_cells(self, capacity: int) -> None:
        old = len(self.cells)
        grown = np.empty((capacity, CELL_WORDS), dtype=np.uint32)
        grown[:old] = self.cells
        grown[old:] = FREE_CELL
        self.cells = grown
        new_buffer = self._ctx.buffer(reserve=max(capacity, 1) * CELL_WORDS * 4)
        old_buffer = self._buffers["cells"]
        if old:
            self._ctx.copy_buffer(new_buffer, old_buffer, size=old * CELL_WORDS * 4)
        if capacity > old:
            new_buffer.write(grown[old:].tobytes(), offset=old * CELL_WORDS * 4)
        old_buffer.release()
        self._buffers["cells"] = new_buffer

    def _write_runs(self, name: str, rows: np.ndarray, indices: np.ndarray) -> None:
        row_bytes = rows[0].nbytes if len(rows) else 0
        buffer = self._buffers[name]
        for start, stop in dirty_runs(indices):
            data = rows[start:stop].tobytes()
            buffer.write(data, offset=start * row_bytes)
            self.bytes_uploaded += len(data)

    def _replace(self, name: str, data: bytes, row_bytes: int) -> None:
        old = self._buffers.pop(name, None)
        if old is not None:
            old.release()
        # A zero-sized buffer is not allowed: keep one row of the free pattern so the binding is valid.
        self._buffers[name] = self._ctx.buffer(data if data else _empty_row(name, row_bytes))
        self.bytes_uploaded += len(data)

    # -- use -----------------------------------------------------------------------------------------
    def bind(self) -> None:
        self._buffers["instances"].bind_to_storage_buffer(INSTANCE_BINDING)
        self._buffers["buckets"].bind_to_storage_buffer(BUCKET_BINDING)
        self._buffers["cells"].bind_to_storage_buffer(CELL_BINDING)

    def read_back(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the GPU holds (tests compare it with the mirror)."""
        inst = np.frombuffer(self._buffers["instances"].read(), dtype=INSTANCE_DTYPE)[: len(self.instances)]
        b = np.frombuffer(self._buffers["buckets"].read(), dtype=np.uint32).reshape(-1, BUCKET_ENTRIES, 2)
        c = np.frombuffer(self._buffers["cells"].read(), dtype=np.uint32).reshape(-1, CELL_WORDS)
        return inst.copy(), b[: len(self.buckets)].copy(), c[: len(self.cells)].copy()

    def release(self) -> None:
        for buffer in self._buffers.values():
            buffer.release()
        self._buffers.clear()


def _empty_row(name: str, row_bytes: int) -> bytes:
    if name == "buckets":
        return EMPTY_BUCKET.tobytes()
    if name == "cells":
        return FREE_CELL.tobytes()
    return bytes(row_bytes)


def _as_instances(instances: np.ndarray) -> np.ndarray:
    arr = np.asarray(instances)
    if arr.dtype != INSTANCE_DTYPE:
        try:
            arr = arr.astype(INSTANCE_DTYPE)
        except (TypeError, ValueError):
            raise RenderError(f"grid instances have dtype {arr.dtype}, expected INSTANCE_DTYPE") from None
    return np.ascontiguousarray(arr.reshape(-1))


def _as_rows(rows: np.ndarray, row_shape: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(rows)
    if arr.size and arr.dtype != np.uint32:
        raise RenderError(f"grid {what} must be uint32, got {arr.dtype}")
    try:
        return np.ascontiguousarray(arr, dtype=np.uint32).reshape((-1, *row_shape))
    except ValueError:
        raise RenderError(f"grid {what} have shape {arr.shape}, expected (n, {', '.join(map(str, row_shape))})") from None


def _check_range(idx: np.ndarray, n: int, what: str) -> None:
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise RenderError(f"grid update: {what} index {int(idx.max())} outside 0..{n - 1}")
