"""Grid deltas on the wire: the body of Update and Snapshot messages, in two layouts.

A `GridDelta` is what one message changes in the mirror: the cell capacity, some instance transforms,
whole buckets (global index + 8 (key, slot) entries) and whole cells (slot + 8 words), indices sorted
and unique. Applying it is a plain assignment, so a mirror that applies every delta in order equals
the server for everything sent. An Update may carry several deltas (parts) for disjoint indices, made
apart and sent together; they read as their union (`decode_delta_parts`).

PLAIN is the paper's layout: counts, then indices and words as raw little-endian uint32.

PACKED is the default and is lossless for any input, canonical or not:
- indices sorted, as LEB128 varints of (gap - 1);
- a bucket is its number of used entries (used entries first, the rest EMPTY) and only those entries;
  a cell is its number of points (allocated bit set, first) and only those points, rest zero. A bucket
  or cell that breaks that form is flagged (RAW) and sent whole, so nothing is ever lost;
- point words are split into fields (position 15 bits, normal, AO) and every multi-byte field into byte
  planes, so that bytes with the same meaning sit together before compression.
"""
from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from psao.protocol.errors import LimitError, PayloadError
from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, EMPTY, KEY_WORD, POINTS_PER_CELL
from psao.protocol.limits import DEFAULT_LIMITS, Limits
from psao.protocol.pointword import ALLOCATED_BIT

RAW = 0xFF  # count byte of a bucket or cell sent whole


class Layout(IntEnum):
    PLAIN = 0
    PACKED = 1


LAYOUT_NAMES = {"plain": Layout.PLAIN, "packed": Layout.PACKED}


def layout_name(layout: Layout) -> str:
    return next(name for name, value in LAYOUT_NAMES.items() if value == layout)


def _empty_u32(*shape) -> np.ndarray:
    return np.zeros(shape, dtype=np.uint32)


@dataclass
class GridDelta:
    cell_capacity: int
    transform_ids: np.ndarray = field(default_factory=lambda: _empty_u32(0))  # (k,) sorted
    transforms: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4), np.float32))  # (k, 4, 4)
    bucket_ids: np.ndarray = field(default_factory=lambda: _empty_u32(0))  # (nb,) sorted, global
    buckets: np.ndarray = field(default_factory=lambda: _empty_u32(0, BUCKET_ENTRIES, 2))  # (nb, 8, 2)
    cell_slots: np.ndarray = field(default_factory=lambda: _empty_u32(0))  # (nc,) sorted
    cells: np.ndarray = field(default_factory=lambda: _empty_u32(0, CELL_WORDS))  # (nc, 8)

    def __post_init__(self):
        self.transform_ids = np.ascontiguousarray(self.transform_ids, dtype=np.uint32).reshape(-1)
        self.transforms = np.ascontiguousarray(self.transforms, dtype=np.float32).reshape(-1, 4, 4)
        self.bucket_ids = np.ascontiguousarray(self.bucket_ids, dtype=np.uint32).reshape(-1)
        self.buckets = np.ascontiguousarray(self.buckets, dtype=np.uint32).reshape(-1, BUCKET_ENTRIES, 2)
        self.cell_slots = np.ascontiguousarray(self.cell_slots, dtype=np.uint32).reshape(-1)
        self.cells = np.ascontiguousarray(self.cells, dtype=np.uint32).reshape(-1, CELL_WORDS)

    def check(self, limits: Limits = DEFAULT_LIMITS) -> None:
        """Structural validity: matching lengths, sorted unique indices, slots inside the capacity."""
        if not 0 <= self.cell_capacity <= limits.max_cell_capacity:
            raise LimitError(f"cell capacity {self.cell_capacity} over the limit of {limits.max_cell_capacity}")
        pairs = [
            ("transform", self.transform_ids, self.transforms, limits.max_instances),
            ("bucket", self.bucket_ids, self.buckets, limits.max_buckets_per_message),
            ("cell", self.cell_slots, self.cells, limits.max_cells_per_message),
        ]
        for what, ids, rows, most in pairs:
            if len(ids) != len(rows):
                raise PayloadError(f"{len(ids)} {what} indices for {len(rows)} {what} records")
            if len(ids) > most:
                raise LimitError(f"{len(ids)} {what} records in one message, over the limit of {most}")
            if len(ids) > 1 and not np.all(ids[1:] > ids[:-1]):
                raise PayloadError(f"{what} indices are not sorted and unique")
        if len(self.cell_slots) and int(self.cell_slots[-1]) >= self.cell_capacity:
            raise PayloadError(f"cell slot {int(self.cell_slots[-1])} outside the capacity {self.cell_capacity}")
        if not np.all(np.isfinite(self.transforms)):
            raise PayloadError("instance transform with NaN or infinity")

    @property
    def n_points(self) -> int:
        """Allocated points carried (for bytes-per-point figures)."""
        return int(np.count_nonzero(self.cells[:, :POINTS_PER_CELL] & ALLOCATED_BIT))

    def equals(self, other: "GridDelta") -> bool:
        return self.cell_capacity == other.cell_capacity and all(
            np.array_equal(getattr(self, f), getattr(other, f))
            for f in ("transform_ids", "bucket_ids", "buckets", "cell_slots", "cells")
        ) and self.transforms.tobytes() == other.transforms.tobytes()


