"""The dask back-end against the local tracer, tiles against whole-scene workers, and a scaling model, in one run.

1. Throughput: the same bake trace (courtyard, N = 256, 128 rays) with the local Embree tracer (2 worker
   processes) and with the dask back-end on a LocalCluster of 2 worker processes, on the same 2 cores, back
   to back in each of --repeats rounds (which goes first alternates); the median of the rounds' ratios is
   the throughput ratio (target >= 0.85; a pair sees the same load, the best of each need not), and the
   grid bytes must be identical. CPU seconds over every process involved are printed beside it.
2. Scaling model (model_time): the trace time at W workers predicted from the rays one process traces
   per CPU second R (the local tracer in this thread, on a sample of the same points), the per-task
   overhead o (near-empty tasks on the 1-worker cluster), the client and scheduler's CPU per task and the
   share of a core each of W busy processes gets on this machine (core_share), checked against the
   measured traces on 1 and 2 workers (target: within 25%). Every input is measured in the same round as
   the traces it predicts, right before them.
3. Memory: a large generated scene (builtin:courtyard-8x8, 64 courtyards, 1.5 M triangles) traced on a fresh
   2-worker LocalCluster without tiles (each worker loads and holds the whole scene) and with --tiles (each
   task carries only its tile's triangles): peak resident memory (ru_maxrss) of each worker, in a table; the two
   results must be identical.

Writes a chart (throughput against workers: model, cap, measured; peak memory per worker) and a JSON file.

    .venv/bin/python -m benchmarks.bench_dask [--scene builtin:courtyard] [--density 256] [--rays 128]
        [--repeats 3] [--large builtin:courtyard-8x8] [--large-density 4] [--large-rays 16] [--skip-memory]
        [--out out/bench_dask] [--chart docs/images/dask_scaling.png]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.scene import load_scene
from psao.server.bake import build_scene_grid
from psao.server.geometry import grid_world_points, scene_center, scene_world_geometry, to_world
from psao.server.points.generate import generate_scene_points
from psao.server.settings import ClusterSettings, PointSettings, TraceSettings
from psao.server.tracer import make_tracer

THROUGHPUT_TARGET = 0.85
MODEL_TOLERANCE = 0.25
WORKERS = 2


def local_cluster(workers: int):
    from distributed import LocalCluster

    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")


def dask_tracer(scene, address: str, **kw):
    return make_tracer("dask", scene_center(scene), cluster=ClusterSettings(address, **kw), scene_spec=scene.source)


def grid_bytes(grid, table, vis) -> bytes:
    from psao.protocol import pointword as pw

    grid.set_ao(table.slot, table.index, pw.quantise_ao(vis))
    return b"".join(a.tobytes() for a in (grid.instances, grid.buckets, grid.cells))


# ---------------------------------------------------------------- 1. throughput and 2. scaling
def process_cpu() -> dict[int, float]:
    """User + system CPU seconds of this process and each live descendant (workers, nannies), by pid."""
    import psutil

    me = psutil.Process()
    out = {}
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
            out[p.pid] = t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return out


def measure(tracer, pos, nrm, ids, s: TraceSettings) -> dict:
    """One timed trace: wall seconds, CPU seconds of this process (client, and the scheduler of a
    LocalCluster) and of the others, the seconds the workers spent inside their trace calls, tasks."""
    cpu0, inside0, tasks0 = process_cpu(), tracer.account.cpu_total, tracer.tasks_done
    t0, thread0 = time.perf_counter(), time.thread_time()
    vis = tracer.visibility(pos, nrm, ids, s)
    wall, thread = time.perf_counter() - t0, time.thread_time() - thread0
    cpu1 = process_cpu()
    me = os.getpid()
    spent = {pid: c - cpu0.get(pid, 0.0) for pid, c in cpu1.items()}
    return {"vis": vis, "wall": wall, "cpu_thread": thread, "cpu_main": spent.pop(me, 0.0), "cpu_others": sum(spent.values()),
            "inside": tracer.account.cpu_total - inside0, "tasks": tracer.tasks_done - tasks0,
            "rays": len(pos) * s.rays, "load": os.getloadavg()[0]}


SPIN = ("import time\nt0, c0 = time.perf_counter(), time.process_time()\n"
        "while time.perf_counter() - t0 < {seconds}: pass\n"
        "print((time.process_time() - c0) / (time.perf_counter() - t0))")


def core_share(w: int, seconds: float = 2.0) -> float:
    """The share of a core each of `w` busy processes gets on this machine now (1 on cores of their own):
    w processes spin for `seconds` together, each reports its CPU seconds per wall second."""
    procs = [subprocess.Popen([sys.executable, "-c", SPIN.format(seconds=seconds)], stdout=subprocess.PIPE, text=True)
             for _ in range(w)]
    return float(np.mean([float(p.communicate()[0]) for p in procs]))


def model_time(w: int, m: dict, share: float = 1.0) -> float:
    """Predicted trace seconds at `w` workers (the scaling model; docs/dask.md states it).

    A trace is n tasks of r rays. A worker spends o + r / (R a) on a task: o the per-task overhead
    (near-empty tasks on one worker), R the rays one process traces per CPU second, a the share of a core
    each of the w workers gets (1 with a core each; on a shared machine, measured by core_share just
    before the trace). Tasks are whole, so the busiest worker runs ceil(n / w) of them. The one client and
    scheduler spend c of CPU per task, a floor of n c however many workers there are."""
    n, R = m["tasks"], m["rate"]
    r = m["total_rays"] / n
    return max(math.ceil(n / w) * (m["overhead"] + r / (R * share)), n * m["overhead_client_cpu"])


def throughput_and_scaling(args, v: Verdicts) -> dict:
    """Every input of the model and every trace it predicts, measured in the same rounds, interleaved."""
    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    pointsets = generate_scene_points(scene, PointSettings(density=args.density))
    grid = build_scene_grid(scene, pointsets)
    table, pos, nrm = grid_world_points(grid, scene)
    ids = table.point_id
    rays = len(pos) * args.rays
    s = TraceSettings(rays=args.rays, ao_distance=scene.ao_distance)
    tiny_s = TraceSettings(rays=1, ao_distance=scene.ao_distance)
    print(f"{args.scene} N={args.density:g}: {len(pos):,} points, {rays / 1e6:.0f} M rays per trace "
          f"(points and grid {time.perf_counter() - t0:.0f} s); load {os.getloadavg()[0]:.2f}", flush=True)
    geometry = scene_world_geometry(scene)
    warm = slice(0, min(len(pos), 4096))
    sample = slice(None, None, max(1, len(pos) // args.rate_points))
    n_tiny = args.overhead_tasks

    # The local pool forks: start it before the clusters' threads exist.
    local = make_tracer("embree", scene_center(scene), workers=WORKERS)
    local.set_static(*geometry)
    local.warm_up()
    local.visibility(pos[warm], nrm[warm], ids[warm], s)
    one = make_tracer("embree", scene_center(scene), workers=1)  # traces in this process
    one.set_static(*geometry)
    one.visibility(pos[warm], nrm[warm], ids[warm], s)
    clusters, remote, startup = {}, {}, {}
    for w in (1, WORKERS):  # start-up: cluster, scene delivered to every worker, first (warm-up) trace
        t_start = time.perf_counter()
        clusters[w] = local_cluster(w)
        remote[w] = dask_tracer(scene, clusters[w].scheduler_address)
        remote[w].set_static(*geometry)
        remote[w].warm_up()
        remote[w].visibility(pos[warm], nrm[warm], ids[warm], s)  # workers load their Warp kernels
        startup[w] = time.perf_counter() - t_start
        print(f"  {w}-worker LocalCluster: started, scene on every worker, warm in {startup[w]:.1f} s", flush=True)
    chunked = remote[1].settings
    tiny = dataclasses.replace(chunked, chunk_points=1)

    rounds, results = [], {}
    for r in range(args.repeats):
        row = {}
        row["rate"] = measure(one, pos[sample], nrm[sample], ids[sample], s)  # in this thread: CPU rate
        remote[1].settings = tiny
        row["tiny"] = measure(remote[1], pos[:n_tiny], nrm[:n_tiny], ids[:n_tiny], tiny_s)
        remote[1].settings = chunked
        order = [("local", local), ("dask2", remote[WORKERS])]  # the pair alternates which goes first
        for name, tracer in [*(order if r % 2 == 0 else order[::-1]), ("dask1", remote[1])]:
            share = core_share(WORKERS if name != "dask1" else 1)
            row[name] = measure(tracer, pos, nrm, ids, s)
            row[name]["share"] = share
            results.setdefault(name, row[name]["vis"])
        for m in row.values():
            m.pop("vis")
        rate = row["rate"]["rays"] / row["rate"]["cpu_thread"]
        tiny_m = row["tiny"]
        row["model_inputs"] = {"rate": rate, "overhead": tiny_m["wall"] / n_tiny,
                               "overhead_client_cpu": tiny_m["cpu_main"] / n_tiny,
                               "share": {1: row["dask1"]["share"], WORKERS: row["dask2"]["share"]},
                               "tasks": row["dask2"]["tasks"], "total_rays": rays}
        row["model"] = {w: model_time(w, row["model_inputs"], row["model_inputs"]["share"][w]) for w in (1, WORKERS)}
        rounds.append(row)
        print(f"  round {r + 1}: R = {rate / 1e6:.2f} Mrays per CPU s ({row['rate']['rays'] / row['rate']['wall'] / 1e6:.2f} "
              f"per wall s), o = {1e3 * tiny_m['wall'] / n_tiny:.1f} ms per task (client+scheduler CPU "
              f"{1e3 * tiny_m['cpu_main'] / n_tiny:.1f} ms); load {row['rate']['load']:.2f}", flush=True)
        for name in ("local", "dask2", "dask1"):
            m = row[name]
            print(f"    {name:6s} {m['wall']:7.1f} s, {rays / m['wall'] / 1e6:5.2f} Mrays/s, {m['tasks']:4d} tasks, "
                  f"core share {m['share']:.2f}, inside trace calls {m['inside']:6.1f} s, CPU here {m['cpu_main']:5.1f} s / "
                  f"workers {m['cpu_others']:6.1f} s; load {m['load']:.2f}", flush=True)
        print(f"    model: {row['model'][1]:.1f} s at 1 worker, {row['model'][WORKERS]:.1f} s at {WORKERS}", flush=True)
    for w in (1, WORKERS):
        remote[w].close()
        clusters[w].close()
    local.close()
    one.close()

    best = {k: min(row[k]["wall"] for row in rounds) for k in ("local", "dask2", "dask1")}
    paired = [row["local"]["wall"] / row["dask2"]["wall"] for row in rounds]  # the two traces of a round, back to back
    ratio = float(np.median(paired))
    cpu = {k: min(row[k]["cpu_main"] + row[k]["cpu_others"] for row in rounds) for k in ("local", "dask2")}
    print(f"throughput: dask / local per round {', '.join(f'{x:.3f}' for x in paired)}; best of {args.repeats}: local "
          f"{rays / best['local'] / 1e6:.2f} Mrays/s, dask {rays / best['dask2'] / 1e6:.2f} Mrays/s "
          f"({best['local'] / best['dask2']:.3f}); rays per CPU second, dask / local: {cpu['local'] / cpu['dask2']:.3f}")
    v.check(f"{scene.name} N={args.density:g} {args.rays} rays dask ({WORKERS} workers) / local ({WORKERS} processes) "
            f"throughput, median of {len(rounds)} back-to-back pairs", ratio, ">=", THROUGHPUT_TARGET)
    same = grid_bytes(grid, table, results["local"]) == grid_bytes(grid, table, results["dask2"])
    v.record(f"{scene.name} N={args.density:g} grid bytes identical, dask and local", same)
    v.record("1-worker cluster result identical", bool(np.array_equal(results["dask1"], results["local"])))

    # The model from each round's own inputs against that round's traces; the verdict on the median error.
    errors = {w: [row["model"][w] / row[name]["wall"] - 1 for row in rounds] for w, name in ((1, "dask1"), (WORKERS, "dask2"))}
    inputs = {k: float(np.median([row["model_inputs"][k] for row in rounds])) for k in rounds[0]["model_inputs"] if k != "share"}
    print(f"scaling model (medians of the rounds): R = {inputs['rate'] / 1e6:.2f} Mrays per CPU second, "
          f"o = {inputs['overhead'] * 1e3:.1f} ms per task (client+scheduler CPU {inputs['overhead_client_cpu'] * 1e3:.1f} ms), "
          f"{inputs['tasks']:.0f} tasks of {rays / inputs['tasks'] / 1e6:.2f} M rays")
    for w in (1, WORKERS):
        name = "dask1" if w == 1 else "dask2"
        per_round = ", ".join(f"{row['model'][w]:.1f} / {row[name]['wall']:.1f} s (a = {row[name]['share']:.2f})" for row in rounds)
        print(f"  {w} worker(s): model / measured per round {per_round}")
        v.check(f"scaling model trace time / measured at {w} worker(s), median |1 - x| of {len(rounds)} rounds",
                float(np.median(np.abs(errors[w]))), "<=", MODEL_TOLERANCE)
    return {"scene": args.scene, "density": args.density, "rays": args.rays, "points": len(pos), "total_rays": rays,
            "rounds": rounds, "startup": startup, "ratio": ratio, "paired": paired, "best_ratio": best["local"] / best["dask2"],
            "cpu_ratio": cpu["local"] / cpu["dask2"], "grid_identical": same, "model_inputs": inputs,
            "errors": errors}


# ---------------------------------------------------------------- 3. memory with and without tiles
def memory(args, v: Verdicts) -> dict:
    from psao.server.tracer.dask_backend import worker_peak_rss

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
                     "peak_rss_workers": sorted(float(x) for x in peak.values()),
                     "peak_rss_mean": float(np.mean(list(peak.values())))})
        tracer.close()
        cluster.close()
    print(f"{'mode':12s} {'tasks':>6s} {'idle MiB':>9s} {'peak RSS of each worker, MiB':>30s} {'peak - idle':>12s} {'trace s':>8s}")
    for r in rows:
        each = " / ".join(f"{x / 2**20:.0f}" for x in r["peak_rss_workers"])
        print(f"{r['mode']:12s} {r['tasks']:6d} {r['idle_rss'] / 2**20:9.0f} {each:>30s} "
              f"{(r['peak_rss'] - r['idle_rss']) / 2**20:12.0f} {r['seconds']:8.1f}")
    v.record(f"{scene.name} tiled result identical to the whole-scene one", bool(np.array_equal(vis["tiles"], vis["whole scene"])))
    peak = {r["mode"]: r["peak_rss"] for r in rows}
    v.check(f"{scene.name} peak RSS per worker (largest), tiles / whole scene", peak["tiles"] / peak["whole scene"], "<", 1.0)
    grown = {r["mode"]: r["peak_rss"] - r["idle_rss"] for r in rows}
    v.check(f"{scene.name} worker memory growth, tiles / whole scene", grown["tiles"] / max(grown["whole scene"], 1), "<=", 0.5)
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
    """Mrays/s against workers: the model with a core per worker (extrapolated), the model with each round's
    measured core share at 1 and 2 workers, and the measured traces of every round."""
    m, rays = th["model_inputs"], th["total_rays"]
    w = np.unique(np.round(np.geomspace(1, 256, 60))).astype(int)
    ax.plot(w, [rays / model_time(int(k), m) / 1e6 for k in w], label="model, a core per worker")
    ax.plot(w, w * m["rate"] / 1e6, ":", color="grey", label="W x single-worker rate R")
    ax.axhline(rays / (m["tasks"] * m["overhead_client_cpu"]) / 1e6, ls="--", color="tab:red", lw=0.8,
               label="client + scheduler cap")
    for i, row in enumerate(th["rounds"]):
        x = np.array([1, WORKERS]) * (1 + 0.04 * (i - 1))  # rounds side by side
        ax.plot(x, [rays / row["model"][k] / 1e6 for k in (1, WORKERS)], "s", mfc="none", color="tab:orange", ms=8,
                label="model, core share measured in the round" if i == 0 else None)
        ax.plot(x, [rays / row[k]["wall"] / 1e6 for k in ("dask1", "dask2")], "o", color="k", ms=4,
                label="measured (LocalCluster on the shared 2 cores)" if i == 0 else None)
    ax.set(xscale="log", yscale="log", xlabel="workers (one core each)", ylabel="Mrays/s",
           title=f"{th['scene']} N={th['density']:g}, {th['rays']} rays: {m['tasks']:.0f} tasks, "
                 f"o = {m['overhead'] * 1e3:.0f} ms")
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
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the model's inputs and the traces it predicts")
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
