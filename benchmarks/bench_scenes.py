"""Every model at its default settings, and at 4x the default density: one table, one chart.

For each scene (every mesh file under ../shared/scenes, the composed scene examples/composed.toml that
places some of them, and every built-in scene) and each density scale, a child process bakes at the
scene's default (scale-aware) density times the scale, each instance's own factor kept (a TOML scene
without an AO distance samples each [[instance]] at its own size: sampling.instance_factors), with the
default density's detail levels (src/psao/server/points/sampling.py: small triangles up to DETAIL_FACTOR times denser) and
the bake's default rays per point unless --rays, and reports: points, bake seconds, points dropped to grid
overflow, reconstruction MAE and hole fraction at random surface probes against AO traced there directly, PSNR of
PSAO, SSAO and GTAO against an RTAO reference on the same frames, and the child's peak resident memory.
Probes on surfaces buried inside closed geometry (src/psao/server/points/buried.py, every one-sided instance as
posed at time 0) are seen from nowhere and left out of MAE and holes; their share is the "buried"
column. The probes' AO is traced with `psao bake`'s check's rays (ProbeSettings.rays, 1024), fine enough to
judge an MAE of 0.02; reference spp, frame size and frame count are kept modest for a shared 2-core
machine and printed with the table.

Targets per scene and scale: recon_mae < 0.02, holes < 0.1 %, dropped < 0.5 %, PSNR PSAO > SSAO and
> GTAO.

    python -m benchmarks.bench_scenes [--scales 1,4] [--scenes builtin:cornell,...] [--out out/bench_scenes]
        [--maps [--maps-view EX,EY,EZ:TX,TY,TZ --maps-size 960x540]]
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.verdicts import Verdicts
from psao.server.settings import DensifySettings, ProbeSettings

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "scenes"
# Sponza with characters and a rolling boulder from SHARED, at default settings
COMPOSED = REPO / "examples" / "composed.toml"
BUILTINS = ("builtin:cornell", "builtin:courtyard", "builtin:space", "builtin:robots", "builtin:tangle")
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off")
TARGETS = {"recon_mae": 0.02, "holes_pct": 0.1, "dropped_pct": 0.5}


def scene_specs() -> list[str]:
    files = sorted(p for p in SHARED.glob("*/*") if p.suffix.lower() in MESH_SUFFIXES) if SHARED.is_dir() else []
    composed = [str(COMPOSED.relative_to(REPO))] if SHARED.is_dir() else []
    return [str(p) for p in files] + composed + list(BUILTINS)


def measure_one(spec: str, scale: float, cfg: dict) -> dict:
    """Runs in the child: bake, accuracy at probes, frames against the reference."""
    from psao.eval.quality import QualityRenderer, frame_poses, mean_scores, reference_images, score_frames
    from psao.eval.reference import ReferenceSettings
    from psao.scene import load_scene
    from psao.server.bake import bake_scene, reconstruction_error, sample_probes
    from psao.server.points.buried import visible_probes
    from psao.server.settings import BakeSettings, DensifySettings, GapFillSettings
    from psao.server.points.sampling import DETAIL_FACTOR, default_density, estimate_points, instance_factors

    scene = load_scene(spec)
    density = default_density(scene) * scale
    factors = instance_factors(scene)
    # the same density on every instance where no instance has a factor; else the default's points times the
    # scale as a budget, which keeps the factors
    sampling = {"density": density} if (factors == 1).all() else {"points": estimate_points(
        scene, density, BakeSettings.min_points, DETAIL_FACTOR, factors=factors)}
    t0 = time.perf_counter()
    rays = {} if cfg["rays"] is None else {"rays": cfg["rays"]}
    fill = GapFillSettings(passes=cfg.get("gap_fill", 0), first_step=cfg.get("gap_fill_first_step", False))
    res = bake_scene(scene, BakeSettings(**sampling, detail_factor=DETAIL_FACTOR, gap_fill=fill,
                                         densify=DensifySettings(rounds=cfg.get("densify", 0)), **rays), show_progress=False)
    density = res.stats["density"]
    seconds = time.perf_counter() - t0
    probes = visible_probes(scene, sample_probes(scene, cfg["probes"]))
    try:
        err = reconstruction_error(res.grid, scene, res.tracer, probes, rays=cfg["probe_rays"])
    finally:
        res.tracer.close()
    methods = ("psao", "ssao", "gtao")
    size = tuple(cfg["size"])
    poses = frame_poses(scene, cfg["frames"], size)
    with QualityRenderer(scene, size, methods=methods) as qr:
        frames = qr.render(res.grid, poses, timing_repeats=1)
    refs = reference_images(scene, frames, ReferenceSettings(spp=cfg["spp"]), show_progress=False)
    rows = score_frames(frames, refs, methods)
    if cfg.get("maps"):
        frame, ref = frames[0], refs[0]
        if cfg.get("maps_view"):  # the error map from a camera of its own instead of the first scored frame
            frame, ref = view_frame(scene, res.grid, cfg["maps_view"], tuple(cfg["maps_size"]), cfg["spp"])
        save_maps(res.grid, frame, ref, Path(cfg["maps"]) / f"maps_{scene.name}_x{scale:g}.png")
    s = res.stats
    return {
        "scene": scene.name, "spec": spec, "scale": scale, "density": density, "points": s["points_kept"],
        "seconds": seconds, "dropped_pct": 100 * s["points_dropped_overflow"] / max(s["points_generated"], 1),
        "recon_mae": err["recon_mae"], "holes_pct": 100 * err["hole_fraction"], "buried_pct": 100 * (1 - err["probes"] / cfg["probes"]),
        **{f"psnr_{m}": mean_scores(rows, m).psnr for m in methods},
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def parse_view(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """'EX,EY,EZ:TX,TY,TZ' -> (eye, target) in world units."""
    parts = [tuple(float(v) for v in part.split(",")) for part in text.split(":")]  # ValueError on a non-number
    if len(parts) != 2 or any(len(p) != 3 for p in parts) or parts[0] == parts[1]:
        raise ValueError(f"wants two different 3D points EX,EY,EZ:TX,TY,TZ, got {text!r}")
    return parts[0], parts[1]


def view_frame(scene, grid, view: str, size: tuple[int, int], spp: int):
    """PSAO's frame and the RTAO reference from one camera (--maps-view), at `size`."""
    import numpy as np

    from psao.client.render.views import near_far
    from psao.eval.quality import FramePose, QualityRenderer, reference_images
    from psao.eval.reference import ReferenceSettings
    from psao.scene.camera import ORBIT_FOV_Y, look_at, perspective

    eye, target = (np.array(v, np.float64) for v in parse_view(view))
    near, far = near_far(scene, eye)
    pose = FramePose(0, 0.0, look_at(eye, target), perspective(ORBIT_FOV_Y, size[0] / size[1], near, far))
    with QualityRenderer(scene, size, methods=("psao",)) as qr:
        frame = qr.render(grid, [pose], timing_repeats=1)[0]
    return frame, reference_images(scene, [frame], ReferenceSettings(spp=spp), show_progress=False)[0]


