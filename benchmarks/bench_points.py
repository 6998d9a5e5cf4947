"""Point generation against point-cloud-utils' Poisson disk sampler, one run.

Part 1, scene: points for every instance of the scene (generate_points per instance, seeds mixed with
the instance index) at the density that gives --points final points in total. Target: 1,000,000 points
on builtin:courtyard in under 30 s.

Part 2, merged mesh: all instances merged into one world-space mesh. `pcu.sample_mesh_poisson_disk` is
asked for --pcu-samples (it returns about that many, sometimes more); ours is then run as one instance at
the density that gives exactly the count pcu returned. Target: ours >= 10x faster, with a minimum point
spacing at least as large.

Spacing figures per method: minimum and mean nearest-neighbour (NN) distance, both in world units and
divided by the Poisson radius r = sqrt(A / (2 sqrt(3) P)), and the coefficient of variation (std / mean) of
the NN distance. "All" pairs is plain 3D Euclidean NN; "same side" only counts neighbours whose normals
make a cosine > -0.5, so points on the two faces of a thin wall do not count as close (what AO needs:
each face keeps its own points).

Warp initialisation and kernel loading happen once per process, in a warm-up on a tiny mesh, and are
reported on their own line.

--sweep 3,5 adds rows for other spawn ratios; --feasibility prints how far apart points kept from a
random pool of that ratio can be at all (greedy independent-set bound), which is what limits the minimum
spacing of any elimination from 2N spawned points.

    .venv/bin/python -m benchmarks.bench_points [SCENE] [--points 1000000] [--pcu-samples 200000] [--out DIR]
        [--sweep 3,5] [--feasibility] [--skip-scene]
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.verdicts import Verdicts

SCENE_TARGET_S = 30.0
SPEEDUP_TARGET = 10.0
SAME_SIDE_COS = -0.5


@dataclass
class Spacing:
    points: int
    radius: float  # Poisson radius of the set, world units
    min_all: float
    min_same_side: float
    mean: float
    cv: float  # of the NN distance, all pairs
    cv_same_side: float


def nn_distances(positions: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: distance to the nearest other point, and to the nearest one on the same side
    (among the 8 nearest; inf when all 8 face the other way)."""
    d, idx = cKDTree(positions).query(positions, k=9)
    same = (normals[idx[:, 1:]] * normals[:, None, :]).sum(axis=2) > SAME_SIDE_COS
    return d[:, 1], np.where(same, d[:, 1:], np.inf).min(axis=1)


def spacing(positions: np.ndarray, normals: np.ndarray, area: float) -> Spacing:
    """NN statistics of a point set on a surface of world `area`."""
    nn, nn_same = nn_distances(positions, normals)
    nn_same = nn_same[np.isfinite(nn_same)]
    return Spacing(
        points=len(positions),
        radius=float(np.sqrt(area / (2 * np.sqrt(3) * len(positions)))),
        min_all=float(nn.min()),
        min_same_side=float(nn_same.min()),
        mean=float(nn.mean()),
        cv=float(nn.std() / nn.mean()),
        cv_same_side=float(nn_same.std() / nn_same.mean()),
    )


def greedy_spacing_bound(spawn_ratio: float, keep: int = 5000, seed: int = 0) -> float:
    """How far apart `keep` points chosen among spawn_ratio * keep uniform random ones can be, in units of
    the Poisson radius: the largest spacing d at which a min-degree greedy independent set of the
    "closer than d" graph (2D unit torus) still holds `keep` points. Greedy is near the optimum on such
    graphs, so this shows what any elimination from that pool can reach (pure-Python loop: a few seconds)."""
    import heapq

    rng = np.random.default_rng(seed)
    n = int(round(spawn_ratio * keep))
    p = rng.random((n, 2))
    tree = cKDTree(p, boxsize=1.0)
    r = np.sqrt(1.0 / (2 * np.sqrt(3) * keep))

    def independent(d: float) -> int:
        nbrs = tree.query_ball_point(p, d)
        deg = np.array([len(x) - 1 for x in nbrs])
        alive = np.ones(n, dtype=bool)
        heap = [(deg[i], i) for i in range(n)]
        heapq.heapify(heap)
        chosen = 0
        while heap:
            d_i, i = heapq.heappop(heap)
            if not alive[i] or d_i != deg[i]:
                continue
            chosen += 1
            alive[nbrs[i]] = False
            for j in nbrs[i]:
                for k in nbrs[j]:
                    if alive[k]:
                        deg[k] -= 1
                        heapq.heappush(heap, (deg[k], k))
        return chosen

    lo, hi = 0.5, 2.0
    for _ in range(10):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if independent(mid * r) >= keep else (lo, mid)
    return lo


