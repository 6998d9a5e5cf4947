"""The dask back-end against the local tracer, tiles against whole-scene workers, and a scaling model, in one run.

1. Throughput: the same bake trace (courtyard, N = 256, 128 rays) with the local Embree tracer (2 worker
   processes) and with the dask back-end on a LocalCluster of 2 worker processes, on the same 2 cores,
   alternating, --repeats times each; the best wall time of each gives the throughput ratio (target >= 0.85),
   and the grid bytes must be identical. CPU seconds over every process involved are printed beside it.
2. Scaling model: a task of r rays costs a worker o + r / R seconds, R the single-worker ray rate (the local
   tracer on one core, on a sample of the same points) and o the per-task overhead (near-empty tasks on a
   1-worker cluster). W workers then trace at X(W) = W r / (o + r / R) rays/s, and no faster than r / o
   (every task also passes through the one scheduler and the one client, whose share is inside o). The
   model's trace time is checked against measured ones at 1 and 2 workers (target: within 25%).
3. Memory: a large generated scene (builtin:courtyard-8x8, 64 courtyards, 1.5 M triangles) traced on a fresh
   2-worker LocalCluster without tiles (each worker loads and holds the whole scene) and with --tiles (each
   task carries only its tile's triangles): peak resident memory per worker, in a table; the two results
   must be identical.

Writes a chart (throughput against workers: model, cap, measured; peak memory per worker) and a JSON file.

    .venv/bin/python -m benchmarks.bench_dask [--scene builtin:courtyard] [--density 256] [--rays 128]
        [--repeats 2] [--large builtin:courtyard-8x8] [--large-density 4] [--large-rays 16] [--skip-memory]
        [--out out/bench_dask] [--chart docs/images/dask_scaling.png]
"""
from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao_scene import load_scene
from psao_server.bake import build_scene_grid, grid_world_points, scene_center, scene_world_geometry, to_world
from psao_server.points import generate_scene_points
from psao_server.settings import ClusterSettings, PointSettings, TraceSettings
from psao_server.tracer import make_tracer

THROUGHPUT_TARGET = 0.85
MODEL_TOLERANCE = 0.25
WORKERS = 2


