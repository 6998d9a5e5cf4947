"""PSAO AO pass against the SSAO baseline, same renderer, same frames, one run.

For each point density N the courtyard's grid is built with the server's own point generation and
Grid; the AO values come from a bake when --bake is given, otherwise a synthetic field (the pass's
cost depends on how cells are filled, not on the AO values). Every frame of the camera path is
rendered once as warm-up, then each AO pass is timed on the same G-buffer with GPU timer queries and
with wall time bracketed by ctx.finish(). Target: PSAO <= 1.5x SSAO (AO + blur), flat in N.

`--against TREE` judges this tree's AO pass against another checkout's (e.g. an older commit made with
`git worktree add /tmp/before COMMIT`): this file's measuring code runs in child processes on each tree's
own modules (renderer, shaders, grid build; PYTHONPATH=TREE), interleaved for `--rounds` rounds (A B,
B A, A B, ...). A run's figure is PSAO's GPU time over SSAO's timed right next to it (median over a
frame's repeats, geometric mean over frames), so load that changes during a run cancels out pair by
pair; the growth at each N
is the median over rounds of this tree's figure over the other tree's in the same round (target: at most
MAX_GROWTH, +15%), so one disturbed round does not decide. Process CPU time per pass (llvmpipe renders
on the CPU, in this process's threads) is printed beside it as a cross-check that preemption by other
processes does not count in.

    .venv/bin/python -m benchmarks.bench_render [--densities 64,256,1024] [--frames 4] [--bake] [--against TREE [--rounds 3]]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts

TARGET_RATIO = 1.5
MAX_GROWTH = 1.15  # --against: this tree's PSAO/SSAO ratio over the other tree's, at each N


def child_argv(argv: list[str]) -> list[str]:
    """The benchmark's arguments for a child run: without --against/--rounds/--json/--chart."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg in ("--against", "--rounds", "--chart"):
            skip = True
        elif arg != "--json" and not arg.startswith(("--against=", "--rounds=", "--chart=")):
            out.append(arg)
    return out


def run_child(tree: Path, args: list[str], label: str, chart_path: Path) -> dict:
    """This file's benchmark run on `tree`'s modules (its renderer, shaders and grid build): its --json result."""
    cmd = [sys.executable, str(Path(__file__).resolve()), *args, "--json", "--chart", str(chart_path)]
    print(f"{label} on {tree}: {' '.join(cmd[1:])}", flush=True)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    proc = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, env=env)
    for line in proc.stdout.splitlines()[:-1]:
        if line.startswith("N="):
            print(f"  [{label}] {line}", flush=True)
    last = proc.stdout.strip().splitlines()[-1:] or [""]
    if not last[0].startswith("{"):
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"bench_render: the {label} run on {tree} failed: {tail}")
    return json.loads(last[0])


def run_against(tree: Path, rounds: int, argv: list[str]) -> tuple[list[dict], list[dict]]:
    """`rounds` runs of each tree, interleaved, the order swapped every round: (this tree's, the other's)."""
    here = Path(__file__).resolve().parents[1]
    args = child_argv(argv)
    runs: dict[str, list[dict]] = {"this tree": [], "baseline": []}
    trees = [("this tree", here), ("baseline", tree)]
    for k in range(rounds):
        print(f"round {k + 1}/{rounds}", flush=True)
        for label, root in trees if k % 2 == 0 else trees[::-1]:
            chart_path = here / "out" / "bench_render" / f"against_{label.replace(' ', '_')}.png"
            runs[label].append(run_child(root, args, label, chart_path))
    return runs["this tree"], runs["baseline"]


