"""Each object of a composed scene at its own scale: per-instance accuracy at default settings against the
scene-wide sampling in the same run.

The scene (default examples/composed.toml: Sponza from ../shared/scenes with two CesiumMen, a fox and a
boulder, no AO distance and no density) is baked at its defaults, where each [[instance]] is sampled at
OBJECT_SAMPLING_FRACTION x its own diagonal (Instance.sampling_scale, sampling.instance_factors), and again
with every instance at the scene's density (sampling_scale 0: the baseline), and for each `--fractions`
value with the objects' scales at that fraction of their diagonals (the calibration of the constant). Per
instance: points, and the recon MAE and holes at --probes probes on that instance alone (the visible ones,
as `psao bake` scores them) against AO traced there with --probe-rays rays. Area-weighted probes of the whole
scene land almost all on the largest object, which hides the small ones; these do not.

Targets at the defaults, per instance: recon_mae < 0.02 and holes < 0.1 % (bench_scenes.TARGETS). Without
../shared/scenes the run prints one SKIPPED line and exits 0.

    python -m benchmarks.bench_objects [--scene examples/composed.toml] [--probes 3000] [--fractions 0.1,0.8]
        [--out out/bench_objects]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from benchmarks.bench_scenes import REPO, SHARED, TARGETS
from benchmarks.verdicts import Verdicts
from psao.server.settings import ProbeSettings

DEFAULT_SCENE = REPO / "examples" / "composed.toml"


def measure(scene, probes: int, probe_rays: int) -> list[dict]:
    """Bake `scene` at its defaults; per instance its points, recon MAE and hole fraction."""
    from psao.server.bake import bake_scene, reconstruction_error, sample_probes
    from psao.server.points.buried import visible_probes

    result = bake_scene(scene, show_progress=False)
    rows = []
    try:
        for k, inst in enumerate(scene.instances):
            alone = sample_probes(dataclasses.replace(scene, instances=[inst]), probes, seed=100 + k)
            alone.instance[:] = k
            alone = visible_probes(scene, alone)
            err = reconstruction_error(result.grid, scene, result.tracer, alone, rays=probe_rays) if len(alone.instance) \
                else {"recon_mae": float("nan"), "hole_fraction": float("nan"), "probes": 0}
            rows.append({"instance": inst.name, "points": len(result.pointsets[k]), "recon_mae": err["recon_mae"],
                         "holes_pct": 100 * err["hole_fraction"], "probes": err["probes"]})
    finally:
        result.tracer.close()
    return rows


def with_fraction(scene, fraction: float | None):
    """The scene with each object's sampling scale at `fraction` of its own diagonal, at most the scene's AO
    distance (None: the scene's for all). An object is an [[instance]]: its parts are named INSTANCE/PART."""
    out = dataclasses.replace(scene, instances=[dataclasses.replace(i) for i in scene.instances])
    objects: dict[str, list] = {}
    for inst in out.instances:
        objects.setdefault(inst.name.split("/")[0], []).append(inst)
    for parts in objects.values():
        scale = 0.0 if fraction is None else min(fraction * out.diagonal(parts), scene.ao_distance)
        for inst in parts:
            inst.sampling_scale = scale
    return out


def chart(runs: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = [r["instance"] for r in next(iter(runs.values()))]
    x = np.arange(len(names))
    width = 0.8 / len(runs)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), dpi=100)
    for j, (label, rows) in enumerate(runs.items()):
        off = (j - (len(runs) - 1) / 2) * width
        axes[0].bar(x + off, [r["recon_mae"] for r in rows], width, label=label)
        axes[1].bar(x + off, [r["points"] for r in rows], width, label=label)
    axes[0].axhline(TARGETS["recon_mae"], color="k", ls="--", lw=0.8)
    axes[0].set_ylabel("recon MAE at the instance's probes")
    axes[1].set_ylabel("points")
    axes[1].set_yscale("log")
    for a in axes:
        a.set_xticks(x, names, rotation=30, ha="right")
    axes[0].legend(fontsize=8)
    fig.suptitle("Each object at its own scale: per-instance accuracy and points")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(DEFAULT_SCENE.relative_to(REPO)), help="a TOML scene without ao_distance")
    ap.add_argument("--probes", type=int, default=3000, help="random surface probes per instance")
    ap.add_argument("--probe-rays", type=int, default=ProbeSettings.rays, help="rays per probe for the truth")
    ap.add_argument("--fractions", default="", help="comma list of object sampling fractions to bake as well")
    ap.add_argument("--out", type=Path, default=Path("out") / "bench_objects")
    args = ap.parse_args(argv)
    try:
        fractions = [float(f) for f in args.fractions.split(",") if f.strip()]
    except ValueError:
        ap.error(f"--fractions: numbers, got {args.fractions!r}")
    if any(not f > 0 for f in fractions) or args.probes < 1:
        ap.error("--fractions must be > 0 and --probes at least 1")
    if not SHARED.is_dir():
        print(f"SKIPPED bench_objects: the shared scenes ({SHARED}) are not there")
        return 0
    from psao.scene import SceneError, load_scene
    from psao.scene.model import OBJECT_SAMPLING_FRACTION

    try:
        scene = load_scene(args.scene)
    except SceneError as exc:
        ap.error(str(exc))
    runs = {f"default ({OBJECT_SAMPLING_FRACTION:g} x diagonal)": measure(scene, args.probes, args.probe_rays),
            "scene-wide (baseline)": measure(with_fraction(scene, None), args.probes, args.probe_rays)}
    for f in fractions:
        runs[f"{f:g} x diagonal"] = measure(with_fraction(scene, f), args.probes, args.probe_rays)
    print(f"{scene.name}: AO distance {scene.ao_distance:.4g}; {args.probes} probes per instance x {args.probe_rays} rays")
    print(f"{'sampling':>28s} " + " ".join(f"{r['instance']:>22s}" for r in next(iter(runs.values()))))
    for label, rows in runs.items():
        print(f"{label:>28s} " + " ".join(f"{r['points']:>8,d} {r['recon_mae']:.4f} {r['holes_pct']:5.2f}%"
                                          for r in rows) + f"   total {sum(r['points'] for r in rows):,}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_objects.json").write_text(json.dumps({"scene": args.scene, "runs": runs}, indent=1))
    chart(runs, args.out / "bench_objects.png")
    v = Verdicts("bench_objects")
    default, base = list(runs.values())[:2]
    for r, b in zip(default, base):
        v.check(f"{r['instance']} recon_mae at defaults (scene-wide sampling: {b['recon_mae']:.4f})", r["recon_mae"], "<",
                TARGETS["recon_mae"])
        v.check(f"{r['instance']} holes_pct at defaults", r["holes_pct"], "<", TARGETS["holes_pct"])
    print(f"wrote {args.out / 'bench_objects.json'} and {args.out / 'bench_objects.png'}")
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
