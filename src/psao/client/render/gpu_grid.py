"""The streamed grid on the GPU: instance records, buckets and cells as integer lookup tables.

Each table is an RGBA32UI 2D texture read as a flat array of 16-byte texels, TABLE_WIDTH texels per
row (src/psao/protocol/shaders/psao_common.glsl, psao_fetch): an instance record is 3 texels, a bucket 4, a cell 2. The
bytes are exactly src/psao/protocol/gridformat.py's, so the mirror's arrays go up unchanged.

Textures rather than shader storage buffers: llvmpipe turns every storage-buffer load into a per-lane
scalar loop but gathers texel fetches with SIMD code (benchmarks/bench_render.py compares the pass with
SSAO's). TABLE_WIDTH comes from src/psao/protocol/shader_constants.py, which also gives the shader its value.

A CPU shadow of buckets and cells lets `update` coalesce scattered dirty rows into a few contiguous
writes (rows between two nearby dirty runs are rewritten from the shadow: cheaper than one GL call per
row) and lets the cell table grow or shrink without reading the GPU copy back.
"""
from __future__ import annotations

import numpy as np

from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, EMPTY_BUCKET, FREE_CELL, INSTANCE_DTYPE
from psao.protocol.pointword import NORMAL_CODES, oct_decode
from psao.protocol.shader_constants import TABLE_WIDTH
from psao.client.errors import RenderError

TEXEL_WORDS = 4  # RGBA32UI
MERGE_GAP_ROWS = 32  # dirty runs closer than this many rows are written as one range
# Texture units the grid occupies (the passes use the low units for G-buffer inputs).
UNITS = {"instances": 8, "buckets": 9, "cells": 10}
UNIFORMS = {"instances": "u_psao_instances", "buckets": "u_psao_buckets", "cells": "u_psao_cells"}
_FREE_ROW = {"instances": np.zeros(12, np.uint32), "buckets": EMPTY_BUCKET.reshape(-1), "cells": FREE_CELL}


def dirty_runs(indices: np.ndarray, max_gap: int = MERGE_GAP_ROWS) -> list[tuple[int, int]]:
    """Sorted unique row indices -> [(first, stop)) ranges covering them, merging gaps below max_gap."""
    idx = np.unique(np.asarray(indices, dtype=np.int64))
    if idx.size == 0:
        return []
    breaks = np.nonzero(np.diff(idx) > max_gap)[0]
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    stops = np.concatenate([idx[breaks], [idx[-1]]]) + 1
    return list(zip(starts.tolist(), stops.tolist()))


def normal_table() -> np.ndarray:
    """(256, 4) float32: the unit normal of every 8-bit oct code exactly as pointword.oct_decode gives
    it; the shader reads these (u_psao_normals) instead of decoding, so shader and oracle agree."""
    table = np.zeros((NORMAL_CODES, 4), dtype=np.float32)
    table[:, :3] = oct_decode(np.arange(NORMAL_CODES, dtype=np.uint32))
    return table