# ---------------------------------------------------------------------------------------------- reading


class Reader:
    """Bounds-checked cursor over a payload: every take is checked against what is left."""

    def __init__(self, payload: bytes, what: str):
        self.view = memoryview(payload)
        self.pos = 0
        self.what = what

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.view):
            raise PayloadError(f"{self.what}: truncated (needs {n} bytes at offset {self.pos}, has {len(self.view)})")
        out = self.view[self.pos : self.pos + n]
        self.pos += n
        return out

    def unpack(self, st: struct.Struct) -> tuple:
        return st.unpack(self.take(st.size))

    def array(self, dtype, count: int) -> np.ndarray:
        dt = np.dtype(dtype)
        return np.frombuffer(self.take(dt.itemsize * count), dtype=dt).copy()

    def rest(self) -> memoryview:
        return self.take(len(self.view) - self.pos)

    def at_end(self) -> bool:
        return self.pos == len(self.view)

    def done(self) -> None:
        if self.pos != len(self.view):
            raise PayloadError(f"{self.what}: {len(self.view) - self.pos} unexpected bytes after the end")


# ------------------------------------------------------------------------------------------------ plain

_COUNTS = struct.Struct("<BIIII")  # layout, cell capacity, transforms, buckets, cells


def _check_counts(capacity: int, k: int, nb: int, nc: int, limits: Limits) -> None:
    for what, n, most in (
        ("cell capacity", capacity, limits.max_cell_capacity),
        ("transform count", k, limits.max_instances),
        ("bucket count", nb, limits.max_buckets_per_message),
        ("cell count", nc, limits.max_cells_per_message),
    ):
        if n > most:
            raise LimitError(f"grid delta: {what} {n} over the limit of {most}")


def _encode_plain(d: GridDelta) -> bytes:
    head = _COUNTS.pack(Layout.PLAIN, d.cell_capacity, len(d.transform_ids), len(d.bucket_ids), len(d.cell_slots))
    parts = [d.transform_ids, d.transforms, d.bucket_ids, d.buckets, d.cell_slots, d.cells]
    return head + b"".join(np.ascontiguousarray(p).astype(p.dtype.newbyteorder("<")).tobytes() for p in parts)


def _decode_plain(r: Reader, capacity: int, k: int, nb: int, nc: int) -> _Part:
    return _Part(
        capacity,
        r.array("<u4", k),
        r.array("<f4", 16 * k).reshape(k, 4, 4),
        r.array("<u4", nb),
        r.array("<u4", nb * 2 * BUCKET_ENTRIES).reshape(nb, BUCKET_ENTRIES, 2),
        (r.array("<u4", nc), r.array("<u4", nc * CELL_WORDS).reshape(nc, CELL_WORDS)),
    )


# ------------------------------------------------------------------------------------- packed: helpers


_VARINT_SHIFTS = np.arange(0, 35, 7, dtype=np.int64)  # the 5 groups of 7 bits of a uint32
_VARINT_LIMITS = np.int64(1) << _VARINT_SHIFTS[1:]  # a value at or above limit k takes more than k + 1 bytes
_VARINT_GROUP = np.arange(5)


def varint_encode(values: np.ndarray) -> bytes:
    """uint32 values -> LEB128 bytes (7 bits per byte, high bit = more follows), vectorised: every value's
    5 groups at once, then the groups each value needs (its length) in order."""
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    if v.size == 0:
        return b""
    groups = (v[:, None] >> _VARINT_SHIFTS) & 0x7F  # (n, 5)
    nbytes = np.searchsorted(_VARINT_LIMITS, v, side="right") + 1  # 1..5
    groups[_VARINT_GROUP < (nbytes - 1)[:, None]] |= 0x80  # more follows
    return groups.astype(np.uint8)[_VARINT_GROUP < nbytes[:, None]].tobytes()


