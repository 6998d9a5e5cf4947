"""What a whole trace from the bake's static hits costs against a full trace, and what the hits take in memory.

Per scene (built-in courtyard and robots): a bake at --density points/m^2 and --rays rays keeps the static
scene's answers of its static points (psao.server.tracer.static_hits); one tick of motion (1/60 s after t = 0)
selects the static points near the movers; on those points, in the tracer's worker (one process), the
tracer's seconds per point of
  whole    the whole --rays-ray set from the kept static hits (only the rays the static scene lets
           through, traced against the movers: TracePart.static_hit), what the budgeted tick's whole
           traces do,
  full     the same ray sets traced against the whole scene (the full trace),
  round    one --round-rays-ray slice of them (a budgeted round),
best of --repeats, and their ratio whole / full, the figure BudgetSettings.exact_cost stands for. Also the
share of those rays the static scene occludes and the bytes the kept hits take. Verdicts: the whole
traces equal the full trace exactly, cost less than it, and the hits take ceil(rays / 8) + 2 bytes a point.

The seconds are the tracer's own per-chunk clock in its worker (CpuAccount.cpu_total): a speed figure,
so run it under the benchmark lock for figures to report; niced on a loaded machine the ratio holds
better than the absolute microseconds.

    .venv/bin/python -m benchmarks.bench_static_hits [--density 64] [--rays 32] [--round-rays 8] [--repeats 3]
"""
from __future__ import annotations

import argparse
import os

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.server.tick.budget import BudgetSettings


def scene_costs(name: str, args) -> dict:
    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings, TickSettings, TraceSettings
    from psao.server.tick.server_tick import ServerTick
    from psao.server.tracer.base import TracePart

    bake = bake_scene(load_scene(f"builtin:{name}"), BakeSettings(density=args.density, rays=args.rays, workers=1),
                      show_progress=False)
    hits = bake.static_hits
    points = sum(len(ps) for ps in bake.pointsets)
    tick = ServerTick(bake, TickSettings(rays=args.rays, workers=1))
    try:
        tick(tick.grid, 0.0)
        frame = tick.animator.frame(1.0 / 60.0)
        changed, _ = tick._motion_candidates(frame)
        ids = changed[hits.known[changed]]  # the static points one tick of motion selects
        tick.pose_tracer(frame)
        tracer, s = tick.tracer, tick.trace_settings
        pos, nrm, packed = tick.world_pos[ids], tick.world_nrm[ids], hits.packed(ids)
        rounds = TraceSettings(rays=args.rays, ao_distance=s.ao_distance, seed=s.seed,
                               slices=args.rays // args.round_rays)
        parts = {"whole": TracePart(pos, nrm, ids, s, static_hit=packed),
                 "full": TracePart(pos, nrm, ids, s),
                 "round": TracePart(pos, nrm, ids, rounds, np.zeros(len(ids), np.int64))}
        best, vis = {}, {}
        for _ in range(args.repeats):
            for kind, part in parts.items():
                before = tracer.account.cpu_total
                vis[kind] = tracer.visibility_parts([part])[0][0]
                spent = (tracer.account.cpu_total - before) / max(len(ids), 1)
                best[kind] = min(best.get(kind, np.inf), spent)
        occluded = float(np.unpackbits(packed, axis=1, count=args.rays).mean()) if len(ids) else float("nan")
        return {"points": int(len(ids)), "us": {k: 1e6 * v for k, v in best.items()},
                "equal": bool(np.array_equal(vis["whole"], vis["full"])), "static_occluded": occluded,
                "hits_bytes": hits.nbytes, "scene_points": points}
    finally:
        tick.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--density", type=float, default=64.0, help="bake points per m^2")
    ap.add_argument("--rays", type=int, default=32, help="rays per point (bake and tick)")
    ap.add_argument("--round-rays", type=int, default=8, help="rays of one budgeted round, a divisor of --rays")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    if args.rays < 1 or args.round_rays < 1 or args.rays % args.round_rays or args.repeats < 1:
        ap.error("--rays and --round-rays must be >= 1, --round-rays dividing --rays; --repeats >= 1")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; BudgetSettings.exact_cost = "
          f"{BudgetSettings.exact_cost:g}")
    v = Verdicts("bench_static_hits")
    for name in ("courtyard", "robots"):
        r = scene_costs(name, args)
        us = r["us"]
        per_point = r["hits_bytes"] / max(r["scene_points"], 1)
        print(f"  {name} N={args.density:g}, {args.rays} rays: {r['points']} static points selected by one tick of "
              f"motion; us a point: whole from static hits {us['whole']:.2f}, full trace {us['full']:.2f}, "
              f"{args.round_rays}-ray round {us['round']:.2f}; static scene occludes {100 * r['static_occluded']:.1f}% "
              f"of their rays; kept hits {r['hits_bytes'] / 1e6:.2f} MB for {r['scene_points']} points "
              f"({per_point:.1f} bytes a point)", flush=True)
        v.check(f"{name} whole traces from static hits equal the full trace (1 = equal)", float(r["equal"]), ">=", 1.0)
        v.check(f"{name} whole trace from static hits / full trace, seconds a point", us["whole"] / us["full"], "<", 1.0)
        v.check(f"{name} kept static hits, bytes a point", per_point, "<=", (args.rays + 7) // 8 + 2)
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
