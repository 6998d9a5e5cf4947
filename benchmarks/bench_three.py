"""three.js integration: the frame ms of three.js with PSAO (psao-three's pass) against three.js with its own
GTAOPass and SAOPass, and without AO, on the same frame in the same page; and each method's PSNR against RTAO
on that frame.

A real `psao serve SCENE --density N --web-example three` (`--grid FILE` serves a grid baked before),
Debian's chromium driven by playwright (WebGL2 on SwiftShader) opening the example at a fixed camera (the
scene's first camera path at t = 0), twice:

- quality: a server that only serves its bake (no edits, nothing moves). Once the page streams it draws the
  frame in each mode and reads each method's AO term (window.psao.readAoTerms: PSAO's AO target, GTAOPass's
  denoised AO, SAOPass's blurred SAO; no AO is 1), and the PSAO pass's G-buffer (instance-local positions and
  normals); those pixels placed by the mirror's transforms are the RTAO reference's (psao.eval.reference,
  `--spp` rays a pixel, cached under out/.cache/rtao). PSNR over the composited AO image (AO on covered
  pixels, 1 on the background), as psao bench scores it;
- frame ms: a server with `--edits` random grid edits a tick (they keep Updates coming, and change AO at
  random, so this run's frames are not scored); once the page has decoded `--updates` Updates it draws rounds
  of `--frames` frames in each AO mode in turn (interleaved, so load on the machine falls on every mode
  alike). Software rendering on a busy CPU: the figures are ratios measured in one run.

    .venv/bin/python -m benchmarks.bench_three [--scene builtin:courtyard] [--density 64] [--size 320x180] [--spp 256]

Writes OUT/bench_three.json (the figures), OUT/bench_three.png (the AO images and PSNR beside the frame ms
ratios) and a screenshot per mode. Without chromium or playwright it says so in one line and exits 0
(skipped).
"""
from __future__ import annotations

import argparse
import base64
import json
import statistics
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from benchmarks.bench_web import add_server_arguments, fixed_camera, parse_page_args, start_server
from benchmarks.verdicts import Verdicts
from psao.eval.browser import CHROMIUM, CHROMIUM_ARGS

MODES = ("psao", "gtao", "sao", "none")
NAMES = {"psao": "PSAO", "gtao": "GTAOPass", "sao": "SAOPass", "none": "no AO"}


def _decode(b64: str, dtype) -> np.ndarray:
    return np.frombuffer(base64.b64decode(b64), dtype=dtype)


def _page(p, port: int, view, proj, w: int, h: int):
    """A paused example page at the fixed camera, once it streams."""
    browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    page = browser.new_page(viewport={"width": w + 40, "height": h + 40})
    page.goto(f"http://127.0.0.1:{port}/?width={w}&height={h}", wait_until="commit", timeout=600_000)
    page.wait_for_function("!!(window.psao && window.psao.setCamera)", timeout=600_000, polling=100)
    page.evaluate("([v, p]) => window.psao.setCamera(v, p)",
                  [view.astype(np.float32).reshape(-1).tolist(), proj.astype(np.float32).reshape(-1).tolist()])
    page.wait_for_function("window.psao.state === 'streaming' && window.psao.frames >= 1", timeout=600_000, polling=100)
    return browser, page


def ao_terms(port: int, view, proj, w: int, h: int) -> tuple[dict, dict[str, np.ndarray]]:
    """The PSAO pass's G-buffer and mirror (readPsao) and each mode's AO term, (h, w) float32 bottom-up."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser, page = _page(p, port, view, proj, w, h)
        page.evaluate("window.psao.paused = true")
        frame = page.evaluate("() => { window.psao.renderOnce(); return window.psao.readPsao(); }")
        terms = page.evaluate("window.psao.readAoTerms()")
        browser.close()
    ao = {m: _decode(t["data"], t["dtype"]).astype(np.float32).reshape(h, w, 4)[..., 0] for m, t in terms.items()}
    ao["none"] = np.ones((h, w), np.float32)
    return frame, ao


def rtao(scene, frame: dict, view, proj, spp: int) -> tuple[np.ndarray, np.ndarray]:
    """(RTAO visibility, coverage mask), (h, w) bottom-up: the G-buffer's instance-local targets placed by the
    mirror's transforms (the back side of a double-sided mesh traced from its side)."""
    from psao.eval.reference import FrameKey, ReferenceSettings, reference_ao

    w, h = frame["width"], frame["height"]
    local = _decode(frame["local"], np.float32).reshape(h * w, 4)
    normal = _decode(frame["normal"], np.float32).reshape(h * w, 4)
    transforms = _decode(frame["transforms"], np.float32).reshape(-1, 4, 4).astype(np.float64)
    covered = local[:, 3] > 0.5
    m = transforms[np.rint(local[covered, 3]).astype(np.int64) - 1]
    world = np.zeros((h * w, 3))
    world[covered] = np.einsum("pij,pj->pi", m[:, :3, :3], local[covered, :3]) + m[:, :3, 3]
    n = np.zeros((h * w, 3))
    n[covered] = np.einsum("pji,pj->pi", np.linalg.inv(m[:, :3, :3]), normal[covered, :3])  # inverse transpose
    n[covered] *= np.where(normal[covered, 3] > 0.5, -1.0, 1.0)[:, None]
    gbuffer = SimpleNamespace(world=world.reshape(h, w, 3), normal=n.reshape(h, w, 3), mask=covered.reshape(h, w))
    ref = reference_ao(scene, gbuffer, transforms, ReferenceSettings(spp=spp), key=FrameKey(view, proj, 0.0))
    return ref, gbuffer.mask


