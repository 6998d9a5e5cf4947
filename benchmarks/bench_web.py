"""Web client: time from opening the URL to the first PSAO frame, JS decode per update, browser frame
time against the moderngl client's on the same frame, scene bytes against snapshot bytes.

A real `psao serve SCENE --density N --test-edits K` (edits keep Updates coming; `--grid FILE` serves a
grid baked before, so a run does not wait for the bake), Debian's chromium driven by playwright
(WebGL2 on SwiftShader) opening the served page at a fixed camera (the scene's first camera path at
t = 0), once per codec in `--codecs` (the page offers only that one), and the desktop client's
FrameRenderer (moderngl, EGL/llvmpipe here) drawing the page's own mirror at the same camera and size.
Both are software renderers on the same busy CPU: the frame figure is their ratio, measured in the same run.

    .venv/bin/python -m benchmarks.bench_web [--scene builtin:courtyard] [--density 256] [--grid FILE]
        [--size 320x180] [--codecs zstd-stream,zstd]

Splits of the first frame (ms after navigation start): page start (HTML, modules, WebGL2 context and
shader compiles), scene load (SceneRequest to the scene decoded and uploaded), snapshot transfer and
decode (Hello to the last chunk applied and uploaded; its JS work is split into zstd decompression,
delta parsing, mirror writes and texture upload, the rest is waiting for the server and the socket),
first draw (to the first frame drawn with PSAO, waited for with a one-pixel read). Without chromium or
playwright it says so in one line and exits 0 (skipped).
"""
from __future__ import annotations

import argparse
import base64
import json
import signal
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.eval.browser import CHROMIUM, CHROMIUM_ARGS, missing_browser
from psao.eval.processes import ServeExited, ServerProcess, ServeTimeout

ROOT = Path(__file__).resolve().parents[1]
def add_server_arguments(ap: argparse.ArgumentParser, bench: str, density: float, rays: int, edits: int, updates: int,
                         frames: int) -> None:
    """The served scene's options that start_server reads, the page's --size, the Updates to wait for, the
    frames to time and the output folder."""
    ap.add_argument("--scene", default="builtin:courtyard")
    ap.add_argument("--density", type=float, default=density)
    ap.add_argument("--grid", type=Path, default=None, help="serve this grid (psao bake --out) instead of baking")
    ap.add_argument("--rays", type=int, default=rays, help="bake rays per point (the page's work does not depend on it)")
    ap.add_argument("--edits", type=int, default=edits, help="points edited per tick (keeps Updates coming)")
    ap.add_argument("--tick-hz", type=float, default=10.0)
    ap.add_argument("--size", default="320x180")
    ap.add_argument("--updates", type=int, default=updates, help="Updates to decode before measuring frames")
    ap.add_argument("--frames", type=int, default=frames)
    ap.add_argument("--out", default=str(ROOT / "out" / bench))


def parse_page_args(ap: argparse.ArgumentParser, argv: list[str] | None, bench: str):
    """The parsed arguments, or None (said in one line) where no browser can run the page."""
    args = ap.parse_args(argv)
    why = missing_browser()
    if why:
        print(f"{bench}: SKIPPED: {why}", flush=True)
        return None
    return args


def start_server(args, extra: tuple[str, ...] = ()) -> ServerProcess:
    """`psao serve` of the benchmark's scene (and `extra` arguments), listening; its log in --out/serve.err."""
    err = Path(args.out) / "serve.err"
    grid = ["--grid", str(args.grid)] if args.grid else ["--density", str(args.density), "--rays", str(args.rays)]
    server = ServerProcess(args.scene, [*grid, "--test-edits", str(args.edits), "--tick-hz", str(args.tick_hz), *extra],
                           start_timeout=1800.0, host=None, log_path=err, log_stdout=False, cwd=ROOT,
                           stop_signal=signal.SIGTERM, stop_grace=60.0)
    try:
        server.start()
    except ServeExited as exc:
        raise SystemExit(f"bench_web: psao serve exited: {exc.log[-500:]}") from None
    except ServeTimeout:
        raise SystemExit("bench_web: the server did not start within 30 minutes") from None
    print(f"server up after {server.listen_s:.0f} s ({f'grid {args.grid}' if args.grid else f'bake at N={args.density:g}'})",
          flush=True)
    return server


