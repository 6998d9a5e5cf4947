"""`psao demo` (what `make demo` runs): the whole system once, on this machine, in about a minute.

1. `psao serve builtin:courtyard --animate` at a demo density as a separate process on a free
   127.0.0.1 port (it bakes, then ticks: the boulders roll);
2. a headless `psao client --render` process connects, mirrors the grid and renders what it receives
   along the camera path for a few seconds: bytes on the wire, updates, frames;
3. the camera path with the scene animated (the server's tick in this process rolls the boulders and
   re-traces around them up to each frame's time), PSAO and SSAO in one headless renderer, a few frames
   scored against a low-spp RTAO reference with the boulders where the frame has them;
4. two of the frames the streaming client rendered itself scored the same way (its own PSAO images,
   the G-buffer drawn again here from its frames.jsonl for SSAO and the reference);
5. a short report on stdout and the paths of what it wrote under out/demo/.
No arguments, no downloads. The server is killed (its process group) on every exit path.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from psao.client.render.output import parse_size
from psao.eval.settings import DemoSettings

DEMO = DemoSettings()
SIZE = parse_size(DEMO.size)  # (width, height) pixels


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = "Serve the animated courtyard, stream it to a headless client, render, score and chart (no arguments)."


def run(args) -> int:
    from psao.eval.processes import interrupt_on_sigterm

    with interrupt_on_sigterm():
        return _run(args)


def _run(args) -> int:
    from psao.eval.bench_cli import Log, ensure_writable
    from psao.scene import load_scene

    t_start = time.perf_counter()
    out = ensure_writable(DEMO.out, "output folder")
    ensure_writable(Path("out") / ".cache", "cache folder")
    log = Log()
    scene = load_scene(DEMO.scene)
    stream = stream_demo(scene, out, log)
    quality = quality_demo(scene, out, log)
    client = client_demo(scene, stream, log)
    written = write_demo_outputs(quality, out)
    print_report(scene, stream, quality, client, written, time.perf_counter() - t_start)
    return 0


def stream_demo(scene, out: Path, log) -> dict:
    """A real animating server and a real headless client that renders what it receives (--render)."""
    from psao.eval.processes import ServerProcess, client_has_render, run_client, stream_rates, welcome_bytes

    extra, frames_dir = [], None
    if client_has_render():
        frames_dir = out / "client_frames"
        extra = ["--render", str(frames_dir), "--ao", "psao", "--size", f"{SIZE[0]}x{SIZE[1]}"]
    log(f"psao serve {DEMO.scene} --animate (N={DEMO.density:g}, {DEMO.rays} rays, {DEMO.tick_hz:g} Hz) and a headless psao client "
        f"for {DEMO.stream_seconds:g} s after its snapshot")
    with ServerProcess(DEMO.scene, ["--animate", "--density", f"{DEMO.density:g}", "--rays", str(DEMO.rays), "--tick-rays",
                               str(DEMO.rays), "--tick-hz", f"{DEMO.tick_hz:g}"]) as server:
        stats = run_client(server.url, DEMO.scene, DEMO.stream_seconds, extra)
        rates = stream_rates(stats, welcome_bytes(scene))
        rates["server_ms_tick"] = server.tick_ms()
        rates["url"] = server.url
    rates["client_frames"] = int(stats.get("frames_rendered", 0))
    rates["client_frames_dir"] = str(frames_dir) if rates["client_frames"] else None
    return rates


def client_demo(scene, stream: dict, log) -> list:
    """The streaming client's own frames against RTAO (empty when it rendered none)."""
    from psao.eval.client_frames import score_client_frames
    from psao.eval.reference import ReferenceSettings

    if not stream["client_frames_dir"]:
        return []
    log(f"RTAO reference at {DEMO.spp} spp on {DEMO.client_scored} of the streaming client's own frames")
    return score_client_frames(scene, stream["client_frames_dir"], DEMO.client_scored,
                               ReferenceSettings(spp=DEMO.spp, cache_dir=Path("out") / ".cache" / "rtao"))


def quality_demo(scene, out: Path, log) -> dict:
    """The camera path with the scene animated: the server's tick in this process moves the boulders and
    re-traces their surroundings up to each frame's time; PSAO and SSAO drawn from that grid state."""
    from PIL import Image

    from psao.eval.dynamic import AnimatedServer, AnimatedSettings
    from psao.server.settings import BakeSettings
    from psao.eval.quality import QualityRenderer, frame_poses, reference_images, score_frames
    from psao.eval.reference import ReferenceSettings

    poses = frame_poses(scene, DEMO.frames, SIZE)
    log(f"animating {DEMO.scene} (server tick in this process, N={DEMO.density:g}) and rendering {len(poses)} frames "
        f"of the camera path with PSAO and SSAO at {SIZE[0]}x{SIZE[1]}")
    with AnimatedServer(scene, AnimatedSettings(BakeSettings(density=DEMO.density, rays=DEMO.rays), tick_rays=DEMO.rays,
                                                       tick_hz=DEMO.tick_hz)) as server:
        with QualityRenderer(scene, SIZE) as qr:
            t0 = time.perf_counter()
            frames = qr.render(server.grid, poses, timing_repeats=1, before_frame=server.frame_state)
            wall = time.perf_counter() - t0
            gl = qr.gl_renderer
        tick_s = sum(st.seconds_total for st in server.stats)
        points = server.points
        tick_ms = server.mean_tick_ms()
    frames_dir = out / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    for f in frames:
        for m, rgb in (f.composite or {}).items():
            Image.fromarray(rgb, mode="RGB").save(frames_dir / f"frame_{f.pose.index:03d}_{m}.png")
    picked = [frames[i] for i in np.linspace(0, len(frames) - 1, DEMO.scored).round().astype(int)]
    log(f"RTAO reference at {DEMO.spp} spp on {len(picked)} frames")
    refs = reference_images(scene, picked, ReferenceSettings(spp=DEMO.spp, cache_dir=Path("out") / ".cache" / "rtao"))
    rows = score_frames(picked, refs)
    return {"frames": frames, "picked": picked, "refs": refs, "rows": rows,
            "frame_wall_ms": 1e3 * (wall - tick_s) / len(poses), "tick_ms": tick_ms,
            "gl_renderer": gl, "frames_dir": frames_dir, "points": points}