def judge_against(tree: Path, here: list[dict], base: list[dict], v) -> None:
    """Per N: the median over rounds of this tree's paired PSAO/SSAO figure over the baseline's in the same
    round; the same for process CPU time, printed."""
    for i, row in enumerate(here[0]["rows"]):
        pairs = [(h["rows"][i], b["rows"][i]) for h, b in zip(here, base)]
        growths = [h["ratio_pairs"] / b["ratio_pairs"] for h, b in pairs]
        for k, ((h, b), g) in enumerate(zip(pairs, growths)):
            print(f"N={row['density']:g} round {k + 1}: PSAO/SSAO {h['ratio_pairs']:.3f} here (PSAO {h['gpu_ms']['psao']:.2f} ms), "
                  f"{b['ratio_pairs']:.3f} on {tree} (PSAO {b['gpu_ms']['psao']:.2f} ms): growth x{g:.3f}")
        growth = float(np.median(growths))
        cpu = float(np.median([h["ratio_cpu"] / b["ratio_cpu"] for h, b in pairs]))
        raw = float(np.median([h["gpu_ms"]["psao"] / b["gpu_ms"]["psao"] for h, b in pairs]))
        print(f"N={row['density']:g}: median growth x{growth:.3f} over {len(growths)} rounds (cross-checks: "
              f"CPU-time PSAO/SSAO x{cpu:.3f}, PSAO GPU ms alone x{raw:.3f})")
        chart_against(pairs, growth, Path("out") / "bench_render" / f"against_N{row['density']:g}.png", tree)
        v.check(f"N={row['density']:g} PSAO/SSAO ratio growth against {tree} (median of {len(growths)} interleaved rounds)",
                growth, "<=", MAX_GROWTH)


def build_grid(scene, density: float, bake: bool, rays: int):
    from psao.protocol import pointword as pw
    from psao.server.bake import build_scene_grid
    from psao.server.points.generate import generate_points, instance_seed
    try:
        from psao.server.settings import BakeSettings, PointSettings
    except ImportError:  # checkouts from before settings.py (an --against baseline)
        from psao.server.bake import BakeSettings
        from psao.server.points.generate import PointSettings

    if bake:
        from psao.server.bake import bake_scene

        result = bake_scene(scene, BakeSettings(density=density, rays=rays), show_progress=False)
        result.tracer.close()
        return result.grid
    settings = PointSettings(density=density)
    sets = [generate_points(scene.meshes[i.mesh], i.transform, settings, seed=instance_seed(0, k))
            for k, i in enumerate(scene.instances)]
    grid = build_scene_grid(scene, sets)  # as the server builds it: double-sided instances flagged
    t = grid.point_table()
    field = 0.55 + 0.45 * np.sin(1.3 * t.local_pos[:, 0]) * np.cos(0.9 * t.local_pos[:, 2])
    grid.set_ao(t.slot, t.index, pw.quantise_ao(field))
    return grid


def time_pass(ctx, timer, name, fn, wall: dict, cpu: dict):
    ctx.finish()
    start, start_cpu = time.perf_counter(), time.process_time()
    with timer.measure(name):
        fn()
    ctx.finish()
    wall.setdefault(name, []).append((time.perf_counter() - start) * 1e3)
    cpu.setdefault(name, []).append((time.process_time() - start_cpu) * 1e3)