def chart(path: Path, ref: np.ndarray, ao: dict[str, np.ndarray], psnr: dict[str, float], ratio: dict[str, float],
          title: str) -> None:
    """The AO images (top-down) with their PSNR, and each mode's frame ms over PSAO's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 5, figsize=(17, 3.2), gridspec_kw={"width_ratios": [1, 1, 1, 1, 0.8]})
    for ax, (name, img) in zip(axes, [("RTAO reference", ref)] + [(f"{NAMES[m]}: {psnr[m]:.2f} dB", ao[m])
                                                                  for m in ("psao", "gtao", "sao")]):
        ax.imshow(np.flipud(np.clip(img, 0, 1)), cmap="gray", vmin=0, vmax=1)
        ax.set_title(name, fontsize=10)
        ax.axis("off")
    ax = axes[-1]
    ax.bar([NAMES[m] for m in MODES], [ratio[m] for m in MODES], color=["#3b7", "#888", "#aaa", "#ccc"])
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_ylabel("frame ms / PSAO's")
    ax.tick_params(axis="x", labelsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def frame_ms(port: int, view, proj, w: int, h: int, args) -> dict[str, list[float]]:
    """Per AO mode, the ms of each frame drawn (composer render + a one-pixel read); screenshots to --out."""
    from playwright.sync_api import sync_playwright

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser, page = _page(p, port, view, proj, w, h)
        page.wait_for_function(f"window.psao.updates >= {args.updates}", timeout=600_000, polling=100)
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
    ap.add_argument("--spp", type=int, default=256, help="RTAO reference rays per pixel")
    args = parse_page_args(ap, argv, "bench_three")
    if args is None:
        return 0
    from psao.eval.metrics import composite_ao, psnr as psnr_of
    from psao.scene import load_scene

    w, h = (int(v) for v in args.size.split("x"))
    scene = load_scene(args.scene)
    view, proj = fixed_camera(scene, w, h)
    out = Path(args.out)
    # no edits and no progressive start: the page scores the full bake, which nothing changes afterwards
    server = start_server(argparse.Namespace(**{**vars(args), "edits": 0}), ("--web-example", "three", "--no-progressive"))
    try:
        frame, ao = ao_terms(server.port, view, proj, w, h)
    finally:
        server.close()
    ref, mask = rtao(scene, frame, view, proj, args.spp)
    reference = composite_ao(ref, mask)
    psnr = {m: psnr_of(reference, composite_ao(ao[m], mask)) for m in MODES}
    server = start_server(args, ("--web-example", "three"))
    try:
        ms = frame_ms(server.port, view, proj, w, h, args)
    finally:
        server.close()
    med = {m: statistics.median(t) for m, t in ms.items()}
    ratio = {m: med[m] / med["psao"] for m in MODES}
    print(f"\n{args.scene} N={args.density:g}, {w}x{h}, {args.rounds} rounds of {args.frames} frames per mode; "
          f"PSNR against RTAO at {args.spp} spp over {int(mask.sum()):,} covered pixels\n")
    print("| three.js frame | median ms | / PSAO | PSNR dB against RTAO |\n|---|---|---|---|")
    for m in MODES:
        print(f"| {NAMES[m]} | {med[m]:.1f} | {ratio[m]:.2f} | {psnr[m]:.2f} |")
    summary = {"scene": args.scene, "density": args.density, "size": args.size, "spp": args.spp,
               "covered_pixels": int(mask.sum()), "frame_ms_median": med, "frame_ms_over_psao": ratio, "psnr_db": psnr}
    (out / "bench_three.json").write_text(json.dumps(summary, indent=1) + "\n")
    chart(out / "bench_three.png", ref, ao, psnr, ratio,
          f"three.js example, {args.scene} N={args.density:g} {w}x{h}: AO against RTAO ({args.spp} spp) and frame ms")
    print(f"wrote {out / 'bench_three.json'} and {out / 'bench_three.png'}")
    v = Verdicts("bench_three")
    # Target: PSAO's pass costs a three.js frame no more than three.js's GTAOPass does on the same frame.
    v.check("PSAO / GTAOPass frame ms", med["psao"] / med["gtao"], "<=", 1.0)
    # Target: PSAO's AO is closer to RTAO than three.js's own AO passes on the same frame.
    v.check("PSAO - GTAOPass PSNR dB", psnr["psao"] - psnr["gtao"], ">", 0.0)
    v.check("PSAO - SAOPass PSNR dB", psnr["psao"] - psnr["sao"], ">", 0.0)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