def varint_decode(data: bytes | memoryview, count: int, what: str) -> np.ndarray:
    """LEB128 bytes -> exactly `count` uint32 values; anything else in `data` is an error."""
    b = np.frombuffer(data, dtype=np.uint8)
    if count == 0:
        if b.size:
            raise PayloadError(f"{what}: {b.size} bytes for no values")
        return _empty_u32(0)
    ends = b < 0x80
    if b.size == count and ends.all():  # every value in one byte (small gaps, the usual case): the values
        return b.astype(np.uint32)
    last = np.flatnonzero(ends)
    if len(last) != count or not ends[-1]:
        raise PayloadError(f"{what}: varint section does not hold exactly {count} values")
    lengths = np.diff(last, prepend=-1)  # bytes of each value
    if lengths.max() > 5:
        raise PayloadError(f"{what}: varint longer than 5 bytes")
    # every byte's 7 bits shifted to its place in its value, summed per value: work in proportion to the
    # bytes (no row of 5 groups per value)
    first = last - lengths + 1
    place = np.arange(b.size, dtype=np.int64) - np.repeat(first, lengths)
    v = np.add.reduceat((b & 0x7F).astype(np.uint64) << (7 * place).astype(np.uint64), first)
    if v.max() > 0xFFFFFFFF:
        raise PayloadError(f"{what}: varint value beyond 32 bits")
    return v.astype(np.uint32)


# Up to this many ids, gaps_encode writes their varints by a loop: the tile parts and heads the encode thread
# writes every tick are a few dozen ids each, where numpy's per-call cost is most of the work.
LOOP_GAPS_IDS = 512


def gaps_encode(sorted_ids: np.ndarray) -> bytes:
    """Strictly increasing ids -> varints of the first id and of every gap minus one (a few hundred ids
    by a loop, as their decode: numpy's per-call cost is most of the work there; the same bytes)."""
    ids = np.asarray(sorted_ids, dtype=np.int64).reshape(-1)
    if len(ids) <= LOOP_GAPS_IDS:
        out = _gaps_encode_loop(ids.tolist())
        if out is not None:
            return out
    gaps = np.empty_like(ids)
    if len(ids):
        gaps[0] = ids[0]
        np.subtract(ids[1:], ids[:-1] + 1, out=gaps[1:])
    return varint_encode(gaps)


def _gaps_encode_loop(ids: list[int]) -> bytes | None:
    """gaps_encode by a loop over the ids; None where they are not strictly increasing from 0 (the
    vectorised encode then writes what it writes for them)."""
    out = bytearray()
    last = -1
    for i in ids:
        gap = i - last - 1
        if gap < 0:
            return None
        last = i
        while gap >= 0x80:
            out.append((gap & 0x7F) | 0x80)
            gap >>= 7
        out.append(gap)
    return bytes(out)


# Varint sections of at most this many bytes (all of an Update's sections together) are decoded by a loop
# over their bytes: a usual Update's cell slots are a few dozen bytes, where the fixed cost of the
# vectorised decode's numpy calls is many times the work. Both ways give the same ids and refuse the same input.
LOOP_VARINT_BYTES = 512


def gaps_decode(data, count: int, what: str) -> np.ndarray:
    return gaps_decode_parts([data], [count], what)


def gaps_decode_parts(datas: list, counts: list[int], what: str) -> np.ndarray:
    """Several sections as gaps_encode writes them (each its own run of ids, `counts[i]` of them) -> all
    their ids, in order; each section must hold exactly its count."""
    if sum(len(d) for d in datas) <= LOOP_VARINT_BYTES:
        return _gaps_loop(datas, counts, what)
    return _gaps_numpy(datas, counts, what)


def _gaps_loop(datas: list, counts: list[int], what: str) -> np.ndarray:
    """gaps_decode_parts by a loop over the bytes (7 bits each, lowest group first, high bit: more follows)."""
    ids: list[int] = []
    for data, count in zip(datas, counts):
        start, last, value, shift = len(ids), -1, 0, 0
        for byte in bytes(data):
            value |= (byte & 0x7F) << shift
            if byte & 0x80:
                shift += 7
                if shift == 35:
                    raise PayloadError(f"{what}: varint longer than 5 bytes")
                continue
            if value > 0xFFFFFFFF:
                raise PayloadError(f"{what}: varint value beyond 32 bits")
            last += value + 1
            ids.append(last)
            value = shift = 0
        if shift or len(ids) - start != count:
            raise PayloadError(f"{what}: varint section does not hold exactly {count} values")
        if last > 0xFFFFFFFF:
            raise PayloadError(f"{what}: index beyond 32 bits")
    return np.array(ids, np.uint32)