def measure(renderer, views, repeats: int) -> dict:
    """Median GPU, wall and process CPU ms per pass over all frames x repeats (passes alternate order per
    frame), and PSAO over SSAO timed right next to each other (GPU timer, process CPU): the median over a
    frame's repeats, then the geometric mean over frames (frames differ in their ratio, so one median over
    all of them would jump between frames)."""
    ctx, timer = renderer.ctx, renderer.timer
    gpu: dict[str, list[float]] = {}
    wall: dict[str, list[float]] = {}
    cpu: dict[str, list[float]] = {}
    paired: dict[str, list[float]] = {"gpu": [], "cpu": []}
    for view, proj in views:
        renderer.submit(view, proj)  # warm-up and G-buffer of this frame
        timer.collect()
        frame_gpu: dict[str, list[float]] = {}
        frame_cpu: dict[str, list[float]] = {}
        for rep in range(repeats):
            passes = [("psao", renderer.psao.run),
                      ("ssao", lambda: (renderer.ssao.run_occlusion(view, proj), renderer.ssao.run_blur()))]
            for name, fn in passes[:: 1 if rep % 2 == 0 else -1]:
                time_pass(ctx, timer, name, fn, wall, frame_cpu)
            for name, ms in timer.collect().items():
                frame_gpu.setdefault(name, []).append(ms)
        for store, frame, key in ((gpu, frame_gpu, "gpu"), (cpu, frame_cpu, "cpu")):
            for name, values in frame.items():
                store.setdefault(name, []).extend(values)
            paired[key].append(float(np.median(np.array(frame["psao"]) / np.array(frame["ssao"]))))
    return {"gpu_ms": {k: float(np.median(v)) for k, v in gpu.items()},
            "wall_ms": {k: float(np.median(v)) for k, v in wall.items()},
            "cpu_ms": {k: float(np.median(v)) for k, v in cpu.items()},
            "ratio_pairs": float(np.exp(np.mean(np.log(paired["gpu"])))),
            "ratio_cpu": float(np.exp(np.mean(np.log(paired["cpu"]))))}


def run_density(scene, density, args, views, size):
    from psao.client.render.renderer import FrameRenderer

    t0 = time.perf_counter()
    grid = build_grid(scene, density, args.bake, args.rays)
    build_s = time.perf_counter() - t0
    with FrameRenderer(scene, size, "both", ssao_samples=args.ssao_samples) as r:
        r.upload_grid(grid.instances, grid.buckets, grid.cells)
        m = measure(r, views, args.repeats)
        holes = hole_fraction(r, views)
        if args.images:
            save_images(r, views[0], Path(args.images), int(density))
    row = {"density": density, "points": int(grid.n_points()), "cells": int(len(grid.allocated_cells())),
           "build_s": build_s, "holes": holes, **m, "ratio_gpu": m["gpu_ms"]["psao"] / m["gpu_ms"]["ssao"],
           "ratio_wall": m["wall_ms"]["psao"] / m["wall_ms"]["ssao"]}
    print(format_row(row), flush=True)
    return row


def hole_fraction(renderer, views) -> float:
    """Covered pixels where no point has weight (eq. 4 falls back to AO = 1), over all frames."""
    covered = holes = 0
    for view, proj in views:
        frame = renderer.render(view, proj)
        covered += int(frame.mask.sum())
        holes += int((frame.mask & (frame.psao_weight == 0)).sum())
    return holes / max(covered, 1)


def save_images(renderer, view_proj, out: Path, density: int) -> None:
    from psao.client.render.output import save_frame

    frame = renderer.render(*view_proj, read_gbuffer=False)
    for path in save_frame(frame, out / f"N{density}", 0):
        print(f"  wrote {path}")


def format_row(r) -> str:
    g, w = r["gpu_ms"], r["wall_ms"]
    return (f"N={r['density']:>6g} points={r['points']:>9,} cells={r['cells']:>8,} holes={r['holes']:.2%} | "
            f"GPU ms: psao {g['psao']:7.2f} ssao {g['ssao']:7.2f} ratio {r['ratio_gpu']:.2f} | "
            f"wall ms: psao {w['psao']:7.2f} ssao {w['ssao']:7.2f} ratio {r['ratio_wall']:.2f} | "
            f"paired ratio GPU {r['ratio_pairs']:.2f} CPU {r['ratio_cpu']:.2f}")


