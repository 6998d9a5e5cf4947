"""`psao bake SCENE`: generate points, build the grid, trace AO, write the grid, report accuracy."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from psao.options import default
from psao.server.points import sampling
from psao.server.cli.cluster import add_cluster_arguments, cluster_settings
from psao.server.outputs import check_output_path, write_atomically
from psao.server.settings import BakeSettings, DensifySettings, GapFillSettings, ProbeSettings
from psao.server.tracer import BACKENDS


def add_bake_arguments(p: argparse.ArgumentParser, density: bool = True) -> None:
    """The bake's options, shared by every sub-command that bakes (bake, serve, bench: it has its own
    --densities, so density=False leaves --density out)."""
    if density:
        sampling.add_arguments(p)  # --density, --points, --max-points
    p.add_argument("--rays", type=int, default=default(BakeSettings, "rays"), help="AO rays per point in the bake")
    p.add_argument("--seed", type=int, default=default(BakeSettings, "seed"), help="seed of the points and rays")
    p.add_argument("--spawn-ratio", type=float, default=default(BakeSettings, "spawn_ratio"),
                   help="points spawned per point kept before elimination (2 as the paper; 4 leaves fewer holes)")
    p.add_argument("--gap-fill", type=int, default=default(BakeSettings, "gap_fill.passes"), metavar="PASSES",
                   help="rounds of adding points where the client's lookup finds none (0: off)")
    p.add_argument("--gap-fill-ratio", type=float, default=default(BakeSettings, "gap_fill.ratio"), metavar="R",
                   help="random candidates per kept point and round for --gap-fill")
    p.add_argument("--gap-fill-first-step", action="store_true",
                   help="--gap-fill adds points also where the lookup's first step (radius r, normals within "
                        "FIRST_T_N) finds none, not only where the whole lookup does (small faces at creases)")
    p.add_argument("--densify", type=int, default=default(BakeSettings, "densify.rounds"), metavar="ROUNDS",
                   help="rounds of adding points where the lookup misses the traced AO of candidate points "
                        f"(AO varying fast: mouldings, creases; 0: off; needs --rays >= {DensifySettings.min_rays})")
    add_tracer_arguments(p)
    add_cluster_arguments(p)  # --cluster: the bake's trace on a Dask cluster


def add_tracer_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tracer", choices=BACKENDS, default=default(BakeSettings, "tracer"), help="tracer back-end")
    p.add_argument("--workers", type=int, default=default(BakeSettings, "workers"),
                   help="tracer worker processes (0: all cores)")


def bake_settings(args: argparse.Namespace) -> BakeSettings:
    """BakeSettings from the options of add_bake_arguments, checked (BakeSettings.check: ConfigError)."""
    points = sampling.bake_kwargs(args) if hasattr(args, "points") else {}
    settings = BakeSettings(**points, rays=args.rays, seed=args.seed, tracer=args.tracer, workers=args.workers,
                            spawn_ratio=args.spawn_ratio, cluster=cluster_settings(args),
                            gap_fill=GapFillSettings(passes=args.gap_fill, ratio=args.gap_fill_ratio,
                                                     first_step=args.gap_fill_first_step),
                            densify=DensifySettings(rounds=args.densify))
    settings.check()  # a bad number fails before the scene loads
    return settings


def bake_arguments(settings: BakeSettings) -> list[str]:
    """The options of add_bake_arguments that give `settings` (for a `psao bake` or `psao serve` process)."""
    points = (["--density", f"{settings.density:g}"] if settings.density is not None else
              ["--points", f"{settings.points:g}"] if settings.points is not None else [])
    detail = ["--detail-factor", str(settings.detail_factor)] if settings.detail_factor is not None else []
    return [*points, "--max-points", f"{settings.max_points:g}", *detail, "--rays", str(settings.rays), "--seed", str(settings.seed),
            "--spawn-ratio", f"{settings.spawn_ratio:g}", "--gap-fill", str(settings.gap_fill.passes),
            "--gap-fill-ratio", f"{settings.gap_fill.ratio:g}", "--tracer", settings.tracer,
            "--workers", str(settings.workers), "--densify", str(settings.densify.rounds),
            *(["--gap-fill-first-step"] if settings.gap_fill.first_step else [])]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="builtin:NAME, a scene .toml, or a mesh file (glTF, GLB, OBJ, ...)")
    add_bake_arguments(p)
    p.add_argument("--ao-distance", type=float, default=None, help="override the scene's AO distance (world units)")
    p.add_argument("--out", type=Path, default=None, help="grid file to write (.npz); default out/<scene>-N<density>.npz")
    p.add_argument("--probes", type=int, default=default(ProbeSettings, "probes"),
                   help="random surface probes for recon_mae; the visible ones are scored, those buried in closed geometry "
                        "left out (0 = skip)")
    p.add_argument("--probe-rays", type=int, default=default(ProbeSettings, "rays"), help="rays per probe for the ground truth")
    p.add_argument("--json", action="store_true", help="print one JSON object with the statistics as the last line")


def probe_settings(args: argparse.Namespace) -> ProbeSettings:
    """ProbeSettings from --probes and --probe-rays, checked (ProbeSettings.check: ConfigError)."""
    settings = ProbeSettings(probes=args.probes, rays=args.probe_rays)
    settings.check()
    return settings


def run(args: argparse.Namespace) -> int:
    from psao.scene import load_scene
    from psao.server.bake import bake_scene, reconstruction_error, sample_probes
    from psao.server.points.buried import visible_probes

    probe = probe_settings(args)
    settings = bake_settings(args)
    out = check_output_path(args.out, ".npz") if args.out is not None else None  # before the work, not after
    scene = load_scene(args.scene, ao_distance=args.ao_distance)
    result = bake_scene(scene, settings)
    stats = dict(result.stats)
    try:
        tracer = result.tracer
        if probe.probes:
            # scored where a view can see: probes buried in closed geometry (no points there by design) are left out
            probes = visible_probes(scene, sample_probes(scene, probe.probes))
            stats["probes_buried"] = probe.probes - len(probes.instance)
            if len(probes.instance):
                stats.update(reconstruction_error(result.grid, scene, tracer, probes, rays=probe.rays))
    finally:
        result.tracer.close()
    out = out or check_output_path(Path("out") / f"{scene.name}-N{stats['density']:.4g}.npz", ".npz")
    meta = {"scene": args.scene, **{k: v for k, v in stats.items() if isinstance(v, (int, float, str))}}
    write_atomically(out, lambda f: result.grid.save(f, scene_hash=scene.content_hash(), meta=meta))
    stats["out"] = str(out)
    _print_summary(stats)
    if args.json:
        print(json.dumps(stats))
    return 0


def _print_summary(stats: dict) -> None:
    lines = [
        f"scene {stats['scene']}: {stats['points_kept']:,} points kept of {stats['points_spawned']:,} spawned, "
        f"{stats['points_dropped_overflow']:,} dropped by overflow; {stats['cells']:,} cells, {stats['buckets']:,} buckets",
        f"points {stats['seconds_points']:.2f} s, grid {stats['seconds_grid']:.2f} s, trace {stats['seconds_trace']:.2f} s "
        f"({stats['rays_per_second'] / 1e6:.2f} Mrays/s per busy worker set, bare Embree "
        f"{stats.get('embree_rays_per_second', 0) / 1e6:.2f} Mrays/s on the same rays; wall {stats['rays_per_second_wall'] / 1e6:.2f} Mrays/s)",
    ]
    if "cluster" in stats:
        lines.append(f"cluster {stats['cluster']}: {stats['cluster_tasks']:,} tasks on {stats['cluster_threads']} worker "
                     f"threads, {stats['cluster_workers_lost']} workers lost, peak worker memory "
                     f"{stats['cluster_peak_rss_bytes'] / 2**20:,.0f} MiB")
    if "recon_mae" in stats:
        lines.append(f"reconstruction vs {stats['probe_rays']}-ray truth at {stats['probes']:,} visible probes "
                     f"({stats['probes_buried']:,} buried left out): "
                     f"MAE {stats['recon_mae']:.4f}, p99 {stats['recon_p99']:.3f}, holes {100 * stats['hole_fraction']:.3f}%")
    lines.append(f"grid written to {stats['out']}")
    print("\n".join(lines), file=sys.stderr)