def _gaps_numpy(datas: list, counts: list[int], what: str) -> np.ndarray:
    """gaps_decode_parts vectorised: every section's varints decoded at once."""
    if len(datas) == 1:
        data, count = datas[0], counts[0]
        if count == 0 and not len(data):
            return _empty_u32(0)
        ids = np.cumsum(varint_decode(data, count, what).astype(np.int64) + 1) - 1
        if count and ids[-1] > 0xFFFFFFFF:
            raise PayloadError(f"{what}: index beyond 32 bits")
        return ids.astype(np.uint32)
    lengths = np.array([len(d) for d in datas], np.int64)
    n = np.asarray(counts, np.int64)
    b = np.frombuffer(b"".join(datas), np.uint8)
    full = lengths > 0
    ends = (b < 0x80).astype(np.int64)
    per = np.zeros(len(datas), np.int64)
    if b.size:
        per[full] = np.add.reduceat(ends, (np.cumsum(lengths) - lengths)[full])
    if not (np.array_equal(per, n) and ends[np.cumsum(lengths)[full] - 1].all()):
        raise PayloadError(f"{what}: a varint section does not hold exactly its count of values")
    if not b.size:
        return _empty_u32(0)
    total = np.cumsum(varint_decode(b, int(n.sum()), what).astype(np.int64) + 1)
    starts = np.cumsum(n) - n  # each section's first value
    base = np.where(starts > 0, total[np.maximum(starts - 1, 0)], 0)
    ids = total - np.repeat(base, n) - 1
    if ids.max() > 0xFFFFFFFF:
        raise PayloadError(f"{what}: index beyond 32 bits")
    return ids.astype(np.uint32)


def _le_bytes(a: np.ndarray) -> np.ndarray:
    """(n, itemsize) uint8: each value's little-endian bytes, a row per value (a row slice's transpose is
    its byte planes, as planes() writes them)."""
    a = np.ascontiguousarray(a).reshape(-1)
    return a.astype(a.dtype.newbyteorder("<")).view(np.uint8).reshape(-1, a.dtype.itemsize)


def planes(a: np.ndarray) -> bytes:
    """Little-endian multi-byte values -> their byte planes, lowest byte plane first."""
    return _le_bytes(a).T.tobytes()


def unplanes(r: Reader, dtype, count: int) -> np.ndarray:
    dt = np.dtype(dtype).newbyteorder("<")
    raw = np.frombuffer(r.take(dt.itemsize * count), dtype=np.uint8).reshape(dt.itemsize, count)
    return np.ascontiguousarray(raw.T).view(dt).reshape(count).astype(dt.newbyteorder("="))


def _leading_counts(used: np.ndarray, filler_ok: np.ndarray) -> np.ndarray:
    """Per row: number of leading used entries if the row is canonical (used first, the rest exactly
    the filler), else RAW."""
    n = used.sum(axis=1)
    cols = np.arange(used.shape[1])
    canonical = np.all(np.where(cols < n[:, None], used, filler_ok), axis=1)
    return np.where(canonical, n, RAW).astype(np.uint8)


# ------------------------------------------------------------------------------------ packed: encoding

_PACKED_LENGTHS = struct.Struct("<III")  # bytes of the varint sections: transform ids, bucket ids, cell slots


def _packed_buckets(d: GridDelta) -> list[bytes]:
    """The bucket sections: ids, leading counts, canonical entries' keys and slots, raw buckets."""
    if not len(d.bucket_ids):  # every section empty (an Update that changes cells only)
        return [b""] * 5
    keys, slots = d.buckets[:, :, 0], d.buckets[:, :, 1]
    b_used = keys != EMPTY
    b_count = _leading_counts(b_used, (keys == EMPTY) & (slots == EMPTY))
    b_canon = b_count != RAW
    b_sel = b_used & b_canon[:, None]
    raw = planes(d.buckets[~b_canon]) if not b_canon.all() else b""
    return [gaps_encode(d.bucket_ids), b_count.tobytes(), planes(keys[b_sel]), planes(slots[b_sel]), raw]