class LookupTable:
    """One RGBA32UI texture holding `rows` rows of `row_words` uint32 words each."""

    def __init__(self, ctx, name: str, rows: np.ndarray):
        self._ctx = ctx
        self.name = name
        self.row_words = int(rows.shape[1])
        self.texels_per_row = self.row_words // TEXEL_WORDS
        self.texture = None
        self.bytes_written = 0
        self.replace(rows)

    def replace(self, rows: np.ndarray) -> None:
        """New texture sized for `rows`, all of it written (free rows pad the last texture row)."""
        n_texels = max(len(rows), 1) * self.texels_per_row
        height = -(-n_texels // TABLE_WIDTH)
        limit = int(self._ctx.info["GL_MAX_TEXTURE_SIZE"])
        if height > limit:
            raise RenderError(f"grid {self.name} table of {len(rows)} rows exceeds this OpenGL's texture limit")
        total_words = height * TABLE_WIDTH * TEXEL_WORDS
        padded = np.tile(_FREE_ROW[self.name], -(-total_words // self.row_words))[:total_words]
        flat = np.ascontiguousarray(rows, dtype=np.uint32).reshape(-1)
        padded[: flat.size] = flat
        if self.texture is not None:
            self.texture.release()
        self.texture = self._ctx.texture((TABLE_WIDTH, height), 4, padded.tobytes(), dtype="u4")
        self.texture.filter = (self._ctx.NEAREST, self._ctx.NEAREST)
        self.bytes_written += flat.nbytes

    def write_rows(self, rows: np.ndarray, start: int, stop: int) -> None:
        """Write rows[start:stop] (the full shadow array is passed) at their place in the texture."""
        first, last = start * self.texels_per_row, stop * self.texels_per_row  # texel range [first, last)
        data = np.ascontiguousarray(rows[start:stop], dtype=np.uint32).reshape(-1, TEXEL_WORDS)
        pos = first
        while pos < last:  # at most three writes: partial first row, full middle rows, partial last row
            x, y = pos % TABLE_WIDTH, pos // TABLE_WIDTH
            if x == 0 and last - pos >= TABLE_WIDTH:
                n_rows = (last - pos) // TABLE_WIDTH
                count, viewport = n_rows * TABLE_WIDTH, (0, y, TABLE_WIDTH, n_rows)
            else:
                count = min(TABLE_WIDTH - x, last - pos)
                viewport = (x, y, count, 1)
            chunk = data[pos - first: pos - first + count]
            self.texture.write(chunk.tobytes(), viewport=viewport)
            self.bytes_written += chunk.nbytes
            pos += count

    def read(self, n_rows: int) -> np.ndarray:
        words = np.frombuffer(self.texture.read(), dtype=np.uint32)
        return words[: n_rows * self.row_words].reshape(n_rows, self.row_words).copy()

    def release(self) -> None:
        if self.texture is not None:
            self.texture.release()
            self.texture = None


class GpuGrid:
    """Grid tables of one renderer. `bind(program)` before a pass that includes psao_common.glsl."""

    def __init__(self, ctx):
        self._ctx = ctx
        self.instances = np.zeros(0, dtype=INSTANCE_DTYPE)
        self.buckets = np.zeros((0, BUCKET_ENTRIES, 2), dtype=np.uint32)
        self.cells = np.zeros((0, CELL_WORDS), dtype=np.uint32)
        self._tables = {
            "instances": LookupTable(ctx, "instances", _instance_words(self.instances)),
            "buckets": LookupTable(ctx, "buckets", self.buckets.reshape(0, 16)),
            "cells": LookupTable(ctx, "cells", self.cells),
        }
        self._normals = normal_table().tobytes()

    @property
    def bytes_uploaded(self) -> int:
        """Bytes sent to the GPU so far (full and partial writes), for bus-traffic checks."""
        return sum(t.bytes_written for t in self._tables.values())

    # -- full upload -------------------------------------------------------------------------------
    def upload(self, instances: np.ndarray, buckets: np.ndarray, cells: np.ndarray) -> None:
        """Replace everything (after a snapshot or when loading a baked grid)."""
        self.instances = _as_instances(instances)
        self.buckets = _as_rows(buckets, (BUCKET_ENTRIES, 2), "buckets").copy()
        self.cells = _as_rows(cells, (CELL_WORDS,), "cells").copy()
        self._tables["instances"].replace(_instance_words(self.instances))
        self._tables["buckets"].replace(self.buckets.reshape(-1, 2 * BUCKET_ENTRIES))
        self._tables["cells"].replace(self.cells)

    # -- incremental update --------------------------------------------------------------------------
    def update(self, bucket_idx, bucket_rows, cell_slots, cell_rows, cell_capacity: int | None = None) -> None:
        """Write only dirty buckets and cells. The cell table grows first when the capacity grew, and is
        cut (rewritten whole) when it shrank, following the mirror."""
        bucket_idx = np.asarray(bucket_idx, dtype=np.int64).reshape(-1)
        cell_slots = np.asarray(cell_slots, dtype=np.int64).reshape(-1)
        bucket_rows = _as_rows(bucket_rows, (BUCKET_ENTRIES, 2), "bucket rows")
        cell_rows = _as_rows(cell_rows, (CELL_WORDS,), "cell rows")
        if len(bucket_rows) != len(bucket_idx) or len(cell_rows) != len(cell_slots):
            raise RenderError("grid update: row counts do not match index counts")
        capacity = len(self.cells) if cell_capacity is None else int(cell_capacity)
        _check_range(bucket_idx, len(self.buckets), "bucket")
        _check_range(cell_slots, capacity, "cell slot")
        self.buckets[bucket_idx] = bucket_rows
        flat_buckets = self.buckets.reshape(-1, 2 * BUCKET_ENTRIES)
        for start, stop in dirty_runs(bucket_idx):
            self._tables["buckets"].write_rows(flat_buckets, start, stop)
        if capacity != len(self.cells):
            resized = np.tile(FREE_CELL, (capacity, 1))
            keep = min(capacity, len(self.cells))
            resized[:keep] = self.cells[:keep]
            self.cells = resized
            self.cells[cell_slots] = cell_rows
            self._tables["cells"].replace(self.cells)  # growth doubles: rare, and then all goes up once
            return
        self.cells[cell_slots] = cell_rows
        for start, stop in dirty_runs(cell_slots):
            self._tables["cells"].write_rows(self.cells, start, stop)

    # -- use -----------------------------------------------------------------------------------------
    def prepare(self, program) -> None:
        """Once per program: sampler units and the normal table."""
        for name, uniform in UNIFORMS.items():
            program[uniform].value = UNITS[name]
        program["u_psao_normals"].write(self._normals)

    def bind(self) -> None:
        for name, table in self._tables.items():
            table.texture.use(UNITS[name])

    def read_back(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the GPU holds (tests compare it with the mirror)."""
        inst = self._tables["instances"].read(len(self.instances)).view(INSTANCE_DTYPE).reshape(-1)
        buckets = self._tables["buckets"].read(len(self.buckets)).reshape(-1, BUCKET_ENTRIES, 2)
        return inst, buckets, self._tables["cells"].read(len(self.cells))

    def release(self) -> None:
        for table in self._tables.values():
            table.release()


def _instance_words(instances: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(instances).view(np.uint32).reshape(-1, INSTANCE_DTYPE.itemsize // 4)


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
