"""Where a bake's reconstruction error comes from: the probe reference's noise, the points' noise, the lookup.

`recon_mae` (src/psao/server/bake.reconstruction_error, benchmarks/bench_scenes.py) is the mean |AO the client
reconstructs at random visible surface probes - AO traced at the probes|. Three things make it up, and this
script separates them on one bake:
  (a) the reference's own Monte Carlo error: the probes traced with --probe-rays (and 256) against
      --truth-rays on the same probes (other ray seeds);
  (b) the points' noise: the same grid with every point traced again with --point-rays, scored against the
      fine truth; the drop is what the bake's rays per point cost;
  (c) the lookup (interpolation over r, leaks, missing points): what is left, broken down by the lookup step
      that answered (src/psao/protocol/reconstruct.py) and by the traced AO, with a top view of where the error lies.

    python -m benchmarks.recon_error [--scene ../shared/scenes/sponza/sponza_s_lod4.glb] [--out out/recon_error]

Prints the figures and two verdicts: the probes' reference is within 0.005 of the truth, and the recon MAE
of the bake's own points (its default rays per point, before (b) traces them again) against the truth
meets bench_scenes' target; writes recon_error.json and recon_error.png.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_scenes import TARGETS
from benchmarks.verdicts import Verdicts
from psao.protocol.gridformat import T_D, T_N
from psao.server.settings import ProbeSettings

SPONZA = Path(__file__).resolve().parents[1].parent / "shared" / "scenes" / "sponza" / "sponza_s_lod4.glb"
STEPS = ("r, own face", "2r, near normal", "2r, eq. 3", "3x3x3 ring", "none")


def trace_probes(tracer, scene, probes, rays: int, seed: int) -> np.ndarray:
    from psao.server.settings import TraceSettings

    ids = np.arange(len(probes.instance)) + (1 << 30)
    return tracer.visibility(probes.world_pos, probes.world_normal, ids,
                             TraceSettings(rays=rays, ao_distance=scene.ao_distance, seed=seed, chunk_points=256))


def answering_step(grid, probes) -> np.ndarray:
    """Index into STEPS of the lookup step that answered each probe."""
    from psao.protocol.reconstruct import reconstruct_chunk, reconstruct_ao

    args = (grid.instances, grid.buckets, grid.cells, probes.instance, probes.local_pos.astype(np.float32),
            probes.local_normal.astype(np.float32), T_N, T_D)
    step = np.full(len(probes.instance), len(STEPS) - 2)
    for k, (_, w) in reversed(list(enumerate(reconstruct_chunk(*args)))):
        step[w > 0] = k
    _, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, probes.instance, probes.local_pos, probes.local_normal)
    step[wsum == 0] = len(STEPS) - 1
    return step


def measure(spec: str, probes_n: int, probe_rays: int, truth_rays: int, point_rays: int) -> tuple[dict, dict]:
    from psao.protocol.reconstruct import reconstruct_ao
    from psao.scene import load_scene
    from psao.server.bake import bake_scene, sample_probes
    from psao.server.tracer.grid_trace import trace_grid_points
    from psao.server.points.buried import visible_probes
    from psao.server.settings import BakeSettings, TraceSettings

    scene = load_scene(spec)
    t0 = time.perf_counter()
    res = bake_scene(scene, BakeSettings(), show_progress=False)
    out = {"scene": scene.name, "points": res.stats["points_kept"], "bake_s": time.perf_counter() - t0,
           "bake_rays": res.stats["rays"]}
    try:
        probes = visible_probes(scene, sample_probes(scene, probes_n))
        grid, tracer = res.grid, res.tracer
        truth = trace_probes(tracer, scene, probes, truth_rays, seed=999)
        ref = {k: trace_probes(tracer, scene, probes, k, seed=777) for k in sorted({256, probe_rays})}
        mae = lambda a, b: float(np.abs(a - b).mean())  # noqa: E731
        ao, _ = reconstruct_ao(grid.instances, grid.buckets, grid.cells, probes.instance, probes.local_pos, probes.local_normal)
        out.update(probes=len(truth), probe_rays=probe_rays, truth_rays=truth_rays, point_rays=point_rays)
        for k, v in ref.items():
            out[f"reference_{k}_vs_truth"] = mae(v, truth)
            out[f"recon_vs_{k}"] = mae(ao, v)
        out["recon_vs_truth"] = mae(ao, truth)
        trace_grid_points(grid, scene, tracer, TraceSettings(rays=point_rays, ao_distance=scene.ao_distance, chunk_points=512))
        fine, _ = reconstruct_ao(grid.instances, grid.buckets, grid.cells, probes.instance, probes.local_pos, probes.local_normal)
        out["recon_fine_points_vs_truth"] = mae(fine, truth)
        out["points_noise_part"] = out["recon_vs_truth"] - out["recon_fine_points_vs_truth"]
        err = np.abs(fine - truth)
        step = answering_step(grid, probes)
        out["steps"] = {name: {"share": float((step == k).mean()), "mae": float(err[step == k].mean()) if (step == k).any() else 0.0,
                               "part": float(err[step == k].sum() / len(err))} for k, name in enumerate(STEPS)}
        bins = [(0, 0.01), (0.01, 0.2), (0.2, 0.5), (0.5, 0.8), (0.8, 0.95), (0.95, 1.01)]
        out["by_truth_ao"] = {f"{lo}-{hi}": {"share": float(((truth >= lo) & (truth < hi)).mean()),
                                             "part": float(err[(truth >= lo) & (truth < hi)].sum() / len(err))} for lo, hi in bins}
        out["error_above_0.1"] = {"share": float((err > 0.1).mean()), "part": float(err[err > 0.1].sum() / len(err))}
        data = {"pos": probes.world_pos, "err": err, "step": step, "truth": truth}
    finally:
        res.tracer.close()
    return out, data


def picture(r: dict, data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6), dpi=100, gridspec_kw={"width_ratios": [1, 1, 1.6]})
    parts = {f"reference {r['probe_rays']} rays\nvs {r['truth_rays']}": r[f"reference_{r['probe_rays']}_vs_truth"],
             "reference 256 rays": r["reference_256_vs_truth"],
             f"points' noise\n({r['bake_rays']} -> {r['point_rays']} rays)": r["points_noise_part"],
             "lookup\n(fine points)": r["recon_fine_points_vs_truth"]}
    axes[0].bar(range(len(parts)), list(parts.values()), color=["C7", "C7", "C1", "C3"])
    axes[0].set_xticks(range(len(parts)), list(parts.keys()), fontsize=7)
    axes[0].axhline(TARGETS["recon_mae"], color="k", ls="--", lw=0.8)
    axes[0].set_ylabel("mean |error| over probes")
    axes[0].set_title(f"{r['scene']}: MAE {r['recon_vs_truth']:.4f} (target {TARGETS['recon_mae']}), parts", fontsize=9)
    names = list(r["steps"])
    axes[1].bar(range(len(names)), [r["steps"][n]["part"] for n in names], color="C3")
    for k, n in enumerate(names):
        axes[1].text(k, r["steps"][n]["part"], f"{r['steps'][n]['share']:.1%}\nMAE {r['steps'][n]['mae']:.3f}", ha="center",
                     va="bottom", fontsize=7)
    axes[1].set_xticks(range(len(names)), names, rotation=20, fontsize=7)
    axes[1].margins(y=0.15)
    axes[1].set_title("lookup part by the step that answered", fontsize=9)
    pos, err = data["pos"], data["err"]
    order = np.argsort(err)
    sc = axes[2].scatter(pos[order, 0], pos[order, 2], c=err[order], s=2, cmap="magma", vmin=0, vmax=0.25)
    axes[2].set_aspect("equal")
    axes[2].set_title("lookup error at the probes, top view (x, z)", fontsize=9)
    fig.colorbar(sc, ax=axes[2], fraction=0.03)
    fig.tight_layout()
    fig.savefig(path)  # main made its folder
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(SPONZA))
    ap.add_argument("--probes", type=int, default=20000)
    ap.add_argument("--probe-rays", type=int, default=ProbeSettings.rays, help="the reference bench_scenes scores against")
    ap.add_argument("--truth-rays", type=int, default=8192)
    ap.add_argument("--point-rays", type=int, default=1024)
    ap.add_argument("--out", type=Path, default=Path("out") / "recon_error")
    args = ap.parse_args(argv)
    r, data = measure(args.scene, args.probes, args.probe_rays, args.truth_rays, args.point_rays)
    print(json.dumps(r, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "recon_error.json").write_text(json.dumps(r, indent=1))
    picture(r, data, args.out / "recon_error.png")
    print(f"wrote {args.out / 'recon_error.json'} and {args.out / 'recon_error.png'}")
    v = Verdicts("recon_error")
    v.check(f"{r['scene']} reference ({r['probe_rays']} rays) off the {r['truth_rays']}-ray truth", r[f"reference_{r['probe_rays']}_vs_truth"], "<", 0.005)
    v.check(f"{r['scene']} recon MAE against the {r['truth_rays']}-ray truth", r["recon_vs_truth"], "<", TARGETS["recon_mae"])
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