def fixed_camera(scene, w: int, h: int):
    from psao.scene.camera import camera_at, look_at, perspective, scene_camera

    path = scene_camera(scene)
    eye, target = camera_at(path, 0.0)
    lo, hi = scene.world_bounds()
    far = 4.0 * float(np.linalg.norm(hi - lo)) + 1.0
    return look_at(eye, target), perspective(path.fov_y, w / h, far * 1e-4, far)


def browser_run(port: int, view, proj, w: int, h: int, args, codec: str, shot: Path) -> dict:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": w + 40, "height": h + 40})
        cam = [view.astype(np.float32).reshape(-1).tolist(), proj.astype(np.float32).reshape(-1).tolist()]
        # The camera is fixed before the page's module runs, so the first frame is the measured view.
        page.add_init_script(f"window.__psaoCamera = {json.dumps(cam)};")
        page.goto(f"http://127.0.0.1:{port}/?width={w}&height={h}&codecs={codec}", wait_until="commit", timeout=600_000)
        page.wait_for_function("!!(window.psao && (window.psao.timings.firstDraw || window.psao.refused))",
                               timeout=600_000, polling=50)
        if page.evaluate("window.psao.refused"):
            raise SystemExit(f"bench_web: the page was refused: {page.evaluate('window.psao.message')}")
        page.wait_for_function(f"window.psao.updates >= {args.updates}", timeout=600_000, polling=100)
        out = page.evaluate("""(n) => {
            const a = window.psao; a.paused = true;
            const ms = []; for (let i = 0; i < n; i++) ms.push(a.renderOnce());
            return { timings: a.timings, profile: a.profile, decode: a.decodeMs.slice(), frameMs: ms,
                     sceneBytes: a.sceneBytes, snapshotBytes: a.snapshotBytes, updateBytes: a.updateBytes,
                     updates: a.updates, codec: a.codec, frame: a.readPsao(), points: a.mirror.allocatedPoints() };
        }""", args.frames)
        url = page.evaluate("document.getElementById('view').toDataURL('image/png')")
        shot.parent.mkdir(parents=True, exist_ok=True)
        shot.write_bytes(base64.b64decode(url.split(",", 1)[1]))
        browser.close()
    return out


def moderngl_ms(scene, frame: dict, view, proj, w: int, h: int, frames: int) -> list[float]:
    """Wall ms of the desktop client's PSAO frame (submit + finish) on the page's own mirror."""
    from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, INSTANCE_DTYPE
    from psao.client.render.renderer import FrameRenderer

    dec = lambda k, dt: np.frombuffer(base64.b64decode(frame[k]), dtype=dt)  # noqa: E731
    with FrameRenderer(scene, size=(w, h), ao_mode="psao") as r:
        r.upload_grid(dec("instances", np.uint8).view(INSTANCE_DTYPE), dec("buckets", np.uint32).reshape(-1, BUCKET_ENTRIES, 2),
                      dec("cells", np.uint32).reshape(-1, CELL_WORDS))
        r.set_transforms(dec("transforms", np.float32).reshape(-1, 4, 4))
        r.set_skin_time(frame["serverTime"])
        r.render(view, proj, read_gbuffer=False)  # warm-up: shader compile, first uploads
        out = []
        for _ in range(frames):
            t0 = time.perf_counter()
            r.submit(view, proj)
            r.ctx.finish()
            out.append(1e3 * (time.perf_counter() - t0))
    return out


