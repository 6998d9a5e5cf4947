"""The service in-process with clients in-process, over real loopback sockets: every codec and layout,
a snapshot in many small chunks while ticks keep editing and the cell pool grows."""
from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from psao.protocol.codecs import Codec
from psao.protocol.updates import Layout
from psao.client.connection import MirrorClient
from psao.server.net.clients import Client, SnapshotPlan
from psao.server.grid import Grid
from psao.server.net.service import Service
from psao.server.settings import ServeSettings
from psao.server.tick.testhook import random_edits
from psao.protocol.limits import Limits
from test_bad_input_server import HASH, make_grid


class EditAndGrow:
    """Random edits every tick (points set, moved, freed, allocated); now and then a burst of new points
    (the pool grows)."""

    def __init__(self, seed=0):
        self.rng = np.random.default_rng(seed)
        self.k = 0
        self.grew = 0

    def __call__(self, grid: Grid, t: float) -> None:
        self.k += 1
        random_edits(grid, self.rng, 40)
        if self.k % 25 == 8:
            before = len(grid.cells)
            n = 3 * len(grid.cells)
            pos = self.rng.random((n, 3)) * 0.98 + 0.01
            pos[:, 2] = self.rng.choice([0.0, 0.5, 0.99], n)
            nrm = np.tile(np.float32([0, 0, 1]), (n, 1))
            grid.insert_points(0, pos, nrm, self.rng.integers(0, 256, n).astype(np.uint32))
            self.grew += len(grid.cells) > before


def read_jsonl(path):
    return [json.loads(line) for line in open(path)] if path.exists() else []


async def serve_and_mirror(tmp_path, codec, layout, frames=90):
    grid = make_grid(1500)
    hook = EditAndGrow()
    settings = ServeSettings(port=0, tick_hz=60, codec=codec, layout=layout, stats_interval=1e9,
                             snapshot_cells_per_chunk=64, digest_log=tmp_path / "server.jsonl")
    service = Service(grid, HASH, settings, tick=hook)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await ready.wait()
    url = f"ws://127.0.0.1:{service.port}"
    seen = []
    clients = [MirrorClient(url, HASH, codecs={codec, Codec.NONE}, digest_log=tmp_path / f"c{i}.jsonl",
                            on_update=lambda mirror, transforms, tick: seen.append((len(mirror.cells), tick)))
               for i in range(2)]
    try:
        stats = await asyncio.wait_for(asyncio.gather(*(c.run(frames=frames) for c in clients)), 60)
    finally:
        stop.set()
        await task
    return hook, stats, seen, clients


@pytest.mark.parametrize("codec, layout", [(Codec.ZSTD_STREAM, Layout.PACKED), (Codec.ZSTD, Layout.PLAIN),
                                           (Codec.LZ4, Layout.PACKED), (Codec.NONE, Layout.PLAIN)])
def test_mirror_exact_through_growth(tmp_path, codec, layout):
    hook, stats, seen, clients = asyncio.run(serve_and_mirror(tmp_path, codec, layout))
    assert hook.grew >= 1
    capacities = {c for c, _ in seen}
    assert len(capacities) >= 2  # the mirrors followed the pool as it grew
    server = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(tmp_path / "server.jsonl")}
    for i, s in enumerate(stats):
        assert s.updates == 90 and s.codec == {Codec.ZSTD_STREAM: "zstd-stream", Codec.ZSTD: "zstd",
                                                Codec.LZ4: "lz4", Codec.NONE: "none"}[codec]
        mine = read_jsonl(tmp_path / f"c{i}.jsonl")
        both = [d for d in mine if (d["conn"], d["seq"]) in server]
        assert len(both) >= 60
        assert all(server[(d["conn"], d["seq"])] == d["digest"] for d in both)
        snapshot_chunks = sum(1 for d in mine if d["tick"] == -1)
        assert snapshot_chunks >= 5


def test_pending_sets_fold_ticks_and_follow_capacity():
    limits = Limits(max_cells_per_message=3, max_buckets_per_message=100)
    c = Client("peer", n_buckets=8, capacity=10)
    c.mark(np.array([1, 2]), np.array([0, 5, 9]), 10)
    c.mark(np.array([2]), np.array([5, 12]), 16)  # the pool grew to 16
    assert c.wake.is_set()
    b, cells, drained = c.take_pending(limits, 16)
    assert b.tolist() == [1, 2] and cells.tolist() == [0, 5, 9] and not drained
    b, cells, drained = c.take_pending(limits, 16)
    assert b.tolist() == [] and cells.tolist() == [12] and drained
    c.mark(np.array([], np.uint32), np.array([3, 15]), 16)
    b, cells, drained = c.take_pending(limits, 32)  # the pool grew again: nothing pending in the new slots
    assert cells.tolist() == [3, 15] and drained and len(c.pending_cells) == 32
    with pytest.raises(ValueError):  # the masks are views for reading: a write would bypass the counts
        c.pending_cells[0] = True
    t = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
    assert c.read_transforms(t).tolist() == [0, 1, 2]
    t2 = t.copy()
    t2[1, 0, 3] = 1.0
    assert c.changed_transforms(t).tolist() == [] and c.read_transforms(t2).tolist() == [1]


def test_pending_set_equals_a_plain_mask_through_random_sets_unsets_and_growth():
    """PendingSet keeps a count and the indices set since it last listed them (so a client's planning
    costs what is pending, not the capacity): through any sequence of sets, unsets, listings and growth,
    its count, mask and listing equal those of a plain mask."""
    from psao.server.net.clients import PendingSet

    rng = np.random.default_rng(7)
    size = 1000
    pend, plain = PendingSet(size), np.zeros(size, bool)
    for step in range(3000):
        op = rng.integers(0, 10)
        idx = np.sort(rng.choice(size, int(rng.integers(0, 60)), replace=False))
        if op < 4:
            pend.set(idx)
            plain[idx] = True
        elif op < 8:
            pend.unset(idx)
            plain[idx] = False
        elif op < 9:
            np.testing.assert_array_equal(pend.indices(), np.flatnonzero(plain))
        elif size < 4000:
            size += int(rng.integers(1, 300))
            pend.grow(size)
            plain = np.concatenate([plain, np.zeros(size - len(plain), bool)])
        assert pend.count == plain.sum() and len(pend) == pend.count
        np.testing.assert_array_equal(pend.mask, plain)
    pend.set(np.arange(size))  # more than an eighth of the capacity at once: it lists by a scan from then on
    plain[:] = True
    np.testing.assert_array_equal(pend.indices(), np.flatnonzero(plain))


def test_snapshot_plan_covers_everything_allocated_in_chunks():
    grid = make_grid(2000)
    plan = SnapshotPlan.of(grid, Limits(), cells_per_chunk=50)
    cells = np.concatenate(plan.cell_chunks)
    buckets = np.concatenate(plan.bucket_chunks)
    assert np.array_equal(cells, grid.allocated_cells())
    assert np.array_equal(buckets, grid.allocated_buckets())
    assert len(plan) == -(-len(cells) // 50) and max(len(c) for c in plan.cell_chunks) <= 50
