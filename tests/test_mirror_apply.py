"""The mirror's apply (whole buckets, cells and transforms written by index, in a few numpy assignments)
against a straightforward reference that writes one row at a time, on random deltas: the same arrays, the
same dirty sets; also through the wire (encode, Update.parse) and through a lazy mirror fed by bytes."""
from __future__ import annotations

import numpy as np
import pytest

from psao.client.mirror import Mirror
from psao.protocol import messages as m
from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, EMPTY, FREE_CELL, INSTANCE_DTYPE
from psao.protocol.limits import DEFAULT_LIMITS
from psao.protocol.updates import GridDelta, Layout, encode_delta, state_digest

N_BUCKETS = 300
N_INSTANCES = 5


class ReferenceMirror:
    """What applying a delta means, one row at a time in Python: its capacity cuts or grows the cells
    (free cells), then every transform, bucket and cell of the delta is written at its index."""

    def __init__(self, instances: np.ndarray, n_buckets: int, capacity: int):
        self.instances = instances
        self.buckets = [[[int(EMPTY), int(EMPTY)] for _ in range(BUCKET_ENTRIES)] for _ in range(n_buckets)]
        self.cells = [[int(w) for w in FREE_CELL] for _ in range(capacity)]
        self.transforms = [np.eye(4, dtype=np.float32).tolist() for _ in range(len(instances))]
        self.dirty_buckets: set[int] = set()
        self.dirty_cells: set[int] = set()

    def apply(self, d: GridDelta) -> None:
        if d.cell_capacity < len(self.cells):
            del self.cells[d.cell_capacity:]
        while len(self.cells) < d.cell_capacity:
            self.cells.append([int(w) for w in FREE_CELL])
        for i, t in zip(d.transform_ids.tolist(), d.transforms.tolist()):
            self.transforms[i] = t
        for i, b in zip(d.bucket_ids.tolist(), d.buckets.tolist()):
            self.buckets[i] = b
            self.dirty_buckets.add(i)
        for i, c in zip(d.cell_slots.tolist(), d.cells.tolist()):
            self.cells[i] = c
            self.dirty_cells.add(i)
        self.dirty_cells = {i for i in self.dirty_cells if i < len(self.cells)}

    def digest(self) -> str:
        return state_digest(self.instances, np.array(self.buckets, np.uint32).reshape(-1, BUCKET_ENTRIES, 2),
                            np.array(self.cells, np.uint32).reshape(-1, CELL_WORDS),
                            np.array(self.transforms, np.float32).reshape(-1, 4, 4))


