"""MirrorClient's digest log: the mirror is hashed on a worker thread while the receive loop goes on with
its other work (camera sends), and each line is the digest of the mirror after exactly that message."""
from __future__ import annotations

import asyncio
import time

import numpy as np

from psao.client.connection import MirrorClient
from psao.client.mirror import Mirror
from psao.server.net.service import Service
from psao.server.settings import ServeSettings
from test_bad_input_server import HASH, make_grid
from test_streaming_service import EditAndGrow, read_jsonl

SLOW_DIGEST_S = 0.3  # how long each digest takes here (a large mirror's sha256 takes milliseconds)
DIGESTED = (3, 20, 40)  # messages whose digest the client logs (Welcome is message 0)


def test_digest_off_the_loop_and_exact(tmp_path, monkeypatch):
    spans: list[tuple[float, float]] = []  # (start, end) of every digest
    real = Mirror.digest

    def slow_digest(self):
        t0 = time.perf_counter()
        time.sleep(SLOW_DIGEST_S)  # (on the loop, this would hold up every camera send meanwhile)
        out = real(self)
        spans.append((t0, time.perf_counter()))
        return out

    monkeypatch.setattr(Mirror, "digest", slow_digest)
    camera_at: list[float] = []
    view, proj = np.eye(4, dtype=np.float32), np.eye(4, dtype=np.float32)

    def camera(_t):
        camera_at.append(time.perf_counter())
        return view, proj

    async def run():
        settings = ServeSettings(port=0, tick_hz=60, stats_interval=1e9, snapshot_cells_per_chunk=64,
                                 digest_log=tmp_path / "server.jsonl")
        service = Service(make_grid(1500), HASH, settings, tick=EditAndGrow(seed=3))
        stop, ready = asyncio.Event(), asyncio.Event()
        task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
        await ready.wait()
        client = MirrorClient(f"ws://127.0.0.1:{service.port}", HASH, camera=camera, camera_hz=50.0,
                              digest_log=tmp_path / "client.jsonl", digest_if=lambda _conn, seq: seq in DIGESTED)
        logged = []  # the digest of the mirror right after each Update, as the client applied them
        client.on_update = lambda mirror, *_: logged.append(real(mirror))
        try:
            await asyncio.wait_for(client.run(frames=60), 60)
        finally:
            stop.set()
            await task
        return client, logged

    client, after_update = asyncio.run(run())
    mine = read_jsonl(tmp_path / "client.jsonl")
    assert [d["seq"] for d in mine] == list(DIGESTED) and len(spans) == len(DIGESTED)
    # the loop sent cameras while each digest was being worked out
    for t0, t1 in spans:
        assert sum(t0 < t < t1 for t in camera_at) >= 3
    # each line is the mirror after its own message: Updates are messages snapshot chunks + 1 onwards
    server = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(tmp_path / "server.jsonl")}
    compared = [d for d in mine if (d["conn"], d["seq"]) in server]
    assert all(server[d["conn"], d["seq"]] == d["digest"] for d in compared)
    updates_from = client.stats.messages - client.stats.updates  # Welcome and the snapshot chunks
    updates = [d for d in mine if d["seq"] >= updates_from]
    assert updates and client.stats.reconnects == 0
    for d in updates:
        assert d["digest"] == after_update[d["seq"] - updates_from]  # (its index among the Updates)