class _PackedCells:
    """The packed cell sections of rows of cells, the per-row work done once for all of them, so that
    each run of rows (an Update of parts' tiles: a few cells each) costs only slicing (`sections`)."""

    def __init__(self, slots: np.ndarray, cells: np.ndarray):
        self.slots, self.cells = slots, cells
        points = cells[:, :POINTS_PER_CELL]
        p_used = (points & ALLOCATED_BIT) != 0
        self.counts = _leading_counts(p_used, points == 0)
        self.canon = self.counts != RAW
        sel = p_used & self.canon[:, None]
        p = points[sel]  # the canonical cells' points, row by row: a run of rows has a run of these
        self.p_end = np.cumsum(np.count_nonzero(sel, axis=1))  # points up to and with each row
        self.raw_end = np.cumsum(~self.canon)  # raw cells up to and with each row
        self.keys = _le_bytes(cells[:, KEY_WORD])
        self.pos = _le_bytes(((p >> 16) & 0x7FFF).astype(np.uint16))  # 3 x 5-bit position
        self.normal = ((p >> 8) & 0xFF).astype(np.uint8)  # octahedral normal
        self.ao = (p & 0xFF).astype(np.uint8)

    def sections(self, a: int, b: int) -> list[bytes]:
        """The cell sections of rows a..b-1 (slots strictly increasing): slots, leading counts, keys,
        canonical points' fields, raw cells."""
        if a == b:
            return [b""] * 7
        pa, pb = (int(self.p_end[a - 1]) if a else 0), int(self.p_end[b - 1])
        raw = int(self.raw_end[b - 1]) - (int(self.raw_end[a - 1]) if a else 0)
        return [
            gaps_encode(self.slots[a:b]),
            self.counts[a:b].tobytes(),
            self.keys[a:b].T.tobytes(),
            self.pos[pa:pb].T.tobytes(),
            self.normal[pa:pb].tobytes(),
            self.ao[pa:pb].tobytes(),
            planes(self.cells[a:b, :POINTS_PER_CELL][~self.canon[a:b]]) if raw else b"",
        ]


def _packed_cells(d: GridDelta) -> list[bytes]:
    """The cell sections: slots, leading counts, keys, canonical points' fields, raw cells."""
    if not len(d.cell_slots):
        return [b""] * 7
    return _PackedCells(d.cell_slots, d.cells).sections(0, len(d.cell_slots))


def _encode_packed(d: GridDelta) -> bytes:
    head = _COUNTS.pack(Layout.PACKED, d.cell_capacity, len(d.transform_ids), len(d.bucket_ids), len(d.cell_slots))
    t_ids = gaps_encode(d.transform_ids)
    b_ids, *bucket_rest = _packed_buckets(d)
    c_ids, *cell_rest = _packed_cells(d)
    parts = [head, _PACKED_LENGTHS.pack(len(t_ids), len(b_ids), len(c_ids)), t_ids, planes(d.transforms),
             b_ids, *bucket_rest, c_ids, *cell_rest]
    return b"".join(parts)


def encode_cell_runs(capacity: int, slots: np.ndarray, cells: np.ndarray, runs: list[tuple[int, int]],
                     layout: Layout = Layout.PACKED) -> list[bytes]:
    """encode_delta(GridDelta(capacity, cell_slots=slots[a:b], cells=cells[a:b]), layout) of each run (a, b)
    of rows (each run's slots strictly increasing): the same bytes, with the per-row work done once for
    all the runs (an Update of parts has a few tiles of a few cells each a tick, where numpy's per-call
    cost is most of an encode) and only slicing per run."""
    slots = np.ascontiguousarray(slots, np.uint32).reshape(-1)
    cells = np.ascontiguousarray(cells, np.uint32).reshape(-1, CELL_WORDS)
    if layout != Layout.PACKED or not len(slots):
        return [encode_delta(GridDelta(capacity, cell_slots=slots[a:b], cells=cells[a:b]), layout) for a, b in runs]
    packed = _PackedCells(slots, cells)
    out = []
    for a, b in runs:
        ids, *rest = packed.sections(a, b)
        out.append(b"".join([_CELLS_ONLY_HEAD.pack(Layout.PACKED, capacity, 0, 0, b - a, 0, 0, len(ids)), ids, *rest]))
    return out


def _expand_leading(counts: np.ndarray, width: int) -> np.ndarray:
    """(n,) leading counts -> (n, width) bool mask of the first counts[i] columns."""
    return np.arange(width)[None, :] < counts[:, None]


def _read_counts(r: Reader, n: int, most: int, what: str) -> np.ndarray:
    counts = r.array(np.uint8, n)
    if np.any((counts > most) & (counts != RAW)):
        raise PayloadError(f"{what}: entry count above {most}")
    return counts


def _decode_packed(r: Reader, capacity: int, k: int, nb: int, nc: int) -> _Part:
    lt, lb, lc = r.unpack(_PACKED_LENGTHS)
    if not (k or nb or lt or lb):  # cells only (a tile of an Update of parts): nothing else to read
        return _Part(capacity, _empty_u32(0), np.zeros((0, 4, 4), np.float32), _empty_u32(0),
                     _empty_u32(0, BUCKET_ENTRIES, 2), _read_packed_cells(r, lc, nc))
    transform_ids = gaps_decode(r.take(lt), k, "transform ids")
    transforms = unplanes(r, "<f4", 16 * k).reshape(k, 4, 4) if k else np.zeros((0, 4, 4), np.float32)
    bucket_ids, buckets = _decode_packed_buckets(r, lb, nb)
    return _Part(capacity, transform_ids, transforms, bucket_ids, buckets, _read_packed_cells(r, lc, nc))