def chart(rows, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    ax.bar(x - 0.2, [r["gpu_ms"]["psao"] for r in rows], 0.4, label="PSAO pass")
    ax.bar(x + 0.2, [r["gpu_ms"]["ssao"] for r in rows], 0.4, label="SSAO (AO + blur)")
    ax.set_xticks(x, [f"N={r['density']:g}\nratio {r['ratio_gpu']:.2f}" for r in rows])
    ax.set_ylabel("GPU ms per frame (timer queries)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def chart_against(pairs, growth: float, path: Path, tree: Path) -> None:
    """PSAO/SSAO of both trees in each round, and the median growth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(pairs))
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    ax.bar(x - 0.2, [b["ratio_gpu"] for _, b in pairs], 0.4, label=f"baseline ({tree.name})")
    ax.bar(x + 0.2, [h["ratio_gpu"] for h, _ in pairs], 0.4, label="this tree")
    ax.set_xticks(x, [f"round {k + 1}\nx{h['ratio_gpu'] / b['ratio_gpu']:.2f}" for k, (h, b) in enumerate(pairs)])
    ax.set_ylabel("PSAO / SSAO GPU time")
    ax.set_title(f"N={pairs[0][0]['density']:g}: median growth x{growth:.2f} (limit x{MAX_GROWTH})")
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    print(f"chart: {path}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--size", default="640x360")
    p.add_argument("--densities", default="64,256,1024")
    p.add_argument("--frames", type=int, default=4, help="frames along the camera path")
    p.add_argument("--repeats", type=int, default=5, help="timed repetitions of each pass per frame")
    p.add_argument("--ssao-samples", type=int, default=16)
    p.add_argument("--bake", action="store_true", help="trace real AO (slow) instead of a synthetic field")
    p.add_argument("--rays", type=int, default=64)
    p.add_argument("--images", default=None, metavar="DIR", help="also save the first frame's PNGs per N")
    p.add_argument("--chart", default="out/bench_render/bench_render.png")
    p.add_argument("--json", action="store_true")
    p.add_argument("--against", type=Path, default=None, metavar="TREE",
                   help="run this tree and another checkout, interleaved, and judge the ratio's growth against it")
    p.add_argument("--rounds", type=int, default=3, help="--against: runs of each tree (median of the paired growths)")
    args = p.parse_args(argv)
    if args.against is not None:
        if args.rounds < 1:
            raise SystemExit("bench_render: --rounds must be at least 1")
        here, base = run_against(args.against, args.rounds, list(sys.argv[1:] if argv is None else argv))
        v = Verdicts("bench_render")
        worst = float(np.median([run["worst_ratio"] for run in here]))
        v.check(f"worst PSAO/SSAO GPU time ratio over N={args.densities} (median of {args.rounds} runs)", worst, "<=", TARGET_RATIO)
        judge_against(args.against, here, base, v)
        return v.exit_code()

    from psao.client.render.output import parse_size
    from psao.client.render.views import path_matrices, path_times
    from psao.scene import load_scene, scene_camera

    size = parse_size(args.size)
    scene = load_scene(args.scene)
    path = scene_camera(scene)
    views = [path_matrices(scene, path, float(t), size) for t in path_times(path, args.frames)]
    print(f"{scene.name} at {size[0]}x{size[1]}, {args.frames} frames x {args.repeats} repeats, "
          f"SSAO {args.ssao_samples} samples, AO {'baked' if args.bake else 'synthetic'}")
    rows = []
    for density in [float(d) for d in args.densities.split(",")]:
        rows.append(run_density(scene, density, args, views, size))
    worst = max(r["ratio_gpu"] for r in rows)
    # Growth with N, normalised by SSAO (whose cost does not depend on N): the machine's load changes
    # between densities, the ratio measured on the same frames at the same time does not.
    spread = max(r["ratio_gpu"] for r in rows) / min(r["ratio_gpu"] for r in rows)
    print(f"ratio max/min over N {spread:.2f}")
    v = Verdicts("bench_render")
    v.check(f"worst PSAO/SSAO GPU time ratio over N={args.densities}", worst, "<=", TARGET_RATIO)
    chart(rows, Path(args.chart), f"{scene.name} {size[0]}x{size[1]}: PSAO vs SSAO-{args.ssao_samples}")
    print(f"chart: {args.chart}")
    if args.json:
        print(json.dumps({"rows": rows, "worst_ratio": worst, "spread": spread}))
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