def first_frame_rows(res: dict) -> list[tuple[str, float]]:
    t, pr = res["timings"], res["profile"]
    js = pr["decompressMs"] + pr["parseMs"] + pr["applyMs"] + pr["uploadMs"]
    snap = t["snapshot"] - t["scene"]
    return [
        ("page start (HTML, modules, WebGL2 context, shader compiles)", t["connect"]),
        ("  of which WebGL2 context and shader compiles", t["renderer"] - t["module"]),
        ("scene load (SceneRequest, transfer, decode, upload)", t["scene"] - t["connect"]),
        ("snapshot transfer + decode + upload", snap),
        ("  Hello to Welcome (server)", t["welcome"] - t["hello"]),
        ("  Welcome to the first chunk's arrival (server reads and compresses it)", t["firstChunk"] - t["welcome"]),
        (f"  zstd decompression ({pr['chunks']} chunks)", pr["decompressMs"]),
        ("  delta parsing", pr["parseMs"]),
        ("  mirror writes", pr["applyMs"]),
        ("  texture upload (one texImage2D per table)", pr["uploadMs"]),
        ("  waiting for later chunks (server and socket)", snap - (t["firstChunk"] - t["scene"]) - js),
        ("first draw", t["firstDraw"] - t["snapshot"]),
        ("total", t["firstDraw"]),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_server_arguments(ap, "bench_web", density=256.0, rays=16, edits=200, updates=60, frames=10)
    ap.add_argument("--codecs", default="zstd-stream,zstd", help="one page per codec, each offering only that one")
    args = parse_page_args(ap, argv, "bench_web")
    if args is None:
        return 0
    from psao.scene import load_scene
    from psao.server.net.scene_export import scene_blob, scene_file

    w, h = (int(v) for v in args.size.split("x"))
    codecs = [c.strip() for c in args.codecs.split(",") if c.strip()]
    scene = load_scene(args.scene)
    view, proj = fixed_camera(scene, w, h)
    server = start_server(args)
    runs = {}
    try:
        for codec in codecs:
            runs[codec] = browser_run(server.port, view, proj, w, h, args, codec,
                                      Path(args.out) / f"first_frame_{codec}.png")
            print(f"page with {codec}: first PSAO frame {runs[codec]['timings']['firstDraw'] / 1e3:.1f} s after opening the URL",
                  flush=True)
    finally:
        server.close()  # SIGTERM, up to 60 s to stop, then its process group is killed
    first = runs[codecs[0]]
    desk = moderngl_ms(scene, first["frame"], view, proj, w, h, args.frames)
    gl_ms = statistics.median(desk)
    raw_scene = len(scene_file(scene).serialize())
    print(f"\n{args.scene} N={args.density:g}, {first['points']:,} points, {w}x{h}, tick {args.tick_hz:g} Hz, "
          f"{args.edits} edits per tick")
    print("| first PSAO frame after opening the URL, ms | " + " | ".join(codecs) + " |\n|---|" + "---|" * len(codecs))
    rows = {c: first_frame_rows(r) for c, r in runs.items()}
    for i, (what, _) in enumerate(rows[codecs[0]]):
        print(f"| {what} | " + " | ".join(f"{rows[c][i][1]:.0f}" for c in codecs) + " |")
    print("\n| per codec | " + " | ".join(codecs) + " |\n|---|" + "---|" * len(codecs))
    decode = {c: float(np.mean(r["decode"])) if r["decode"] else float("nan") for c, r in runs.items()}
    web_ms = {c: statistics.median(r["frameMs"]) for c, r in runs.items()}
    for what, f in (("JS decode per Update, ms (decompress + delta + mirror)", lambda c: f"{decode[c]:.2f}"),
                    ("Updates decoded", lambda c: f"{len(runs[c]['decode'])}"),
                    ("bytes per Update", lambda c: f"{runs[c]['updateBytes'] / max(runs[c]['updates'], 1):,.0f}"),
                    ("snapshot bytes (its chunks as received)", lambda c: f"{runs[c]['snapshotBytes']:,}"),
                    ("browser frame ms (median)", lambda c: f"{web_ms[c]:.1f}")):
        print(f"| {what} | " + " | ".join(f(c) for c in codecs) + " |")
    print(f"\nframe ms (median of {args.frames}, same frame): browser ({codecs[0]} page) {web_ms[codecs[0]]:.1f}, moderngl "
          f"{gl_ms:.1f}, ratio {web_ms[codecs[0]] / gl_ms:.2f}")
    print("\n| bytes | once per client |\n|---|---|")
    print(f"| scene (SceneData, zstd) | {first['sceneBytes']:,} |\n| scene uncompressed | {raw_scene:,} |")
    print(f"| snapshot ({codecs[0]}) | {first['snapshotBytes']:,} |")
    print(f"| scene / snapshot | {first['sceneBytes'] / first['snapshotBytes']:.3f} |\n", flush=True)
    assert first["sceneBytes"] == len(scene_blob(scene))
    v = Verdicts("bench_web")
    # Targets (mine): decoding keeps up with the tick rate with room to draw; a browser frame within 4x
    # of the desktop client's; the one-off scene smaller than the snapshot it comes with.
    for c in codecs:
        v.check(f"JS decode ms per update ({c})", decode[c], "<", 1e3 / args.tick_hz / 2)
    v.check("browser / moderngl frame ms", web_ms[codecs[0]] / gl_ms, "<=", 4.0)
    v.check("scene bytes / snapshot bytes", first["sceneBytes"] / first["snapshotBytes"], "<", 1.0)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