def _decode_packed_buckets(r: Reader, lb: int, nb: int) -> tuple[np.ndarray, np.ndarray]:
    if nb == 0:  # every section empty (as _packed_buckets writes it): nothing to read but the empty varints
        gaps_decode(r.take(lb), 0, "bucket ids")
        return _empty_u32(0), _empty_u32(0, BUCKET_ENTRIES, 2)
    bucket_ids = gaps_decode(r.take(lb), nb, "bucket ids")
    b_count = _read_counts(r, nb, BUCKET_ENTRIES, "bucket")
    b_canon = b_count != RAW
    b_sel = _expand_leading(np.where(b_canon, b_count, 0), BUCKET_ENTRIES)
    n_entries = int(b_sel.sum())
    buckets = np.full((nb, BUCKET_ENTRIES, 2), EMPTY, dtype=np.uint32)
    buckets[:, :, 0][b_sel] = unplanes(r, "<u4", n_entries)
    buckets[:, :, 1][b_sel] = unplanes(r, "<u4", n_entries)
    n_raw = int((~b_canon).sum())
    buckets[~b_canon] = unplanes(r, "<u4", n_raw * 2 * BUCKET_ENTRIES).reshape(n_raw, BUCKET_ENTRIES, 2)
    return bucket_ids, buckets


@dataclass
class _CellSections:
    """A packed delta's cell sections, read (slots and counts checked) and not yet put together, so that
    the cells of several parts are put together at once (`_assemble_cells`)."""

    slot_gaps: memoryview  # the slots' varint section (decoded with the other parts': gaps_decode_parts)
    n: int  # cells
    counts: memoryview  # a byte per cell: its points, or RAW
    keys: memoryview  # 4 byte planes of nc key words
    pos: memoryview  # 2 byte planes of n_points position fields
    normal: memoryview
    ao: memoryview
    raw: memoryview  # 4 byte planes of the raw cells' points


_CELL_COUNTS = bytes(range(POINTS_PER_CELL + 1)) + bytes([RAW])  # the count bytes a cell may have


def _read_packed_cells(r: Reader, lc: int, nc: int) -> _CellSections:
    slot_gaps = r.take(lc)
    counts = r.take(nc)
    n_points, n_raw = _points_of_counts(counts)
    keys = r.take(4 * nc)
    pos = r.take(2 * n_points)
    return _CellSections(slot_gaps, nc, counts, keys, pos, r.take(n_points), r.take(n_points),
                         r.take(4 * POINTS_PER_CELL * n_raw))


def _points_of_counts(counts: memoryview) -> tuple[int, int]:
    """(points, raw cells) of a part's count bytes, checked; with bytes methods (a part is often a few dozen
    cells: numpy calls would cost more than the work)."""
    b = counts.tobytes()
    if b.translate(None, _CELL_COUNTS):
        raise PayloadError(f"cell: entry count above {POINTS_PER_CELL}")
    n_raw = b.count(RAW)
    total = sum(b) if len(b) <= 256 else int(np.frombuffer(b, np.uint8).sum(dtype=np.int64))
    return total - RAW * n_raw, n_raw


_CELLS_ONLY_HEAD = struct.Struct("<BIIIIIII")  # _COUNTS then _PACKED_LENGTHS, as a packed part begins
_NO_IDS = _empty_u32(0)
_NO_TRANSFORMS = np.zeros((0, 4, 4), np.float32)
_NO_BUCKETS = _empty_u32(0, BUCKET_ENTRIES, 2)
for _a in (_NO_IDS, _NO_TRANSFORMS, _NO_BUCKETS):
    _a.flags.writeable = False  # shared by every part read by _read_cells_part


def _read_cells_part(r: Reader, limits: Limits) -> tuple[_Part, Layout]:
    """_read_part for a packed part of cells only (the tiles of an Update of parts): its sections are cut
    straight off the payload from its counts, with one bounds check. Anything else (another layout or
    content, a count over a limit, too few bytes) is read by _read_part, which reads or refuses it."""
    view, start = r.view, r.pos
    head = _CELLS_ONLY_HEAD.size
    if len(view) - start < head:
        return _read_part(r, limits)
    layout, capacity, k, nb, nc, lt, lb, lc = _CELLS_ONLY_HEAD.unpack_from(view, start)
    at = start + head + lc  # the count bytes
    if (layout != Layout.PACKED or k or nb or lt or lb or capacity > limits.max_cell_capacity
            or nc > limits.max_cells_per_message or at + nc > len(view)):
        return _read_part(r, limits)
    counts = view[at : at + nc]
    n_points, n_raw = _points_of_counts(counts)
    keys = at + nc
    pos = keys + 4 * nc
    normal = pos + 2 * n_points
    ao = normal + n_points
    raw = ao + n_points
    end = raw + 4 * POINTS_PER_CELL * n_raw
    if end > len(view):
        return _read_part(r, limits)
    r.pos = end
    cells = _CellSections(view[start + head : at], nc, counts, view[keys:pos], view[pos:normal], view[normal:ao],
                          view[ao:raw], view[raw:end])
    return _Part(capacity, _NO_IDS, _NO_TRANSFORMS, _NO_IDS, _NO_BUCKETS, cells), Layout.PACKED


