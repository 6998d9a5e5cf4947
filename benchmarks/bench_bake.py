"""Bake accuracy and tracing throughput in one run; the verdicts check the reconstruction MAE at N = 256
against each scene's target (TARGETS).

For each scene and density: points kept, dropped by overflow, hole fraction and reconstruction MAE at
random surface probes against AO traced directly there with many rays, and the share of the workers'
time spent in the Embree query itself ("eff", seconds measured inside the workers during the bake; the
tracer against a bare embreex run on the same rays is bench_realtime's tracer part). Prints a table and
writes a chart.

--gap-fills 0,4 adds rows with psao.server.points.gapfill on (4 rounds of adding points where the client's
lookup finds none) beside the paper's points, to compare holes, drops and time.

    python -m benchmarks.bench_bake [--scenes builtin:cornell,builtin:courtyard] [--densities 64,256,1024]
        [--spawn-ratios 2,4] [--gap-fills 0,4]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from psao.scene import load_scene
from psao.server.bake import bake_scene, reconstruction_error, sample_probes
from psao.server.settings import BakeSettings, GapFillSettings, ProbeSettings

from benchmarks.verdicts import Verdicts

TARGETS = {"builtin:courtyard": 0.03, "builtin:cornell": 0.02}  # recon_mae at N=256


def measure(spec: str, density: float, rays: int, probes: int, probe_rays: int, spawn_ratio: float,
            gap_fill: int = 0) -> dict:
    scene = load_scene(spec)
    res = bake_scene(scene, BakeSettings(density=density, rays=rays, spawn_ratio=spawn_ratio,
                                         gap_fill=GapFillSettings(passes=gap_fill)))
    try:
        err = reconstruction_error(res.grid, scene, res.tracer, sample_probes(scene, probes), rays=probe_rays)
    finally:
        res.tracer.close()
    s = res.stats
    return {
        "scene": spec, "density": density, "spawn_ratio": spawn_ratio, "gap_fill": gap_fill, "points": s["points_kept"],
        "points_gap_fill": s["points_gap_fill"], "seconds_gap_fill": s["seconds_gap_fill"],
        "dropped_pct": 100 * s["points_dropped_overflow"] / max(s["points_generated"], 1),
        "holes_pct": 100 * err["hole_fraction"], "recon_mae": err["recon_mae"], "recon_p99": err["recon_p99"],
        "seconds_points": s["seconds_points"], "seconds_trace": s["seconds_trace"],
        "mrays_s": s["rays_per_second"] / 1e6, "embree_mrays_s": s["embree_rays_per_second"] / 1e6,
        "trace_efficiency": s["trace_efficiency"], "mrays_s_wall": s["rays_per_second_wall"] / 1e6,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="builtin:cornell,builtin:courtyard")
    ap.add_argument("--densities", default="64,256")
    ap.add_argument("--rays", type=int, default=128)
    ap.add_argument("--spawn-ratios", default="2", help="comma list: points spawned per point kept")
    ap.add_argument("--gap-fills", default="0", help="comma list: gap-fill passes (0 = off), e.g. 0,4")
    ap.add_argument("--probes", type=int, default=ProbeSettings.probes)
    ap.add_argument("--probe-rays", type=int, default=ProbeSettings.rays)
    ap.add_argument("--out", type=Path, default=Path("out/bench_bake"))
    args = ap.parse_args(argv)
    rows = [measure(spec, float(n), args.rays, args.probes, args.probe_rays, float(sr), int(gf))
            for spec in args.scenes.split(",") for sr in args.spawn_ratios.split(",")
            for gf in args.gap_fills.split(",") for n in args.densities.split(",")]
    header = f"{'scene':20s} {'N':>6s} {'spawn':>5s} {'fill':>4s} {'added':>7s} {'fill s':>6s} {'points':>10s} {'dropped%':>9s} {'holes%':>7s} {'MAE':>7s} {'p99':>6s} " \
             f"{'Mrays/s':>8s} {'Embree':>8s} {'eff':>5s} {'target':>10s}"
    print(header)
    for r in rows:
        target = TARGETS.get(r["scene"]) if r["density"] == 256 else None
        verdict = "" if target is None else f"<{target}"
        print(f"{r['scene']:20s} {r['density']:6g} {r['spawn_ratio']:5g} {r['gap_fill']:4d} {r['points_gap_fill']:7,d} "
              f"{r['seconds_gap_fill']:6.1f} {r['points']:10,d} {r['dropped_pct']:9.3f} {r['holes_pct']:7.3f} "
              f"{r['recon_mae']:7.4f} {r['recon_p99']:6.3f} {r['mrays_s']:8.2f} {r['embree_mrays_s']:8.2f} "
              f"{r['trace_efficiency']:5.2f} {verdict:>10s}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_bake.json").write_text(json.dumps(rows, indent=1))
    _chart(rows, args.out / "bench_bake.png")
    print(f"wrote {args.out / 'bench_bake.json'} and {args.out / 'bench_bake.png'}")
    v = Verdicts("bench_bake")
    for r in rows:
        target = TARGETS.get(r["scene"]) if r["density"] == 256 else None
        if target is not None:
            v.check(f"{r['scene']} N=256 spawn {r['spawn_ratio']:g} gap fill {r['gap_fill']} reconstruction MAE",
                    r["recon_mae"], "<", target)
    return v.exit_code()


def _chart(rows, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for spec, sr, gf in dict.fromkeys((r["scene"], r["spawn_ratio"], r["gap_fill"]) for r in rows):
        rs = [r for r in rows if (r["scene"], r["spawn_ratio"], r["gap_fill"]) == (spec, sr, gf)]
        n = [r["density"] for r in rs]
        label = f"{spec} spawn {sr:g}x" + (f" gap fill {gf}" if gf else "")
        axes[0].plot(n, [r["recon_mae"] for r in rs], "o-", label=label)
        axes[1].plot(n, [r["holes_pct"] for r in rs], "o-", label=label)
        axes[2].plot(n, [r["trace_efficiency"] for r in rs], "o-", label=label)
    axes[0].set(title="reconstruction MAE vs traced truth", xlabel="N (points / unit^2)", xscale="log")
    axes[1].set(title="hole fraction (%)", xlabel="N", xscale="log")
    axes[2].set(title="tracer / bare Embree throughput", xlabel="N", xscale="log", ylim=(0, 1.1))
    axes[2].axhline(0.8, color="grey", ls="--", lw=1)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)


if __name__ == "__main__":
    raise SystemExit(main())