def random_instances(rng) -> np.ndarray:
    inst = np.zeros(N_INSTANCES, INSTANCE_DTYPE)
    inst["bucket_offset"] = np.arange(N_INSTANCES) * (N_BUCKETS // N_INSTANCES)
    inst["bucket_count"] = N_BUCKETS // N_INSTANCES
    return inst


def random_cells(rng, n: int) -> np.ndarray:
    """Cells as the grid holds them (a few points with the allocated bit, rest zero) and some of any
    words (sent whole as RAW), so both packed forms are exercised."""
    cells = np.zeros((n, CELL_WORDS), np.uint32)
    points = rng.integers(0, 8, n)
    words = rng.integers(0, 1 << 31, (n, CELL_WORDS), dtype=np.uint32) | np.uint32(1 << 31)
    mask = np.arange(CELL_WORDS - 1)[None, :] < points[:, None]
    cells[:, :CELL_WORDS - 1][mask] = words[:, :CELL_WORDS - 1][mask]
    cells[:, CELL_WORDS - 1] = rng.integers(0, 1 << 20, n)
    raw = rng.random(n) < 0.1
    cells[raw] = rng.integers(0, 1 << 32, (int(raw.sum()), CELL_WORDS), dtype=np.uint32)
    return cells


def random_delta(rng, capacity: int) -> GridDelta:
    """Sorted unique random indices, clustered (small gaps: one-byte varints) or spread (large gaps)."""
    def ids(top: int, most: int) -> np.ndarray:
        n = int(rng.integers(0, min(top, most) + 1))
        if rng.random() < 0.5:  # a run near one place
            start = int(rng.integers(0, max(top - 3 * n, 1)))
            return np.sort(rng.choice(np.arange(start, min(start + 3 * n + 1, top)), min(n, top - start), replace=False))
        return np.sort(rng.choice(top, n, replace=False))

    t = ids(N_INSTANCES, N_INSTANCES)
    b = ids(N_BUCKETS, 60)
    c = ids(capacity, 400) if capacity else np.zeros(0, np.int64)
    buckets = rng.integers(0, 1 << 32, (len(b), BUCKET_ENTRIES, 2), dtype=np.uint32)
    used = rng.integers(0, BUCKET_ENTRIES + 1, len(b))
    buckets[np.arange(BUCKET_ENTRIES)[None, :] >= used[:, None]] = EMPTY
    transforms = rng.normal(size=(len(t), 4, 4)).astype(np.float32)
    return GridDelta(capacity, t, transforms, b, buckets, c, random_cells(rng, len(c)))


def capacities(rng, steps: int) -> list[int]:
    """A cell capacity per delta: mostly the same, sometimes grown, now and then cut."""
    cap, out = int(rng.integers(1, 600)), []
    for _ in range(steps):
        r = rng.random()
        cap = cap + int(rng.integers(1, 400)) if r < 0.2 else max(1, cap - int(rng.integers(1, 200))) if r < 0.3 else cap
        out.append(cap)
    return out


@pytest.mark.parametrize("seed", range(12))
def test_apply_equals_row_by_row_reference(seed):
    rng = np.random.default_rng(seed)
    inst = random_instances(rng)
    caps = capacities(rng, 25)
    mirror = Mirror(inst, N_BUCKETS, caps[0])
    ref = ReferenceMirror(inst, N_BUCKETS, caps[0])
    mirror.take_dirty()  # (a new mirror's first call: everything)
    for k, cap in enumerate(caps):
        d = random_delta(rng, cap)
        mirror.apply(d)
        ref.apply(d)
        if k % 5 == 4:
            b, c = mirror.take_dirty()
            assert b.tolist() == sorted(ref.dirty_buckets) and c.tolist() == sorted(ref.dirty_cells)
            ref.dirty_buckets.clear()
            ref.dirty_cells.clear()
        assert mirror.digest() == ref.digest()
    assert mirror.version == len(caps)


@pytest.mark.parametrize("seed", range(8))
def test_deltas_through_the_wire_apply_as_the_reference(seed):
    """Each random delta encoded (both layouts) in an Update of one or several parts (disjoint cells),
    parsed, and applied to an eager mirror and to a lazy one fed the bytes, equals the reference applying
    the delta itself; the lazy mirror, completed, equals it too."""
    rng = np.random.default_rng(100 + seed)
    inst = random_instances(rng)
    caps = capacities(rng, 15)
    layout = Layout.PACKED if seed % 4 else Layout.PLAIN
    eager = Mirror(inst, N_BUCKETS, caps[0])
    lazy = Mirror(inst, N_BUCKETS, caps[0], DEFAULT_LIMITS)
    ref = ReferenceMirror(inst, N_BUCKETS, caps[0])
    for tick, cap in enumerate(caps):
        d = random_delta(rng, cap)
        payload = m.Update(tick, tick / 60, d, layout).serialize()
        if len(d.cell_slots) > 2 and rng.random() < 0.5:  # the cells split into parts, as a tiled Update
            cut = np.sort(rng.choice(np.arange(1, len(d.cell_slots)), 2, replace=False))
            pieces = np.split(np.arange(len(d.cell_slots)), cut)
            first = GridDelta(cap, d.transform_ids, d.transforms, d.bucket_ids, d.buckets,
                              d.cell_slots[pieces[0]], d.cells[pieces[0]])
            payload = m.Update(tick, tick / 60, first, layout).serialize() + b"".join(
                encode_delta(GridDelta(cap, cell_slots=d.cell_slots[p], cells=d.cells[p]), layout) for p in pieces[1:])
        got = m.Update.parse(payload).delta
        assert got.equals(d)
        eager.apply(got)
        lazy.received(len(payload))
        lazy.apply(got)
        ref.apply(d)
        assert eager.digest() == ref.digest()
    lazy.complete()
    assert lazy.digest() == ref.digest()
