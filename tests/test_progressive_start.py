"""`psao serve --progressive`: a coarse first grid at once, the full grid swapped in behind it (clients
reconnect on GRID_REPLACED_CLOSE), mirrors exact on both grids."""
from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from pathlib import Path

from websockets.frames import Close

from psao.protocol.session import GRID_REPLACED_CLOSE, GRID_REPLACED_REASON, reconnect_at_once, scene_hash_bytes
from psao.scene import load_scene
from psao.server.tick.progressive import ProgressiveSettings, coarse_bake_settings, wants_coarse_grid
from psao.server.settings import BakeSettings
from serving import HANG_S, server_url
from tracing import full_trace

ROOT = Path(__file__).resolve().parents[1]


def test_grid_replaced_close_frame_bytes():
    """The close frame's payload: code 4000 big-endian, then the reason in UTF-8 (RFC 6455 5.5.1)."""
    assert Close(GRID_REPLACED_CLOSE, GRID_REPLACED_REASON).serialize() == b"\x0f\xa0grid replaced: reconnect"
    assert reconnect_at_once(4000)
    assert not any(reconnect_at_once(c) for c in (None, 1000, 1001, 1006, 1008, 1011, 4001))


def test_coarse_grid_only_when_the_full_one_is_much_larger():
    scene = load_scene("builtin:courtyard")
    full = BakeSettings(density=16.0, rays=8)
    assert wants_coarse_grid(scene, full, ProgressiveSettings(first_points=2000))
    assert not wants_coarse_grid(scene, full, ProgressiveSettings(first_points=0))
    assert not wants_coarse_grid(scene, full, ProgressiveSettings(first_points=10**6))
    coarse = coarse_bake_settings(full, 2000, 2)
    assert (coarse.density, coarse.points, coarse.rays, coarse.spawn_ratio, coarse.skip_buried) == (None, 2000.0, 2, 1.0,
                                                                                                   False)
    assert coarse.sampling().factor() == 1  # spawned uniformly: no detail levels at so few points


def test_progressive_start_replaces_the_coarse_grid_and_mirrors_stay_exact(tmp_path):
    """A client that connects at once gets the coarse grid, is closed with GRID_REPLACED_CLOSE when the full
    grid is ready, reconnects by itself, gets the full grid and then its refinement; after every message
    that left nothing pending its mirror equals the server's state, on both grids."""
    from psao.client.connection import MirrorClient, scene_camera_feed

    err, slog, clog = tmp_path / "serve.err", tmp_path / "server.jsonl", tmp_path / "client.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", "builtin:courtyard", "--progressive", "--density", "16",
                             "--rays", "8", "--tick-rays", "2", "--first-points", "2000", "--tick-hz", "20", "--no-cull",
                             "--port", "0", "--digest-log", str(slog)], cwd=ROOT, stderr=open(err, "w"),
                            stdout=subprocess.DEVNULL)
    scene = load_scene("builtin:courtyard")
    sizes: list[int] = []  # allocated cells of the mirror at each complete snapshot
    updates_after: list[int] = [0]

    def on_snapshot(mirror):
        sizes.append(mirror.allocated_cells())

    def on_update(mirror, transforms, tick):
        # one refinement Update after the full grid: how many there are depends on how the refiner's batches
        # fall between ticks (on a busy machine several land in one tick)
        if len(sizes) == 2:
            updates_after[0] += 1
            client.stop()

    try:
        url = server_url(proc, err)
        client = MirrorClient(url, scene_hash_bytes(scene.content_hash()), camera=scene_camera_feed(scene),
                              on_snapshot=on_snapshot, on_update=on_update, digest_log=clog, reconnect=False)
        stats = asyncio.run(asyncio.wait_for(client.run(), HANG_S))
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=HANG_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    log = err.read_text()
    assert "coarse first grid of courtyard" in log and "grid replaced" in log, log
    assert stats.grid_replacements == 1 and stats.reconnects == 0
    assert len(sizes) == 2 and sizes[0] < sizes[1], sizes  # the coarse grid first, then the full one
    assert updates_after[0] >= 1  # then the full grid's refinement
    server = {(d["conn"], d["seq"]): d["digest"] for d in map(json.loads, slog.read_text().splitlines())}
    mine = [json.loads(line) for line in clog.read_text().splitlines()]
    pairs = [(server[(d["conn"], d["seq"])], d["digest"]) for d in mine if (d["conn"], d["seq"]) in server]
    assert all(a == b for a, b in pairs)
    assert len({d["conn"] for d in mine if (d["conn"], d["seq"]) in server}) == 2  # compared on both grids


def test_local_refiner_brings_every_static_point_to_its_full_trace():
    """--progressive without a cluster: the bake's own tracer refines waiting static points in batches on a
    thread of its own beside the ticks; once nothing waits, every static point holds exactly the AO of a full
    trace of its target ray set (as a full bake gives)."""
    import numpy as np

    from psao.protocol import pointword as pw
    from psao.server.bake import bake_scene
    from psao.server.tick.budget import BudgetSettings
    from psao.server.tick.refine import BackgroundTracer, ClusterRefiner, RefineSettings
    from psao.server.settings import TickSettings
    from psao.server.tick.server_tick import ServerTick

    scene = load_scene("builtin:courtyard")
    bake = bake_scene(scene, BakeSettings(density=8, rays=8, seed=5, workers=1), show_progress=False)
    refiner = ClusterRefiner(BackgroundTracer(bake.tracer), RefineSettings(batch_points=2000))
    settings = TickSettings(rays=32, seed=5, budget=BudgetSettings(round_rays=8, budget_ms=0.1), selection=True,
                            workers=1)
    tick = ServerTick(bake, settings, close_bake_tracer=False, refiner=refiner)
    try:
        static = refiner.static
        for _ in range(10_000):
            if not len(tick.queue.waiting(static)) and not refiner.batches:
                break
            assert refiner.wait(HANG_S)
            tick.apply(tick.prepare(0.0))
        assert not len(tick.queue.waiting(static)) and refiner.points_done > 0
        ids = np.flatnonzero(static & tick.present())
        vis = full_trace(tick, tick.animator.frame(0.0), ids, 32, 5)
        got = (tick.grid.cells[tick.slot[ids], tick.index[ids]] & np.uint32(0xFF)).astype(np.int64)
        # a code within the tick's write threshold of the stored one is not written (noise kept off the wire)
        off = np.abs(got - pw.quantise_ao(vis).astype(np.int64))
        assert off.max() <= settings.threshold, (ids[off > settings.threshold], got[off > settings.threshold])
    finally:
        tick.close()
