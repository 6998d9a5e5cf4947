"""Densify's worth and cost on one scene: the same bake without and with it, then accuracy and AO pass.

Both bakes use the scene's default density, rays and seed; one has densify off (the default), the
other `--densify-rounds` rounds of it (5, as `psao bake --densify 5`; src/psao/server/points/densify.py). Reported: points, bake seconds, recon MAE and holes at the
visible probes against AO traced there directly (as benchmarks/bench_scenes.py scores them), and the
client's AO pass on both grids: the same renderer draws the same frames of the scene's camera path with
PSAO and SSAO, in interleaved rounds (plain, densified, then densified, plain, ...); a grid's figure is
the geometric mean over frames of PSAO's time over SSAO's next to it (each the G-buffer pass plus the
method's passes, minimum over repeats), and the growth is the median over rounds of the densified
grid's figure over the plain grid's. Run it alone under the benchmark lock: the pass times are speed.

Targets: MAE lower with densify, nothing dropped by it, AO pass growth at most MAX_GROWTH (+15%).

    python -m benchmarks.bench_densify [--scene ../shared/scenes/sponza/sponza_s_lod4.glb] [--rounds 4]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.verdicts import Verdicts

MAX_GROWTH = 1.15
DEFAULT_SCENE = "../shared/scenes/sponza/sponza_s_lod4.glb"


def bake(scene, rounds: int):
    from psao.server.bake import bake_scene
    from psao.server.points.sampling import default_density
    from psao.server.settings import BakeSettings, DensifySettings

    t0 = time.perf_counter()
    res = bake_scene(scene, BakeSettings(density=default_density(scene), densify=DensifySettings(rounds=rounds)),
                     show_progress=False)
    return res, time.perf_counter() - t0


def pass_ratio(frames) -> float:
    """Geometric mean over frames of PSAO's time over SSAO's."""
    return float(np.exp(np.mean([np.log(f.gpu_ms["psao"] / f.gpu_ms["ssao"]) for f in frames])))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=DEFAULT_SCENE)
    ap.add_argument("--probes", type=int, default=20000)
    ap.add_argument("--probe-rays", type=int, default=256)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5, help="timed submissions per frame (minimum kept)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--densify-rounds", type=int, default=5, help="densify's rounds in the densified bake")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))

    from psao.eval.quality import QualityRenderer, frame_poses
    from psao.scene import load_scene
    from psao.server.bake import reconstruction_error, sample_probes
    from psao.server.points.buried import visible_probes

    scene = load_scene(args.scene)
    probes = visible_probes(scene, sample_probes(scene, args.probes))
    rows = {}
    for name, rounds in (("plain", 0), ("densified", args.densify_rounds)):
        res, seconds = bake(scene, rounds)
        try:
            err = reconstruction_error(res.grid, scene, res.tracer, probes, rays=args.probe_rays)
        finally:
            res.tracer.close()
        rows[name] = dict(grid=res.grid, points=res.stats["points_kept"], seconds=seconds, mae=err["recon_mae"],
                          holes=100 * err["hole_fraction"], added=res.stats.get("points_densify", 0),
                          dropped=res.stats["points_dropped_overflow"])
        r = rows[name]
        print(f"{name:>10s}: {r['points']:,} points ({r['added']:,} added), bake {seconds:.1f} s, "
              f"MAE {r['mae']:.4f}, holes {r['holes']:.3f}%, dropped {r['dropped']}", flush=True)

    poses = frame_poses(scene, args.frames, (w, h))
    growth = []
    with QualityRenderer(scene, (w, h), methods=("psao", "ssao")) as qr:
        for k in range(args.rounds):
            names = ("plain", "densified") if k % 2 == 0 else ("densified", "plain")
            fig = {n: pass_ratio(qr.render(rows[n]["grid"], poses, timing_repeats=args.repeats)) for n in names}
            growth.append(fig["densified"] / fig["plain"])
            print(f"round {k}: PSAO/SSAO plain {fig['plain']:.3f}, densified {fig['densified']:.3f}, "
                  f"growth x{growth[-1]:.3f}", flush=True)

    v = Verdicts("bench_densify")
    v.check(f"{scene.name} recon MAE densified - plain", rows["densified"]["mae"] - rows["plain"]["mae"], "<", 0.0)
    v.check(f"{scene.name} points dropped with densify", float(rows["densified"]["dropped"] - rows["plain"]["dropped"]),
            "<=", 0.0)
    v.check(f"{scene.name} AO pass growth (median of {args.rounds} rounds)", float(np.median(growth)), "<=", MAX_GROWTH)
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
