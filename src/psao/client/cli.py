"""`psao client URL [SCENE]`: connect to a PSAO server, keep an exact mirror of its grid, report.

Headless unless --render (frames to PNG) or --window. The receive loop is
`psao.client.connection.MirrorClient`; `build_client(args, scene, on_update=..., on_frame=...)` lets another sub-command reuse the same options and plug in a per-update
callback `on_update(mirror, transforms, tick)` or a per-frame one `on_frame(mirror)` (--render: at --fps).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import threading
import time
from pathlib import Path

from psao.protocol.codecs import CODEC_NAMES
from psao.options import comma_list, default
from psao.client.errors import ConnectError
from psao.client.settings import ConnectSettings, FrameSettings


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("url", help="server URL, e.g. ws://127.0.0.1:8765")
    p.add_argument("scene", nargs="?", default=None, metavar="SCENE",
                   help="the client's own copy of the scene (builtin:NAME, a .toml or a mesh file), checked against "
                        "the server's by hash; without it the client loads the server's scene from the server")
    p.add_argument("--frames", type=int, default=None,
                   help="stop after the snapshot and N updates (a static server, sending no update after the "
                        "snapshot: after N tick periods, at least 5 s), or with --render N rendered frames "
                        "(0: right after the snapshot; default: run until Ctrl-C)")
    p.add_argument("--json", action="store_true", help="print one JSON object with the statistics as the last line")
    p.add_argument("--token", default="",
                   help="token the server requires (visible in the process list: prefer PSAO_TOKEN or --token-file)")
    p.add_argument("--token-file", type=Path, default=None, metavar="FILE",
                   help="read the token from FILE (first line); the environment variable PSAO_TOKEN also works")
    p.add_argument("--tls-ca", type=Path, default=None, metavar="PEM",
                   help="with wss://, trust only these certificates (e.g. a server's self-signed one)")
    p.add_argument("--codecs", default=comma_list(default(ConnectSettings, "codecs")),
                   help="codecs to accept, comma-separated: the names psao serve --codec takes")
    p.add_argument("--read-delay", type=float, default=default(ConnectSettings, "read_delay"), metavar="S",
                   help="pause S seconds after every message (simulates a slow client)")
    p.add_argument("--recv-buffer", type=int, default=None, metavar="BYTES",
                   help="socket receive buffer size (small values make a slow reader felt by the server at once)")
    p.add_argument("--no-reconnect", action="store_true", help="exit when the connection drops")
    p.add_argument("--reconnect-timeout", type=float, default=default(ConnectSettings, "reconnect_timeout"),
                   help="give up after S seconds without a message")
    p.add_argument("--digest-log", type=Path, default=None,
                   help="append the mirror's state digest (jsonl) after every Snapshot and Update (tests)")
    p.add_argument("--digest-every", type=int, default=default(ConnectSettings, "digest_every"), metavar="N",
                   help="with --digest-log: the digest after the first Snapshot's chunks and the first Update, then "
                        "after every N-th Update only (each digest hashes the whole mirror: on a large grid that costs "
                        "more than applying the Update)")
    from psao.client.render.stream_render import add_render_arguments

    add_render_arguments(p)  # --render OUTDIR and its options: frames at the client's own rate (--fps)


def connect_settings(args: argparse.Namespace) -> ConnectSettings:
    """ConnectSettings from --codecs, --read-delay, --reconnect-timeout and --digest-every, checked
    (ConnectSettings.check: ConnectError)."""
    settings = ConnectSettings(codecs=tuple(t.strip() for t in args.codecs.split(",") if t.strip()),
                               read_delay=args.read_delay, reconnect_timeout=args.reconnect_timeout,
                               digest_every=getattr(args, "digest_every", ConnectSettings.digest_every))
    settings.check()
    return settings


def _codecs(names: tuple[str, ...]):
    bad = [n for n in names if n not in CODEC_NAMES]
    if bad or not names:
        raise ConnectError(f"--codecs: unknown codec(s) {', '.join(bad) or '(none)'} (known: {', '.join(CODEC_NAMES)})")
    return frozenset(CODEC_NAMES[n] for n in names)


def _token(args: argparse.Namespace) -> str:
    """--token, else the first line of --token-file, else $PSAO_TOKEN."""
    if args.token:
        return args.token
    path = getattr(args, "token_file", None)
    if path is not None:
        try:
            return path.read_text(encoding="utf-8").splitlines()[0].strip()
        except (OSError, UnicodeDecodeError, IndexError) as exc:
            raise ConnectError(f"cannot read a token from {path}: {getattr(exc, 'strerror', None) or 'empty file'}") from None
    return os.environ.get("PSAO_TOKEN", "").strip()


def _tls_ca(args: argparse.Namespace):
    path = getattr(args, "tls_ca", None)
    if path is not None and not Path(path).is_file():
        raise ConnectError(f"--tls-ca: no file {path}")
    return path


def _aspect(size: str | None) -> float:
    """Width / height of a 'WxH' frame size; 16:9 without one (or a malformed one: the renderer reports it)."""
    try:
        w, h = (int(v) for v in str(size).lower().split("x"))
        return w / h if w > 0 and h > 0 else 16 / 9
    except ValueError:
        return 16 / 9


def build_client(args: argparse.Namespace, scene, on_update=None, on_connect=None, on_snapshot=None, on_frame=None,
                 scene_hash: bytes | None = None):
    """The client of `args`; `scene_hash` names the scene in Hello (default: the scene's content hash)."""
    from psao.protocol.session import scene_hash_bytes
    from psao.client.connection import MirrorClient, scene_camera_feed

    if args.frames is not None and args.frames < 0:
        raise ConnectError(f"--frames must be >= 0, got {args.frames}")
    c = connect_settings(args)
    client = MirrorClient(
        args.url, scene_hash or scene_hash_bytes(scene.content_hash()), token=_token(args), codecs=_codecs(c.codecs),
        camera=scene_camera_feed(scene, _aspect(getattr(args, "size", None)), getattr(args, "camera_path", None)),
        on_update=on_update, on_connect=on_connect, on_snapshot=on_snapshot,
        read_delay=c.read_delay, digest_log=args.digest_log, reconnect=not args.no_reconnect,
        reconnect_timeout=c.reconnect_timeout, recv_buffer=args.recv_buffer, on_frame=on_frame,
        frame_hz=float(getattr(args, "fps", FrameSettings.fps)), tls_ca=_tls_ca(args), digest_every=c.digest_every,
    )
    return client


def report(client, seconds: float) -> dict:
    s, mirror = client.stats, client.mirror
    return {
        "bytes_received": s.bytes_received,
        "messages": s.messages,
        "snapshot_bytes": s.snapshot_bytes,
        "mirror_cells": mirror.allocated_cells() if mirror else 0,
        "mirror_buckets": mirror.allocated_buckets() if mirror else 0,
        "seconds": seconds,
        "updates": s.updates,
        # the Updates' own rate: over the seconds from the first Update to the latest (`seconds` also
        # holds connecting and the snapshot)
        "stream_seconds": s.stream_seconds,
        "updates_per_s": (s.updates - 1) / s.stream_seconds if s.stream_seconds > 0 else 0.0,
        "reconnects": s.reconnects,
        "snapshot_seconds": s.snapshot_seconds,
        "connection_id": s.connection_id,
        "codec": s.codec,
        "mirror_digest": mirror.digest() if mirror else None,
    }


def client_scene(args: argparse.Namespace):
    """(scene, hash for Hello or None, scene bytes fetched): SCENE from disk, else the server's."""
    from psao.client.connection import fetch_scene
    from psao.scene import load_scene

    if args.scene is not None:
        return load_scene(args.scene), None, 0
    return asyncio.run(fetch_scene(args.url, _token(args)))


def run(args: argparse.Namespace, on_update=None) -> int:
    scene, scene_hash, scene_bytes = client_scene(args)
    renderer = on_frame = None
    if getattr(args, "render", None):
        # At the client's own rate (--fps), whatever has arrived by then; frames use the camera pose this
        # client sends at that moment (same clock).
        on_frame = lambda mirror: renderer(mirror, mirror.transforms, mirror.tick,  # noqa: E731
                                           camera_time=client.clock())
    client = build_client(args, scene, on_update=on_update, on_frame=on_frame, scene_hash=scene_hash)
    if on_frame is not None:
        from psao.client.render.stream_render import make_render_callback

        renderer = make_render_callback(scene, args)
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C ends the run with its report, also where SIGINT came in ignored (a script's background job)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    t0 = time.perf_counter()
    try:
        asyncio.run(client.run(frames=args.frames))
    except KeyboardInterrupt:
        pass
    finally:
        if renderer is not None:
            renderer.close()
    out = report(client, time.perf_counter() - t0)
    out["scene_bytes"] = scene_bytes
    if renderer is not None:
        out["frames_rendered"] = renderer.frames
        # per frame: tick, camera time and GPU milliseconds of each pass (timer queries)
        out["frames"] = [{"frame": r["frame"], "tick": r["tick"], "time": r["time"], "gpu_ms": r["gpu_ms"]}
                         for r in renderer.records]
        out["render_dir"] = str(args.render)
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{out['updates']} updates, {out['messages']} messages, {out['bytes_received'] / 1e6:.2f} MB "
              f"(snapshot {out['snapshot_bytes'] / 1e6:.2f} MB in {out['snapshot_seconds'] or 0:.2f} s), "
              f"mirror {out['mirror_cells']} cells, {out['reconnects']} reconnects, {out['seconds']:.1f} s")
    return 0
