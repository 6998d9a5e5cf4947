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

from protocol.session import GRID_REPLACED_CLOSE, GRID_REPLACED_REASON, reconnect_at_once, scene_hash_bytes
from psao_scene import load_scene
from psao_server.progressive import ProgressiveSettings, coarse_bake_settings, wants_coarse_grid
from psao_server.settings import BakeSettings
from serving import HANG_S, server_url

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


def test_progressive_start_replaces_the_coarse_grid_and_mirrors_stay_exact(tmp_path):
    """A client that connects at once gets the coarse grid, is closed with GRID_REPLACED_CLOSE when the full
    grid is ready, reconnects by itself, gets the full grid and then its refinement; after every message
    that left nothing pending its mirror equals the server's state, on both grids."""
    from psao_client.connection import MirrorClient, scene_camera_feed

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
        if len(sizes) == 2:
            updates_after[0] += 1
            if updates_after[0] >= 3:
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
    server = {(d["conn"], d["seq"]): d["digest"] for d in map(json.loads, slog.read_text().splitlines())}
    mine = [json.loads(line) for line in clog.read_text().splitlines()]
    pairs = [(server[(d["conn"], d["seq"])], d["digest"]) for d in mine if (d["conn"], d["seq"]) in server]
    assert all(a == b for a, b in pairs)
    assert len({d["conn"] for d in mine if (d["conn"], d["seq"]) in server}) == 2  # compared on both grids