def save_maps(grid, frame, ref, path: Path) -> None:
    """One frame as three panels: PSAO's AO with its holes (no point has weight, eq. 4 falls back to 1) in
    red, |PSAO - RTAO| (0..0.25), and the RTAO reference. The weights are the oracle's on the frame's own
    G-buffer, which the shader equals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from psao.protocol.reconstruct import reconstruct_ao

    gb = frame.gbuffer
    m = gb.mask & (gb.instance >= 0)
    back = None if gb.back_side is None else gb.back_side[m]
    _, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, gb.instance[m], gb.local[m], gb.local_normal[m],
                             back=back)
    holes = np.zeros(m.shape, bool)
    holes[m] = wsum == 0
    rgb = np.repeat(frame.ao["psao"][..., None], 3, axis=2)
    rgb[holes] = (1.0, 0.0, 0.0)
    err = np.where(m, np.abs(frame.ao["psao"] - ref), 0.0)
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.2), dpi=100)
    axes[0].imshow(np.clip(rgb, 0, 1))
    axes[0].set_title(f"PSAO, holes in red ({holes.sum()} px, {holes.sum() / max(m.sum(), 1):.3%})")
    im = axes[1].imshow(err, cmap="magma", vmin=0, vmax=0.25)
    axes[1].set_title(f"|PSAO - RTAO|, mean {err[m].mean():.4f}")
    fig.colorbar(im, ax=axes[1], fraction=0.03)
    axes[2].imshow(ref, cmap="gray", vmin=0, vmax=1)
    axes[2].set_title("RTAO reference")
    for a in axes:
        a.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def run_child(spec: str, scale: float, cfg: dict) -> dict:
    cmd = [sys.executable, "-m", "benchmarks.bench_scenes", "--child", json.dumps({"spec": spec, "scale": scale, **cfg})]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    last = proc.stdout.strip().splitlines()[-1:] or [""]
    if proc.returncode != 0 or not last[0].startswith("{"):
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return {"spec": spec, "scene": Path(spec).stem if "/" in spec else spec, "scale": scale, "error": tail}
    return json.loads(last[0])


# (heading, row key, format): the console line and the markdown table (benchmarks.report) show these
COLUMNS = (("N / unit^2", "density", ".4g"), ("points", "points", ",d"), ("bake s", "seconds", ".1f"),
           ("dropped %", "dropped_pct", ".3f"), ("buried %", "buried_pct", ".1f"), ("recon MAE", "recon_mae", ".4f"),
           ("holes %", "holes_pct", ".3f"), ("PSNR PSAO", "psnr_psao", ".2f"), ("SSAO", "psnr_ssao", ".2f"),
           ("GTAO", "psnr_gtao", ".2f"), ("peak MB", "peak_mb", ".0f"))
HEADER_COLUMNS = ("scene", *(c[0] for c in COLUMNS))


def table_cells(r: dict) -> list[str]:
    """One row's cells, formatted (a model that failed: its error in the first column after the name)."""
    if "error" in r:
        return [r["scene"], f"error: {r['error']}", *[""] * (len(COLUMNS) - 1)]
    return [r["scene"], *(format(r.get(key, float("nan")), fmt) for _, key, fmt in COLUMNS)]