def tree_cpu_seconds() -> float:
    """User + system CPU seconds of this process and all its live descendants (workers, nannies)."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return total


def local_cluster(workers: int):
    from distributed import LocalCluster

    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")


def dask_tracer(scene, address: str, **kw):
    return make_tracer("dask", scene_center(scene), cluster=ClusterSettings(address, **kw), scene_spec=scene.source)


def timed_trace(tracer, pos, nrm, ids, s: TraceSettings) -> tuple[np.ndarray, float, float]:
    cpu0, t0 = tree_cpu_seconds(), time.perf_counter()
    vis = tracer.visibility(pos, nrm, ids, s)
    return vis, time.perf_counter() - t0, tree_cpu_seconds() - cpu0


def grid_bytes(grid, table, vis) -> bytes:
    from protocol import pointword as pw

    grid.set_ao(table.slot, table.index, pw.quantise_ao(vis))
    return b"".join(a.tobytes() for a in (grid.instances, grid.buckets, grid.cells))


# ---------------------------------------------------------------- 1. throughput and 2. scaling
def throughput_and_scaling(args, v: Verdicts) -> dict:
    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    pointsets = generate_scene_points(scene, PointSettings(density=args.density))
    grid = build_scene_grid(scene, pointsets)
    table, pos, nrm = grid_world_points(grid, scene)
    ids = table.point_id
    rays = len(pos) * args.rays
    s = TraceSettings(rays=args.rays, ao_distance=scene.ao_distance)
    print(f"{args.scene} N={args.density:g}: {len(pos):,} points, {rays / 1e6:.0f} M rays per trace "
          f"(points and grid {time.perf_counter() - t0:.0f} s)", flush=True)
    geometry = scene_world_geometry(scene)
    warm = slice(0, min(len(pos), 4096))

    # The local pool forks: start it before the cluster's threads exist.
    local = make_tracer("embree", scene_center(scene), workers=WORKERS)
    local.set_static(*geometry)
    local.warm_up()
    local.visibility(pos[warm], nrm[warm], ids[warm], s)
    cluster = local_cluster(WORKERS)
    remote = dask_tracer(scene, cluster.scheduler_address)
    remote.set_static(*geometry)
    remote.warm_up()
    remote.visibility(pos[warm], nrm[warm], ids[warm], s)  # workers load their Warp kernels

    runs = {"local": [], "dask": []}
    results = {}
    for r in range(args.repeats):
        for name, tracer in (("local", local), ("dask", remote)):
            before = remote.tasks_done
            vis, wall, cpu = timed_trace(tracer, pos, nrm, ids, s)
            if name == "dask":
                tasks_per_trace = remote.tasks_done - before
            runs[name].append({"wall": wall, "cpu": cpu})
            results.setdefault(name, vis)
            print(f"  round {r + 1}: {name:5s} {wall:7.1f} s wall, {rays / wall / 1e6:6.2f} Mrays/s; "
                  f"{cpu:7.1f} CPU s in all processes", flush=True)
    remote.close()
    cluster.close()
    local.close()

    best = {k: min(x["wall"] for x in runs[k]) for k in runs}
    cpu = {k: min(x["cpu"] for x in runs[k]) for k in runs}
    ratio = best["local"] / best["dask"]
    print(f"throughput: local {rays / best['local'] / 1e6:.2f} Mrays/s, dask {rays / best['dask'] / 1e6:.2f} Mrays/s "
          f"(best of {args.repeats}); rays per CPU second, dask / local: {cpu['local'] / cpu['dask']:.3f}")
    v.check(f"{scene.name} N={args.density:g} dask ({WORKERS} workers) / local ({WORKERS} processes) throughput",
            ratio, ">=", THROUGHPUT_TARGET)
    same = grid_bytes(grid, table, results["local"]) == grid_bytes(grid, table, results["dask"])
    v.record(f"{scene.name} N={args.density:g} grid bytes identical, dask and local", same)

    # Scaling model: the single-worker rate R (local tracer, one core, every k-th point) ...
    sample = slice(None, None, max(1, len(pos) // args.rate_points))
    with make_tracer("embree", scene_center(scene), workers=1) as one:
        one.set_static(*geometry)
        one.visibility(pos[warm], nrm[warm], ids[warm], s)
        _, wall, _ = timed_trace(one, pos[sample], nrm[sample], ids[sample], s)
    rate = len(pos[sample]) * args.rays / wall
    # ... the per-task overhead o (near-empty tasks on a 1-worker cluster), and the trace there.
    cluster = local_cluster(1)
    with dask_tracer(scene, cluster.scheduler_address, chunk_points=1) as tiny:
        tiny.set_static(*geometry)
        tiny.warm_up()
        tiny.visibility(pos[:8], nrm[:8], ids[:8], TraceSettings(rays=1, ao_distance=scene.ao_distance))
        n = args.overhead_tasks
        _, wall, _ = timed_trace(tiny, pos[:n], nrm[:n], ids[:n], TraceSettings(rays=1, ao_distance=scene.ao_distance))
    overhead = wall / n
    with dask_tracer(scene, cluster.scheduler_address) as single:
        single.set_static(*geometry)
        single.warm_up()
        single.visibility(pos[warm], nrm[warm], ids[warm], s)
        before = single.tasks_done
        vis1, wall1, _ = timed_trace(single, pos, nrm, ids, s)
        tasks1 = single.tasks_done - before
    cluster.close()
    v.record("1-worker cluster result identical", bool(np.array_equal(vis1, results["local"])))
    measured = {1: wall1, 2: best["dask"]}
    tasks = {1: tasks1, 2: tasks_per_trace}
    model = {w: (tasks[w] * overhead + rays / rate) / w for w in (1, 2)}
    print(f"scaling model: R = {rate / 1e6:.2f} Mrays/s per worker, o = {overhead * 1e3:.1f} ms per task, "
          f"{rays / tasks[2] / 1e6:.2f} M rays per task")
    for w in (1, 2):
        print(f"  {w} worker(s): model {model[w]:.1f} s, measured {measured[w]:.1f} s")
        v.check(f"scaling model trace time / measured at {w} worker(s), |1 - x|", abs(1 - model[w] / measured[w]),
                "<=", MODEL_TOLERANCE)
    return {"scene": args.scene, "density": args.density, "rays": args.rays, "points": len(pos),
            "runs": runs, "ratio": ratio, "cpu_ratio": cpu["local"] / cpu["dask"], "grid_identical": same,
            "rate_per_worker": rate, "overhead_per_task": overhead, "rays_per_task": rays / tasks[2],
            "measured": measured, "model": model, "total_rays": rays}


# ---------------------------------------------------------------- 3. memory with and without tiles
def memory(args, v: Verdicts) -> dict:
    from psao_server.tracer.dask_backend import worker_peak_rss

    t0 = time.perf_counter()
    scene = load_scene(args.large)
    geometry = scene_world_geometry(scene)
    pointsets = generate_scene_points(scene, PointSettings(density=args.large_density))
    pos, nrm = map(np.concatenate, zip(*[to_world(i.transform, ps.positions, ps.normals)
                                         for i, ps in zip(scene.instances, pointsets)]))
    ids = np.arange(len(pos))
    s = TraceSettings(rays=args.large_rays, ao_distance=scene.ao_distance)
    print(f"{args.large}: {len(geometry[1]):,} triangles, {len(pos):,} points at N={args.large_density:g}, "
          f"{args.large_rays} rays (scene and points {time.perf_counter() - t0:.0f} s)", flush=True)
    rows, vis = [], {}
    for mode, tiles in (("whole scene", False), ("tiles", True)):
        cluster = local_cluster(WORKERS)
        tracer = dask_tracer(scene, cluster.scheduler_address, tiles=tiles, tile_points=args.tile_points)
        idle = tracer.client.run(worker_peak_rss)
        t0 = time.perf_counter()
        tracer.set_static(*geometry)
        tracer.warm_up()
        vis[mode] = tracer.visibility(pos, nrm, ids, s)
        seconds = time.perf_counter() - t0
        peak = tracer.client.run(worker_peak_rss)
        rows.append({"mode": mode, "tasks": tracer.tasks_done, "seconds": seconds,
                     "idle_rss": float(np.mean(list(idle.values()))), "peak_rss": float(max(peak.values())),
                     "peak_rss_mean": float(np.mean(list(peak.values())))})
        tracer.close()
        cluster.close()
    print(f"{'mode':12s} {'tasks':>6s} {'idle MiB':>9s} {'peak MiB':>9s} {'peak - idle':>12s} {'trace s':>8s}")
    for r in rows:
        print(f"{r['mode']:12s} {r['tasks']:6d} {r['idle_rss'] / 2**20:9.0f} {r['peak_rss'] / 2**20:9.0f} "
              f"{(r['peak_rss'] - r['idle_rss']) / 2**20:12.0f} {r['seconds']:8.1f}")
    v.record(f"{scene.name} tiled result identical to the whole-scene one", bool(np.array_equal(vis["tiles"], vis["whole scene"])))
    grown = {r["mode"]: r["peak_rss"] - r["idle_rss"] for r in rows}
    v.check(f"{scene.name} worker memory growth, tiles / whole scene", grown["tiles"] / grown["whole scene"], "<=", 0.5)
    return {"scene": args.large, "density": args.large_density, "rays": args.large_rays, "points": len(pos),
            "triangles": len(geometry[1]), "tile_points": args.tile_points, "rows": rows}


def chart(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [k for k in ("throughput", "memory") if k in result]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False)
    if "throughput" in result:
        _throughput_panel(axes[0, 0], result["throughput"])
    if "memory" in result:
        _memory_panel(axes[0, -1], result["memory"])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)


def _throughput_panel(ax, th: dict) -> None:
    w = np.unique(np.round(np.geomspace(1, 256, 60)))
    r, o, R = th["rays_per_task"], th["overhead_per_task"], th["rate_per_worker"]
    ax.plot(w, np.minimum(w * r / (o + r / R), r / o) / 1e6, label="model: min(W r / (o + r/R), r / o)")
    ax.plot(w, w * R / 1e6, ":", color="grey", label="W x single-worker rate R")
    ax.axhline(r / o / 1e6, ls="--", color="tab:red", lw=0.8, label="scheduler/client cap r / o")
    ax.plot(list(th["measured"]), [th["total_rays"] / t / 1e6 for t in th["measured"].values()], "o", color="k",
            label="measured (LocalCluster, 2 cores)")
    ax.set(xscale="log", yscale="log", xlabel="workers (one core each)", ylabel="Mrays/s",
           title=f"{th['scene']} N={th['density']:g}: {r / 1e6:.1f} M rays/task, o = {o * 1e3:.0f} ms")
    ax.legend(fontsize=7)


def _memory_panel(ax, memory: dict) -> None:
    rows = memory["rows"]
    x = np.arange(len(rows))
    ax.bar(x, [q["idle_rss"] / 2**20 for q in rows], color="lightgrey", label="idle worker")
    ax.bar(x, [(q["peak_rss"] - q["idle_rss"]) / 2**20 for q in rows], bottom=[q["idle_rss"] / 2**20 for q in rows],
           color="tab:blue", label="grown while tracing")
    ax.set_xticks(x, [q["mode"] for q in rows])
    ax.set(ylabel="peak resident MiB per worker", title=f"{memory['scene']}: {memory['triangles'] / 1e6:.2f} M triangles")
    ax.legend(fontsize=7)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="builtin:courtyard")
    ap.add_argument("--density", type=float, default=256.0)
    ap.add_argument("--rays", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=2, help="alternating rounds of local and dask traces")
    ap.add_argument("--rate-points", type=int, default=100_000, help="points of the single-worker rate sample")
    ap.add_argument("--overhead-tasks", type=int, default=200, help="near-empty tasks that measure the overhead")
    ap.add_argument("--large", default="builtin:courtyard-8x8")
    ap.add_argument("--large-density", type=float, default=4.0)
    ap.add_argument("--large-rays", type=int, default=16)
    ap.add_argument("--tile-points", type=int, default=ClusterSettings("").tile_points)
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--skip-throughput", action="store_true", help="only the memory part")
    ap.add_argument("--out", type=Path, default=Path("out/bench_dask"))
    ap.add_argument("--chart", type=Path, default=None, help="chart PNG (default OUT/bench_dask.png)")
    args = ap.parse_args(argv)
    v = Verdicts("bench_dask")
    result = {} if args.skip_throughput else {"throughput": throughput_and_scaling(args, v)}
    if not args.skip_memory:
        result["memory"] = memory(args, v)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_dask.json").write_text(json.dumps(result, indent=1, default=float))
    chart_path = args.chart or args.out / "bench_dask.png"
    chart(result, chart_path)
    print(f"wrote {args.out / 'bench_dask.json'} and {chart_path}; this process peaked at "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB")
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
