"""three.js integration: the frame ms of three.js with PSAO (psao-three's pass) against three.js with its own
GTAOPass and SAOPass, and without AO, on the same frame in the same page.

A real `psao serve SCENE --density N --test-edits K --web-example three` (edits keep Updates coming; `--grid
FILE` serves a grid baked before), Debian's chromium driven by playwright (WebGL2 on SwiftShader) opening the
example at a fixed camera (the scene's first camera path at t = 0) and, once it has decoded `--updates`
Updates, drawing rounds of `--frames` frames in each AO mode in turn (interleaved, so load on the machine
falls on every mode alike). Software rendering on a busy CPU: the figures are ratios measured in one run.

    .venv/bin/python -m benchmarks.bench_three [--scene builtin:courtyard] [--density 64] [--size 320x180]

Without chromium or playwright it says so in one line and exits 0 (skipped).
"""
from __future__ import annotations

import argparse
import base64
import statistics
import sys
from pathlib import Path

import numpy as np

from benchmarks.bench_web import add_server_arguments, fixed_camera, parse_page_args, start_server
from benchmarks.verdicts import Verdicts
from psao.eval.browser import CHROMIUM, CHROMIUM_ARGS

MODES = ("psao", "gtao", "sao", "none")


def frame_ms(port: int, view, proj, w: int, h: int, args) -> dict[str, list[float]]:
    """Per AO mode, the ms of each frame drawn (composer render + a one-pixel read); screenshots to --out."""
    from playwright.sync_api import sync_playwright

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": w + 40, "height": h + 40})
        page.goto(f"http://127.0.0.1:{port}/?width={w}&height={h}", wait_until="commit", timeout=600_000)
        page.wait_for_function("!!(window.psao && window.psao.setCamera)", timeout=600_000, polling=100)
        page.evaluate("([v, p]) => window.psao.setCamera(v, p)",
                      [view.astype(np.float32).reshape(-1).tolist(), proj.astype(np.float32).reshape(-1).tolist()])
        page.wait_for_function(f"window.psao.state === 'streaming' && window.psao.updates >= {args.updates}",
                               timeout=600_000, polling=100)
        page.evaluate("window.psao.paused = true")
        ms: dict[str, list[float]] = {m: [] for m in MODES}
        for _ in range(args.rounds):
            for mode in MODES:
                ms[mode] += page.evaluate("([m, n]) => { const a = window.psao; a.mode = m; a.renderOnce(); "
                                          "const t = []; for (let i = 0; i < n; i++) t.push(a.renderOnce()); return t; }",
                                          [mode, args.frames])
                url = page.evaluate("document.getElementById('view').toDataURL('image/png')")
                (out / f"{mode}.png").write_bytes(base64.b64decode(url.split(",", 1)[1]))
        browser.close()
    return ms


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_server_arguments(ap, "bench_three", density=64.0, rays=8, edits=20, updates=10, frames=5)
    ap.add_argument("--rounds", type=int, default=3, help="rounds of --frames frames per AO mode")
    args = parse_page_args(ap, argv, "bench_three")
    if args is None:
        return 0
    from psao.scene import load_scene

    w, h = (int(v) for v in args.size.split("x"))
    view, proj = fixed_camera(load_scene(args.scene), w, h)
    server = start_server(args, ("--web-example", "three"))
    try:
        ms = frame_ms(server.port, view, proj, w, h, args)
    finally:
        server.close()
    med = {m: statistics.median(t) for m, t in ms.items()}
    print(f"\n{args.scene} N={args.density:g}, {w}x{h}, {args.rounds} rounds of {args.frames} frames per mode\n")
    print("| three.js frame | median ms | / PSAO |\n|---|---|---|")
    for m in MODES:
        print(f"| {m} | {med[m]:.1f} | {med[m] / med['psao']:.2f} |")
    v = Verdicts("bench_three")
    # Target (mine): PSAO's pass costs a three.js frame no more than three.js's GTAOPass does on the same frame.
    v.check("PSAO / GTAOPass frame ms", med["psao"] / med["gtao"], "<=", 1.0)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
