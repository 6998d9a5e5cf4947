"""Server tick with the selection on and off, in one run, on the built-in dynamic scenes.

For each scene: bake at density N with the tick's ray count (the bake is the first sync at t = 0), then
tick at 60 Hz scene time with a camera following the scene's first camera path (one client), draining
the dirty sets after every tick as the service does. First with the selection on (points in the
extended view that are on deforming geometry or within the AO distance of a moving instance), then,
on the same grid, with the selection off (every point in the extended view, every tick). Reports per
scene mean and median tick time and points traced per tick, the ratio of rays per tick (target >= 10x
on courtyard and space), the stage split animate / select / trace / grid, and whether the median tick
fits 16.7 ms (60 Hz) or which stage is the bottleneck.

    .venv/bin/python -m benchmarks.bench_tick [--density 256] [--ticks 40] [--ticks-off 4] [--rays 32]
        [--scenes courtyard,space,robots] [--workers 0] [--tracer embree|warp] [--out out/bench_tick]
        [--sweep 0,2,4,8,16]

The threshold sweep (courtyard at --sweep-density) shows what the threshold buys: with R rays one ray
is 255 / R codes, and the same point traces the same rays every tick, so thresholds below one ray's
worth only filter nothing but rounding.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts

FRAME_S = 1.0 / 60.0
RAY_RATIO_TARGET = 10.0
RATIO_SCENES = ("courtyard", "space")
STAGES = ("animate", "select", "trace", "grid")


def camera_at_time(scene, t: float, aspect: float = 16 / 9):
    from psao.scene.camera import camera_at, look_at, perspective, scene_camera
    path = scene_camera(scene)
    eye, target = camera_at(path, t)
    lo, hi = scene.world_bounds()
    far = 2.0 * float(np.linalg.norm(hi - lo))
    return look_at(eye, target), perspective(path.fov_y, aspect, 0.05, far)


def run_ticks(tick, scene, times) -> list[dict]:
    out = []
    for t in times:
        tick.set_cameras([camera_at_time(scene, t)])
        s = tick(tick.grid, t)
        tick.grid.take_dirty()  # the service drains the dirty sets after every tick
        out.append(s.to_dict())
    return out


def summarise(rows: list[dict]) -> dict:
    total = np.array([r["seconds_total"] for r in rows]) * 1e3
    res = {"ticks": len(rows), "mean_ms": float(total.mean()), "median_ms": float(np.median(total)),
           "p90_ms": float(np.quantile(total, 0.9)),
           "traced_mean": float(np.mean([r["traced"] for r in rows])),
           "changed_mean": float(np.mean([r["changed"] for r in rows])),
           "cells_dirty_mean": float(np.mean([r["cells_dirty"] for r in rows])),
           "considered": int(rows[0]["considered"])}
    for st in STAGES:
        res[f"{st}_median_ms"] = float(np.median([r[f"seconds_{st}"] for r in rows]) * 1e3)
    return res


def bench_scene(name: str, args) -> dict:
    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings, TickSettings
    from psao.server.tick.server_tick import ServerTick

    scene = load_scene(f"builtin:{name}")
    t0 = time.perf_counter()
    bake = bake_scene(scene, BakeSettings(density=args.density, rays=args.rays, workers=args.workers),
                      show_progress=False)
    bake_s = time.perf_counter() - t0
    tick = ServerTick(bake, TickSettings(rays=args.rays, workers=args.workers, tracer=args.tracer), baked_time=0.0)
    try:
        tick.grid.take_dirty()
        on_times = [FRAME_S * (k + 1) for k in range(args.ticks)]
        rows_on = run_ticks(tick, scene, on_times)
        tick.settings.selection = False
        off_times = [on_times[-1] + FRAME_S * (k + 1) for k in range(args.ticks_off)]
        rows_off = run_ticks(tick, scene, off_times)
    finally:
        tick.close()
    on, off = summarise(rows_on), summarise(rows_off)
    # 0 traced with the selection gives an infinite ratio: that is no measurement, and the verdict fails it
    ratio = off["traced_mean"] / on["traced_mean"] if on["traced_mean"] else float("inf")
    return {"scene": name, "points": int(bake.stats["points_kept"]), "bake_s": bake_s, "on": on, "off": off,
            "ray_ratio": ratio, "rows_on": rows_on, "rows_off": rows_off}


def threshold_sweep(name: str, thresholds: list[int], args) -> list[dict]:
    """Changed points and dirty cells per tick against the threshold, on copies of one bake; and the
    largest |stored - full re-trace| at the end over the points not waiting for a view (the threshold
    bounds it)."""
    import copy
    from psao.protocol import pointword as pw
    from psao.scene import load_scene
    from psao.server.bake import BakeResult, bake_scene
    from psao.server.settings import BakeSettings, TickSettings
    from psao.server.tick.server_tick import ServerTick

    scene = load_scene(f"builtin:{name}")
    bake = bake_scene(scene, BakeSettings(density=args.sweep_density, rays=args.rays, workers=args.workers),
                      show_progress=False)
    bake.tracer.close()
    out = []
    times = [FRAME_S * (k + 1) for k in range(args.sweep_ticks)]
    for th in thresholds:
        copy_ = BakeResult(scene, copy.deepcopy(bake.grid), bake.pointsets, bake.stats, None)
        tick = ServerTick(copy_, TickSettings(rays=args.rays, workers=args.workers, threshold=th, tracer=args.tracer),
                          baked_time=0.0)
        try:
            rows = run_ticks(tick, scene, times)
            ids = np.flatnonzero(tick.present() & ~tick.stale)  # stale: outside the view, re-traced once seen
            pos, nrm = tick.world_points(tick.last_frame, ids)
            full = pw.quantise_ao(tick.tracer.visibility(pos, nrm, ids, tick.trace_settings)).astype(np.int64)
            stored = (tick.grid.cells[tick.slot[ids], tick.index[ids]] & 0xFF).astype(np.int64)
        finally:
            tick.close()
        out.append({"threshold": th, "changed_mean": float(np.mean([r["changed"] for r in rows])),
                    "cells_dirty_mean": float(np.mean([r["cells_dirty"] for r in rows])),
                    "max_abs_error_codes": int(np.abs(stored - full).max()),
                    "mean_abs_error_codes": float(np.abs(stored - full).mean()),
                    "stale_points": int(tick.stale.sum())})
    return out


def bottleneck(summary: dict) -> str:
    return max(STAGES, key=lambda st: summary[f"{st}_median_ms"])


def print_table(results: list[dict], args) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"server tick, N = {args.density:g}, {args.rays} rays/point, {args.tracer} tracer, one camera "
                        f"(scene's path), 60 Hz scene time")
    for col in ("scene", "points", "selection", "ticks", "mean ms", "median ms", "traced/tick", "changed/tick",
                "cells/tick", "animate", "select", "trace", "grid"):
        table.add_column(col, justify="right")
    for r in results:
        for label in ("on", "off"):
            s = r[label]
            table.add_row(r["scene"], f"{r['points']:,}", label, str(s["ticks"]), f"{s['mean_ms']:.1f}",
                          f"{s['median_ms']:.1f}", f"{s['traced_mean']:,.0f}", f"{s['changed_mean']:,.0f}",
                          f"{s['cells_dirty_mean']:,.0f}",
                          *(f"{s[f'{st}_median_ms']:.1f}" for st in STAGES))
    console = Console(width=170)
    console.print(table)
    for r in results:
        on = r["on"]
        console.print(f"{r['scene']}: median tick {on['median_ms']:.1f} ms, bottleneck {bottleneck(on)} "
                      f"({on[bottleneck(on) + '_median_ms']:.1f} ms median)")


def judge(results: list[dict]) -> Verdicts:
    """Ray ratio on the scenes the target names (0 traced with the selection is a miss: nothing was
    measured), and the median tick against one 60 Hz frame."""
    v = Verdicts("bench_tick")
    for r in results:
        if r["scene"] in RATIO_SCENES:
            v.check(f"{r['scene']} rays per tick, selection off / on", r["ray_ratio"], ">=", RAY_RATIO_TARGET)
        v.check(f"{r['scene']} median tick ms, selection on", r["on"]["median_ms"], "<=", 1e3 * FRAME_S)
    return v


def chart(results: list[dict], path: Path, args) -> None:
    """Left: median tick split by stage with the selection on (linear, the 60 Hz line); right: points
    traced per tick on and off (log), with the ratio."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    names = [r["scene"] for r in results]
    xs = np.arange(len(results))
    colors = {"animate": "#6a9fd8", "select": "#9bd86a", "trace": "#d86a6a", "grid": "#d8c36a"}
    bottom = np.zeros(len(results))
    for st in STAGES:
        v = np.array([r["on"][f"{st}_median_ms"] for r in results])
        ax1.bar(xs, v, bottom=bottom, color=colors[st], label=st)
        bottom += v
    for k, r in enumerate(results):
        ax1.text(xs[k], bottom[k], f"{r['on']['median_ms']:.0f} ms\n(off: {r['off']['median_ms']:.0f} ms)",
                 ha="center", va="bottom", fontsize=8)
    ax1.axhline(1e3 * FRAME_S, color="k", ls="--", lw=1, label="16.7 ms (60 Hz)")
    ax1.set_xticks(xs, names)
    ax1.set_ylim(0, max(bottom.max(), 1e3 * FRAME_S) * 1.3)
    ax1.set_ylabel("median tick, selection on, ms (stage medians stacked)")
    ax1.legend(fontsize=8)
    on = np.array([r["on"]["traced_mean"] for r in results])
    off = np.array([r["off"]["traced_mean"] for r in results])
    ax2.bar(xs - 0.2, np.maximum(on, 1), 0.4, label="selection on")
    ax2.bar(xs + 0.2, np.maximum(off, 1), 0.4, label="selection off (every visible point)")
    for k, r in enumerate(results):
        label = "0 traced" if on[k] == 0 else f"{r['ray_ratio']:.0f}x fewer"
        ax2.text(xs[k], off[k] * 1.15, label, ha="center", va="bottom", fontsize=9)
    ax2.set_xticks(xs, names)
    ax2.set_yscale("log")
    ax2.set_ylim(1, off.max() * 4)
    ax2.set_ylabel("points traced per tick (mean)")
    ax2.legend(fontsize=8, loc="lower right")
    fig.suptitle(f"PSAO server tick, N = {args.density:g}, {args.rays} rays per point, 2-core CPU (Embree)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--density", type=float, default=256.0)
    ap.add_argument("--ticks", type=int, default=40, help="ticks with the selection on")
    ap.add_argument("--ticks-off", type=int, default=4, help="ticks with the selection off (each traces every visible point)")
    ap.add_argument("--rays", type=int, default=32)
    ap.add_argument("--workers", type=int, default=0, help="tracer processes (0: all cores)")
    ap.add_argument("--tracer", default="embree", help="tracer back-end of the ticks: embree (CPU) or warp (CUDA when present)")
    ap.add_argument("--scenes", default="courtyard,space,robots")
    ap.add_argument("--out", type=Path, default=Path("out/bench_tick"))
    ap.add_argument("--sweep", default="0,2,4,8,16", help="thresholds (AO codes) for the courtyard sweep; '' skips it")
    ap.add_argument("--sweep-density", type=float, default=64.0)
    ap.add_argument("--sweep-ticks", type=int, default=20)
    args = ap.parse_args(argv)
    if args.ticks < 1 or args.ticks_off < 1 or args.density <= 0 or args.rays < 1:
        ap.error("ticks, ticks-off and rays must be >= 1, density > 0")
    args.out.mkdir(parents=True, exist_ok=True)
    import os
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (other processes slow every stage)")
    results = []
    for name in args.scenes.split(","):
        t0 = time.perf_counter()
        results.append(bench_scene(name.strip(), args))
        print(f"{name}: {results[-1]['points']:,} points, bake {results[-1]['bake_s']:.1f} s, "
              f"benchmark {time.perf_counter() - t0:.1f} s", flush=True)
    print_table(results, args)
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    chart(results, args.out / "bench_tick.png", args)
    sweep = []
    if args.sweep:
        sweep = threshold_sweep("courtyard", [int(x) for x in args.sweep.split(",")], args)
        print(f"threshold sweep, courtyard N = {args.sweep_density:g}, {args.rays} rays "
              f"(one ray is {255 / args.rays:.1f} codes), {args.sweep_ticks} ticks:")
        for row in sweep:
            print(f"  threshold {row['threshold']:3d} codes: changed/tick {row['changed_mean']:8.0f}, "
                  f"dirty cells/tick {row['cells_dirty_mean']:7.0f}, |stored - full re-trace| max "
                  f"{row['max_abs_error_codes']} mean {row['mean_abs_error_codes']:.3f} codes "
                  f"({row['stale_points']} points outside the view wait, stale)")
    (args.out / "bench_tick.json").write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                                          "results": results, "threshold_sweep": sweep}, indent=1))
    print(f"wrote {args.out / 'bench_tick.png'} and {args.out / 'bench_tick.json'}")
    return judge(results).exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