def format_row(r: dict) -> str:
    cells = table_cells(r)
    return f"{cells[0]:>18s} x{r['scale']:<3g} " + " ".join(f"{c:>10s}" for c in cells[1:])


HEADER = f"{'scene':>18s} {'':4s} " + " ".join(f"{c[0]:>10s}" for c in COLUMNS)


def chart(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ok = [r for r in rows if "error" not in r and r["scale"] == 1]
    if not ok:
        return
    x = np.arange(len(ok))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), dpi=100)
    for k, (m, label) in enumerate((("psao", "PSAO"), ("ssao", "SSAO"), ("gtao", "GTAO"))):
        axes[0].bar(x + (k - 1) * 0.27, [r[f"psnr_{m}"] for r in ok], 0.27, label=label)
    axes[0].set_xticks(x, [r["scene"] for r in ok], rotation=45, ha="right")
    axes[0].set_ylabel("PSNR vs RTAO (dB)")
    axes[0].legend()
    axes[1].bar(x - 0.2, [r["holes_pct"] for r in ok], 0.4, label="holes %")
    axes[1].bar(x + 0.2, [r["dropped_pct"] for r in ok], 0.4, label="dropped %")
    axes[1].axhline(TARGETS["holes_pct"], color="C0", ls="--", lw=0.8)
    axes[1].axhline(TARGETS["dropped_pct"], color="C1", ls="--", lw=0.8)
    axes[1].set_xticks(x, [r["scene"] for r in ok], rotation=45, ha="right")
    axes[1].set_yscale("symlog", linthresh=0.1)
    axes[1].legend()
    fig.suptitle("Every model at its default density (scale-aware)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=None, help="comma list (default: every shared mesh and built-in scene)")
    ap.add_argument("--scales", default="1,4", help="density multiples of each scene's default")
    ap.add_argument("--rays", type=int, default=None, help="bake rays per point (default: the bake's)")
    ap.add_argument("--probes", type=int, default=20000)
    ap.add_argument("--probe-rays", type=int, default=ProbeSettings.rays,
                    help="rays per probe for the AO the reconstruction is scored against (default: psao bake's check). "
                         "Stratified like the points' rays: on Sponza's probes 256 rays are 0.0039 off an 8192-ray "
                         "trace on average and add 0.001 to the MAE, 1024 rays 0.0014 and 0.0002")
    ap.add_argument("--spp", type=int, default=64, help="RTAO reference samples per pixel")
    ap.add_argument("--size", default="320x180")
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out") / "bench_scenes")
    ap.add_argument("--gap-fill", type=int, default=0, metavar="PASSES", help="bake with gap fill rounds (default off)")
    ap.add_argument("--gap-fill-first-step", action="store_true", help="gap fill where the lookup's first step finds nothing")
    ap.add_argument("--densify", type=int, default=DensifySettings.rounds, metavar="ROUNDS",
                    help="bake with densify rounds (default: the bake's, off)")
    ap.add_argument("--maps", action="store_true", help="also save maps_SCENE_xSCALE.png per scene (holes, error map)")
    ap.add_argument("--maps-view", default=None, metavar="EX,EY,EZ:TX,TY,TZ",
                    help="--maps from this camera (eye and target, world units) instead of the first scored frame")
    ap.add_argument("--maps-size", default="960x540", help="--maps-view frame size")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        cfg = json.loads(args.child)
        print(json.dumps(measure_one(cfg.pop("spec"), cfg.pop("scale"), cfg)))
        return 0
    w, h = (int(v) for v in args.size.split("x"))
    cfg = {"rays": args.rays, "probes": args.probes, "probe_rays": args.probe_rays, "spp": args.spp,
           "size": [w, h], "frames": args.frames, "maps": str(args.out) if args.maps else None,
           "gap_fill": args.gap_fill, "gap_fill_first_step": args.gap_fill_first_step, "densify": args.densify}
    if args.maps_view is not None:
        try:  # one line and exit 2 before any bake
            parse_view(args.maps_view)
            mw, mh = (int(v) for v in args.maps_size.split("x"))
        except ValueError as exc:
            ap.error(f"--maps-view / --maps-size: {exc}")
        cfg.update(maps_view=args.maps_view, maps_size=[mw, mh])
    print(f"bake {args.rays or 'default'} rays/point, densify {args.densify} rounds; {args.probes} probes x {args.probe_rays} rays; RTAO {args.spp} spp, "
          f"{args.frames} frames at {w}x{h} along each scene's camera path (default orbit where it has none)")
    print(HEADER, flush=True)
    specs = args.scenes.split(",") if args.scenes else scene_specs()
    rows = []
    for scale in (float(s) for s in args.scales.split(",")):
        for spec in specs:
            rows.append(run_child(spec, scale, cfg))
            print(format_row(rows[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_scenes.json").write_text(json.dumps(rows, indent=1))
    chart(rows, args.out / "bench_scenes.png")
    from psao.eval.metrics import PSNR_CAP

    v = Verdicts("bench_scenes")
    for r in rows:
        name = f"{r['scene']} x{r['scale']:g}"
        if "error" in r:
            v.check(f"{name} baked", 0.0, ">", 0.0)
            continue
        for key, target in TARGETS.items():
            v.check(f"{name} {key}", r[key], "<", target)
        for other in ("ssao", "gtao"):
            gain = r["psnr_psao"] - r[f"psnr_{other}"]
            if r["psnr_psao"] >= PSNR_CAP:  # PSAO equals the reference (a frame with no occlusion): a tie is no loss
                v.check(f"{name} PSNR PSAO (exact) - {other.upper()} dB", gain, ">=", 0.0)
            else:
                v.check(f"{name} PSNR PSAO - {other.upper()} dB", gain, ">", 0.0)
    print(f"wrote {args.out / 'bench_scenes.json'} and {args.out / 'bench_scenes.png'}")
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