def world_area(scene) -> float:
    total = 0.0
    for inst in scene.instances:
        mesh = scene.meshes[inst.mesh]
        a = mesh.area(inst.transform[:3, :3])
        total += a * (2 if mesh.double_sided else 1)
    return float(total)


def merged_mesh(scene) -> tuple[np.ndarray, np.ndarray]:
    """All instances as one world-space (v, f); double-sided meshes appear once (pcu has no sides)."""
    vs, fs, base = [], [], 0
    for inst in scene.instances:
        mesh = scene.meshes[inst.mesh]
        vs.append(mesh.vertices @ inst.transform[:3, :3].T + inst.transform[:3, 3])
        fs.append(mesh.faces + base)
        base += len(mesh.vertices)
    return np.concatenate(vs), np.concatenate(fs)


def warm_up() -> float:
    """Warp init and kernel load on a tiny mesh; returns seconds."""
    from psao.scene.model import Mesh
    from psao.server.points.generate import generate_points
    from psao.server.settings import PointSettings

    quad = Mesh("warm", np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    start = time.perf_counter()
    generate_points(quad, np.eye(4), PointSettings(density=100))
    return time.perf_counter() - start


def run_scene(scene, settings, points: int) -> dict:
    """Part 1: every instance at the density giving `points` in total."""
    from rich.progress import Progress

    from psao.server.points.generate import generate_points, instance_seed

    density = points / world_area(scene)
    settings = replace(settings, density=density)
    sets = []
    start = time.perf_counter()
    with Progress(transient=True) as progress:
        task = progress.add_task("points per instance", total=len(scene.instances))
        for k, inst in enumerate(scene.instances):
            mesh = scene.meshes[inst.mesh]
            sets.append(generate_points(mesh, inst.transform, settings, seed=instance_seed(settings.seed, k)))
            progress.advance(task)
    seconds = time.perf_counter() - start
    return {
        "density": density,
        "instances": len(sets),
        "points": int(sum(len(s) for s in sets)),
        "spawned": int(sum(s.spawned for s in sets)),
        "seconds": seconds,
        "sets": sets,
    }


def face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def run_pcu(v: np.ndarray, f: np.ndarray, samples: int, seed: int) -> tuple[float, np.ndarray, np.ndarray]:
    import point_cloud_utils as pcu

    start = time.perf_counter()
    fi, bc = pcu.sample_mesh_poisson_disk(v, f, samples, random_seed=seed + 1)  # pcu: seed 0 means "time"
    seconds = time.perf_counter() - start
    positions = pcu.interpolate_barycentric_coords(f, fi, bc, v)
    return seconds, positions, face_normals(v, f)[fi]


def run_ours_merged(v: np.ndarray, f: np.ndarray, count: int, settings) -> tuple[float, object]:
    from psao.scene.model import Mesh
    from psao.scene.model import triangle_areas
    from psao.server.points.generate import generate_points

    merged = Mesh("merged", v, f)
    area = float(triangle_areas(v, f).sum())
    s = replace(settings, density=count / area, min_points=1)
    start = time.perf_counter()
    ps = generate_points(merged, np.eye(4), s)
    return time.perf_counter() - start, ps


def print_table(rows: list[tuple[str, float, Spacing]]) -> None:
    print(f"{'method':34s} {'seconds':>8s} {'points':>9s} {'min NN':>9s} {'min/r':>6s} {'min same':>9s} "
          f"{'same/r':>6s} {'mean NN':>9s} {'mean/r':>6s} {'CV NN':>6s} {'CV same':>7s}")
    for name, sec, s in rows:
        print(f"{name:34s} {sec:8.2f} {s.points:9d} {s.min_all:9.5f} {s.min_all / s.radius:6.3f} "
              f"{s.min_same_side:9.5f} {s.min_same_side / s.radius:6.3f} {s.mean:9.5f} {s.mean / s.radius:6.3f} "
              f"{s.cv:6.3f} {s.cv_same_side:7.3f}")


def write_charts(out: Path, merged: dict, scene_name: str) -> Path:
    """Times (log scale), NN distance histograms over r, and a top view of one patch for both methods."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(20, 5))
    names = list(merged)
    secs = [merged[n]["seconds"] for n in names]
    ax[0].bar(names, secs, color=["tab:green", "tab:gray"])
    ax[0].set_yscale("log")
    ax[0].set_ylabel("seconds (log)")
    ax[0].set_title(f"{scene_name}, merged mesh, {merged[names[0]]['spacing'].points} points")
    for n, color in zip(names, ["tab:green", "tab:gray"]):
        s = merged[n]["spacing"]
        nn, nn_same = nn_distances(merged[n]["positions"], merged[n]["normals"])
        ax[1].hist(nn_same / s.radius, bins=120, range=(0, 2.5), histtype="step", color=color, label=f"{n}, same side")
        ax[1].hist(nn / s.radius, bins=120, range=(0, 2.5), histtype="step", color=color, ls=":", label=f"{n}, all")
    ax[1].set_xlabel("NN distance / Poisson radius r")
    ax[1].set_yscale("log")
    ax[1].legend(fontsize=7)
    # a square patch of the largest horizontal surface (the floor): top view, 40 r wide
    for k, (n, color) in enumerate(zip(names, ["tab:green", "tab:gray"])):
        p, nrm, s = merged[n]["positions"], merged[n]["normals"], merged[n]["spacing"]
        up = nrm[:, 1] > 0.99
        floor_y = np.median(p[up, 1]) if up.any() else np.median(p[:, 1])
        sel = up & (np.abs(p[:, 1] - floor_y) < 1e-3)
        centre = np.median(p[sel], axis=0) if sel.any() else p.mean(axis=0)
        half = 20 * s.radius
        win = sel & (np.abs(p[:, 0] - centre[0]) < half) & (np.abs(p[:, 2] - centre[2]) < half)
        ax[2 + k].scatter(p[win, 0], p[win, 2], s=4, color=color)
        ax[2 + k].set_aspect("equal")
        ax[2 + k].set_title(f"{n}: floor patch, 40 r wide")
    fig.tight_layout()
    path = out / "bench_points.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    from psao.scene import load_scene
    from psao.server.settings import PointSettings

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", nargs="?", default="builtin:courtyard")
    ap.add_argument("--points", type=int, default=1_000_000, help="final points over the whole scene (part 1)")
    ap.add_argument("--pcu-samples", type=int, default=200_000, help="num_samples asked of pcu (part 2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spawn-ratio", type=float, default=2.0, help="spawned / kept (the paper: 2)")
    ap.add_argument("--sweep", default="", help="extra spawn ratios for the merged comparison, e.g. 3,5,8")
    ap.add_argument("--skip-scene", action="store_true", help="only the merged-mesh comparison")
    ap.add_argument("--feasibility", action="store_true",
                    help="also print the greedy bound on the spacing reachable from the spawn pool")
    ap.add_argument("--out", type=Path, default=Path("out/bench_points"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    settings = PointSettings(seed=args.seed, spawn_ratio=args.spawn_ratio)
    scene = load_scene(args.scene)
    summary: dict = {"scene": args.scene, "spawn_ratio": args.spawn_ratio}

    verdicts = Verdicts("bench_points")
    summary["warp_warm_up_seconds"] = warm_up()
    print(f"warm-up (Warp init, kernel load): {summary['warp_warm_up_seconds']:.2f} s")

    if not args.skip_scene:
        part = run_scene(scene, settings, args.points)
        ok = part["seconds"] < SCENE_TARGET_S
        print(f"\nscene {args.scene}: {part['instances']} instances, density {part['density']:.1f}/unit^2, "
              f"{part['spawned']} spawned -> {part['points']} points in {part['seconds']:.2f} s")
        verdicts.check(f"{args.scene} {part['points']} points, seconds", part["seconds"], "<", SCENE_TARGET_S)
        summary["scene_part"] = {k: v for k, v in part.items() if k != "sets"} | {"pass": ok}

    v, f = merged_mesh(scene)
    area = float(0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())
    pcu_s, pcu_p, pcu_n = run_pcu(v, f, args.pcu_samples, args.seed)
    ours_s, ours = run_ours_merged(v, f, len(pcu_p), settings)
    merged = {
        "psao (Yuksel elimination)": {"seconds": ours_s, "positions": ours.positions, "normals": ours.normals,
                                      "spacing": spacing(ours.positions, ours.normals, area)},
        "pcu.sample_mesh_poisson_disk": {"seconds": pcu_s, "positions": pcu_p, "normals": pcu_n,
                                         "spacing": spacing(pcu_p, pcu_n, area)},
    }
    sweep = []
    for ratio in [float(x) for x in args.sweep.split(",") if x]:
        sec, ps = run_ours_merged(v, f, len(pcu_p), replace(settings, spawn_ratio=ratio))
        sweep.append((f"psao, spawn ratio {ratio:g}", sec, spacing(ps.positions, ps.normals, area)))
    print(f"\nmerged mesh: {len(f)} triangles, area {area:.1f}; pcu asked for {args.pcu_samples}, returned {len(pcu_p)}")
    print_table([(n, m["seconds"], m["spacing"]) for n, m in merged.items()] + sweep)
    if args.feasibility:
        bound = greedy_spacing_bound(args.spawn_ratio)
        print(f"greedy bound: keeping 1 in {args.spawn_ratio:g} uniform random points, spacing <= ~{bound:.3f} r "
              f"(2D torus, min-degree greedy independent set)")
        summary["greedy_spacing_bound_over_r"] = bound
    summary["sweep"] = [{"name": n, "seconds": sec} | vars(sp) for n, sec, sp in sweep]
    ours_sp, pcu_sp = (m["spacing"] for m in merged.values())
    speedup = pcu_s / ours_s
    checks = {
        "speedup": speedup,
        "speedup_pass": speedup >= SPEEDUP_TARGET,
        "min_spacing_all_pass": ours_sp.min_all >= pcu_sp.min_all,
        "min_spacing_same_side_pass": ours_sp.min_same_side >= pcu_sp.min_same_side,
    }
    verdicts.check("speed-up over pcu.sample_mesh_poisson_disk", speedup, ">=", SPEEDUP_TARGET)
    verdicts.check("min spacing all pairs, ours / pcu's", ours_sp.min_all / pcu_sp.min_all, ">=", 1.0)
    verdicts.check("min spacing same side, ours / pcu's", ours_sp.min_same_side / pcu_sp.min_same_side, ">=", 1.0)
    summary["merged"] = {n: {"seconds": m["seconds"]} | vars(m["spacing"]) for n, m in merged.items()} | checks
    chart = write_charts(args.out, merged, args.scene)
    (args.out / "bench_points.json").write_text(json.dumps(summary, indent=2))
    print(f"chart: {chart}\n{json.dumps(summary)}")
    return verdicts.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