def _planes_of(parts: list[memoryview], itemsize: int, dtype) -> np.ndarray:
    """Byte planes written part by part (planes()) -> the values of all parts, in order. Each part's planes
    are cut apart by slicing and joined plane by plane (bytes work), so that one numpy pass turns them all
    into values (per-part numpy calls would cost more than the work on parts of a few dozen cells)."""
    if len(parts) == 1:
        joined = parts[0]
    else:
        sizes = [len(p) // itemsize for p in parts]
        joined = b"".join([p[j * n : (j + 1) * n] for j in range(itemsize) for p, n in zip(parts, sizes)])
    rows = np.frombuffer(joined, np.uint8).reshape(itemsize, -1)
    return np.ascontiguousarray(rows.T).view(np.dtype(dtype).newbyteorder("<")).reshape(-1).astype(dtype)


_BELOW_0X80 = bytes(range(0x80))  # bytes.translate(None, _BELOW_0X80) leaves the bytes with the top bit set


def _assemble_cells(sections: list[_CellSections]) -> tuple[np.ndarray, np.ndarray]:
    """(cell slots, cells) of one or more parts' cell sections, in part order. The parts' sections are
    joined as bytes first, so that a few numpy calls put all the cells together."""
    slots = gaps_decode_parts([s.slot_gaps for s in sections], [s.n for s in sections], "cell slots")
    nc = len(slots)
    cells = np.zeros((nc, CELL_WORDS), dtype=np.uint32)
    if not nc:
        return slots, cells
    counts = b"".join(s.counts for s in sections)
    c_count = np.frombuffer(counts, np.uint8)
    cells[:, KEY_WORD] = _planes_of([s.keys for s in sections], 4, np.uint32)
    halves = [len(s.pos) // 2 for s in sections]  # a position's low byte plane, then its high one
    high = b"".join([s.pos[h:] for s, h in zip(sections, halves)])
    if high.translate(None, _BELOW_0X80):
        raise PayloadError("cell: position field above 15 bits")
    # a point word's bytes, lowest first: AO, normal, the position's low byte, its high byte (the allocated
    # bit is set after): one row of bytes each, for every point of every part
    fields = b"".join([*(s.ao for s in sections), *(s.normal for s in sections),
                       *(s.pos[:h] for s, h in zip(sections, halves)), high])
    words = np.ascontiguousarray(np.frombuffer(fields, np.uint8).reshape(4, -1).T).view("<u4").reshape(-1)
    n_raw = counts.count(RAW)
    p_sel = _expand_leading(np.where(c_count != RAW, c_count, 0) if n_raw else c_count, POINTS_PER_CELL)
    points = cells[:, :POINTS_PER_CELL]
    points[p_sel] = words | ALLOCATED_BIT
    if n_raw:
        points[c_count == RAW] = _planes_of([s.raw for s in sections], 4, np.uint32).reshape(-1, POINTS_PER_CELL)
    return slots, cells


# ------------------------------------------------------------------------------------------- public API


def encode_delta(delta: GridDelta, layout: Layout = Layout.PACKED) -> bytes:
    return _encode_plain(delta) if layout == Layout.PLAIN else _encode_packed(delta)


@dataclass
class _Part:
    """One grid delta as read: its cells as (slots, cells), or as packed sections not yet put together."""

    capacity: int
    transform_ids: np.ndarray
    transforms: np.ndarray
    bucket_ids: np.ndarray
    buckets: np.ndarray
    cells: tuple | _CellSections


def decode_delta(r: Reader, limits: Limits = DEFAULT_LIMITS) -> tuple[GridDelta, Layout]:
    """Read a grid delta from the rest of a payload (both layouts); counts are checked before any array
    is allocated and the delta is checked structurally."""
    part, layout = _read_part(r, limits)
    r.done()
    return _union([part], limits), layout


def decode_delta_parts(r: Reader, limits: Limits = DEFAULT_LIMITS) -> tuple[GridDelta, Layout]:
    """Read one or more grid deltas (parts) filling the rest of a payload, as an Update carries them, and
    give their union (`union_of_parts`). Every part is checked as a delta of its own would be; the cells
    of all parts are put together at once (a part costs little more than its bytes)."""
    return _read_parts(r, limits, _read_cells_part)


def _read_parts(r: Reader, limits: Limits, read_part) -> tuple[GridDelta, Layout]:
    """decode_delta_parts with `read_part` reading each part (_read_part reads any part: tests compare)."""
    part, layout = read_part(r, limits)
    parts = [part]
    while not r.at_end():
        part, part_layout = read_part(r, limits)
        if part_layout != layout:
            raise PayloadError(f"grid delta parts in layouts {layout.name} and {part_layout.name}")
        parts.append(part)
    return _union(parts, limits), layout


def union_of_parts(parts: list[GridDelta], limits: Limits = DEFAULT_LIMITS) -> GridDelta:
    """The one delta that several parts make together. Parts share the cell capacity and change disjoint
    transforms, buckets and cells (so the order they are applied in does not matter); the union is checked
    like any delta (limits count every part's rows together)."""
    return _union([_Part(p.cell_capacity, p.transform_ids, p.transforms, p.bucket_ids, p.buckets,
                         (p.cell_slots, p.cells)) for p in parts], limits)


def _union(parts: list[_Part], limits: Limits) -> GridDelta:
    capacity = parts[0].capacity
    if any(p.capacity != capacity for p in parts):
        raise PayloadError("grid delta parts with different cell capacities")
    if isinstance(parts[0].cells, _CellSections):
        slots, cells = _assemble_cells([p.cells for p in parts])
    else:
        slots, cells = (np.concatenate([p.cells[i] for p in parts]) for i in (0, 1))
    kinds = {"transform": ([p.transform_ids for p in parts], [p.transforms for p in parts]),
             "bucket": ([p.bucket_ids for p in parts], [p.buckets for p in parts])}
    out = {}
    for what, (ids, rows) in kinds.items():
        full = [j for j, i in enumerate(ids) if len(i)] or [0]  # (most parts carry cells only)
        if len(full) == 1:
            out[what] = (ids[full[0]], rows[full[0]]) if len(ids[full[0]]) else (ids[0].copy(), rows[0].copy())
        else:
            out[what] = _sorted_union(what, [len(ids[j]) for j in full], np.concatenate([ids[j] for j in full]),
                                      np.concatenate([rows[j] for j in full]))
    sizes = [p.cells.n if isinstance(p.cells, _CellSections) else len(p.cells[0]) for p in parts]
    slots, cells = _sorted_union("cell", sizes, slots, cells)
    delta = GridDelta(capacity, *out["transform"], *out["bucket"], slots, cells)
    delta.check(limits)
    return delta


def _sorted_union(what: str, sizes: list[int], ids: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parts' ids (each part's sorted and unique, as in any delta; `sizes` ids each) and rows,
    concatenated -> sorted by id; an id in two parts is refused."""
    if len(sizes) == 1 or len(ids) < 2:
        return ids, rows
    rising = ids[1:] > ids[:-1]
    starts = np.cumsum(sizes)[:-1]
    starts = starts[(starts > 0) & (starts < len(ids))]
    rising[starts - 1] = True  # a part may begin below the previous one's end
    if not rising.all():
        raise PayloadError(f"{what} indices are not sorted and unique")
    order = np.argsort(ids, kind="stable")
    ids = ids[order]
    if not np.all(ids[1:] > ids[:-1]):
        raise PayloadError(f"grid delta parts overlap: a {what} index in two parts")
    return ids, rows[order]


def _read_part(r: Reader, limits: Limits) -> tuple[_Part, Layout]:
    layout, capacity, k, nb, nc = r.unpack(_COUNTS)
    _check_counts(capacity, k, nb, nc, limits)
    if layout == Layout.PLAIN:
        part = _decode_plain(r, capacity, k, nb, nc)
    elif layout == Layout.PACKED:
        part = _decode_packed(r, capacity, k, nb, nc)
    else:
        raise PayloadError(f"unknown grid delta layout {layout}")
    return part, Layout(layout)


def state_digest(instances: np.ndarray, buckets: np.ndarray, cells: np.ndarray, transforms: np.ndarray) -> str:
    """sha256 over the exact bytes of a grid state (server or mirror), for bit-exact comparisons."""
    h = hashlib.sha256()
    for a in (instances, buckets, cells, transforms):
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.reshape(-1).view(np.uint8))  # the array's own bytes, not a copy
    return h.hexdigest()