def write_demo_outputs(q: dict, out: Path) -> list[Path]:
    from psao.eval import report

    written = []
    mid = len(q["picked"]) // 2
    panels = []
    for m in ("psao", "ssao"):
        r = next(r for r in q["rows"] if r.frame == q["picked"][mid].pose.index and r.method == m)
        panels.append((m.upper() if m == "ssao" else f"PSAO-{DEMO.density:g}", q["picked"][mid].ao[m], r.flip_map, r.scores.as_dict()))
    path = out / "side_by_side.png"
    report.side_by_side(q["refs"][mid], panels, path)
    written.append(path)
    path = out / "frame_times.png"
    frame_chart(q, path)
    written.append(path)
    path = out / "scores.json"
    path.write_text(json.dumps([{"frame": r.frame, "method": r.method, **r.scores.as_dict()} for r in q["rows"]], indent=1))
    written.append(path)
    written.append(q["frames_dir"])
    return written


def frame_chart(q: dict, path: Path) -> None:
    """Client GPU ms per frame along the path (PSAO and SSAO), and the scored frames' FLIP."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = q["frames"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    idx = [f.pose.index for f in frames]
    for m, c in (("psao", "tab:blue"), ("ssao", "tab:orange")):
        a.plot(idx, [f.gpu_ms[m] for f in frames], marker=".", color=c, label=m.upper())
        sel = [r for r in q["rows"] if r.method == m]
        b.plot([r.frame for r in sel], [r.scores.flip for r in sel], marker="o", color=c, label=m.upper())
    a.set_xlabel("frame")
    a.set_ylabel("client GPU ms (G-buffer + AO)")
    a.legend()
    a.grid(alpha=0.3)
    b.set_xlabel("frame")
    b.set_ylabel(f"FLIP vs RTAO {DEMO.spp} spp (lower is better)")
    b.legend()
    b.grid(alpha=0.3)
    fig.suptitle(f"psao demo: {DEMO.scene}, N={DEMO.density:g}, {q['gl_renderer']}")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def print_report(scene, s: dict, q: dict, client: list, written: list[Path], seconds: float) -> None:
    from psao.eval.metrics import LPIPS_NOTE
    from psao.eval.quality import mean_scores

    ps, ss = mean_scores(q["rows"], "psao"), mean_scores(q["rows"], "ssao")
    gpu = {m: float(np.median([f.gpu_ms[m] for f in q["frames"]])) for m in ("psao", "ssao")}
    lines = [
        f"psao demo: {scene.name}, PSAO N={DEMO.density:g} ({q['points']:,} points, {DEMO.rays} rays/point), "
        f"{SIZE[0]}x{SIZE[1]}, {q['gl_renderer']}",
        f"stream   psao serve --animate at {s['url']} ({DEMO.tick_hz:g} Hz asked): snapshot {s['snapshot_mb']:.2f} MB in "
        f"{s['snapshot_s']:.2f} s, then {s['stream_mbit_s']:.3f} Mbit/s over {DEMO.stream_seconds:g} s, {s['updates']} updates "
        f"({s['updates_per_s']:.1f}/s), server {s['server_ms_tick']:.1f} ms/tick"
        + (f"; the headless client rendered {s['client_frames']} frames" if s["client_frames"] else ""),
        f"frames   {len(q['frames'])} along the camera path; client GPU ms per frame (median): PSAO {gpu['psao']:.1f}, "
        f"SSAO {gpu['ssao']:.1f}; wall {q['frame_wall_ms']:.0f} ms per frame (both methods, read-back included); "
        f"in-process server tick {q['tick_ms']:.0f} ms (rolling boulders, {DEMO.rays} rays per re-traced point)",
        f"quality  vs RTAO {DEMO.spp} spp on {len(q['picked'])} animated frames: PSAO PSNR {ps.psnr:.2f} dB, SSIM {ps.ssim:.3f}, "
        f"FLIP {ps.flip:.3f} | SSAO PSNR {ss.psnr:.2f} dB, SSIM {ss.ssim:.3f}, FLIP {ss.flip:.3f}",
        *([f"client   its own frames {', '.join(str(c.frame) for c in client)} vs RTAO {DEMO.spp} spp: PSAO PSNR "
           f"{np.mean([c.psao.psnr for c in client]):.2f} dB, FLIP {np.mean([c.psao.flip for c in client]):.3f} | SSAO "
           f"PSNR {np.mean([c.ssao.psnr for c in client]):.2f} dB, FLIP {np.mean([c.ssao.flip for c in client]):.3f}"]
          if client else []),
        f"note     {LPIPS_NOTE}",
        f"wrote    " + "\n         ".join(str(p) for p in written) + (f"\n         {s['client_frames_dir']}" if s["client_frames_dir"] else ""),
        f"done in {seconds:.0f} s",
    ]
    print("\n".join(lines))
