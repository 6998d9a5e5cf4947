"""The real-time server against its targets, each part measured against a real baseline in the same run.

Parts (--parts, comma list; all by default):
  tracer   the tracer against bare embreex on exactly the same rays with the same number of processes
           (benchmarks.bare_embree): a bake-sized batch (target >= 0.9) and tick-sized batches of a moving
           scene (target >= 0.8), medians of interleaved repeats (wall seconds, so both runs share the load)
  grid     the grid stage (the tick's apply) of a skinned model at --skinned-points points, every skinned
           point re-posed and traced each tick: the grid keeps skinned points in the rest pose, so the
           stage thresholds and writes their AO (no point moves through the grid); skinned points
           handled per second of grid stage (target >= 2 million), and cells dirtied per tick
  rate     ticks per second of a real `psao serve --animate --tick-hz 60` process (its own statistics)
           with a real `psao client` sending its camera (benchmarks.served): courtyard N=256, robots
           N=256 and N=512, the skinned model (target >= 55); also the bytes per second it sends, the
           stages' wall milliseconds per tick and the CPU milliseconds of the thread that prepares the tick
           (animate + select + trace, TickStats.cpu_prepare: wall above it is time spent waiting for the
           GIL, a core or the tracer's worker processes); the lag: the p50/p95 wait of the points in the
           client's view from their reset (the motion changed their neighbourhood) to their first re-trace
           (target p95 <= 100 ms), the queue over the first and last third of the window (bounded), the
           Updates a second the client received (>= 55) and the share of ticks it was on the shared stream
  quality  budgeted tick at 60 Hz (real time, in this process, its automatic budget leaving the room for the
           service that a real served run of the scene measured first: --service-seconds) against the
           unbudgeted tick (every selected point fully re-traced each tick, time not counted) at the same
           scene times: PSNR of the frames a client would draw from each tick's grid at the sampled scene
           times (--frame-size, the camera the ticks were given) against an RTAO reference frame
           (--frame-spp rays a pixel, its own noise taken out: debiased_psnr), while moving and one second
           after motion stops (targets: mean loss <= 1.0 dB, <= 0.5 dB at rest); beside it, not judged, the
           PSNR of the AO of sampled points the motion reaches in the camera's view against a --ref-rays
           trace (the loss where the motion is, undiluted by the pixels it does not reach); PSNR-over-time chart;
           while moving, the squared error split by kind of point (POINT_KINDS: where the loss comes from);
           --exact-share sets the budgeted tick's BudgetSettings.exact_share (0: no whole traces); with
           --fixed-rays R the budgeted tick runs at scene time k / 60 s with R rays a tick instead of in
           real time: the loss at a given tracing throughput, the same on a loaded machine (not judged)

Progressive start (`psao serve`'s default) has a benchmark of its own: benchmarks.bench_progressive.

The Warp CUDA tracer is not measured here unless --tracer warp is given on a machine with a GPU.

    .venv/bin/python -m benchmarks.bench_realtime [--parts tracer,grid,rate,quality] [--seconds 10]
        [--rate-scenes courtyard-256,robots-256,robots-512,skinned]
        [--skinned ../shared/scenes/cesiumman/CesiumMan.glb] [--out out/bench_realtime]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.eval.metrics import PSNR_CAP
from psao.server.tick.budget import BudgetSettings

PARTS = ("tracer", "grid", "rate", "quality")
TARGETS = {"tracer_bake": 0.9, "tracer_tick": 0.8, "grid_points_per_s": 2e6, "ticks_per_s": 55.0,
           "moving_loss_db": 1.0, "rest_loss_db": 0.5, "view_wait_p95_ms": 100.0, "client_updates_per_s": 55.0,
           # the queue's mean over the last third of the window against the first third: at most this ratio
           # (plus QUEUE_SLACK points, for a queue that is nearly empty)
           "queue_growth": 1.2}
QUEUE_SLACK = 1000
SKINNED = "../shared/scenes/cesiumman/CesiumMan.glb"
QUALITY_SCENES = ("courtyard", "robots")  # the quality part's built-in scenes (the target names both)
RATE_CASES = [("courtyard-256", "builtin:courtyard", 256.0), ("robots-256", "builtin:robots", 256.0),
              ("robots-512", "builtin:robots", 512.0),  # and "skinned": --skinned at --skinned-points
              ("lab", str(Path(__file__).resolve().parents[1] / "examples" / "lab.toml"), None)]  # at its defaults


def density_for(scene, points: float) -> float:
    """Density (points per unit^2) giving about `points` points on the scene's surface."""
    from psao.server.geometry import scene_world_geometry

    v, f = scene_world_geometry(scene)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    return float(points / max(area, 1e-12))


# ------------------------------------------------------------------------------------------ tracer
def part_tracer(args, v: Verdicts, out: dict) -> None:
    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.geometry import scene_center
    from psao.server.settings import BakeSettings, TickSettings, TraceSettings
    from psao.server.tick.server_tick import ServerTick

    from benchmarks.bare_embree import BareEmbree

    scene = load_scene("builtin:courtyard")
    bake = bake_scene(scene, BakeSettings(density=args.tracer_density, rays=4, workers=args.workers), show_progress=False)
    tick = ServerTick(bake, TickSettings(rays=32, workers=args.workers))
    try:
        workers = tick.tracer.workers
        rng = np.random.default_rng(0)
        rows = []
        # bake-sized: static points, static scene only (as the bake traces)
        ids = np.sort(rng.choice(tick.static_ids, min(args.bake_points, len(tick.static_ids)), replace=False))
        frame = tick.animator.frame(0.0)
        pos, nrm = tick.world_points(frame, ids)
        s = TraceSettings(rays=args.bake_rays, ao_distance=scene.ao_distance, seed=0)
        static_v, static_f = tick.animator.static_geometry()
        tick.tracer.set_dynamic(None, np.zeros((0, 3), int), None)
        rows.append(("bake", len(ids), s.rays) + _compare(tick.tracer, BareEmbree(static_v, static_f, None, None,
                                                                          scene_center(scene), workers),
                                                       pos, nrm, ids, s, args.repeats))
        # tick-sized: the points a moving tick selects, with the moving part posed at t
        for n_points in args.tick_points:
            t = 1.0
            frame = tick.animator.frame(t)
            near = np.flatnonzero(tick.tracked)
            ids = np.sort(rng.choice(near, min(n_points, len(near)), replace=False))
            pos, nrm = tick.world_points(frame, ids)
            s = TraceSettings(rays=args.tick_rays, ao_distance=scene.ao_distance, seed=1)
            tick.pose_tracer(frame)
            bare = BareEmbree(static_v, static_f, frame.dynamic_vertices, frame.dynamic_faces, scene_center(scene), workers)
            rows.append(("tick", len(ids), s.rays) + _compare(tick.tracer, bare, pos, nrm, ids, s, args.repeats))
    finally:
        tick.close()
    out["tracer"] = [dict(zip(("kind", "points", "rays", "tracer_s", "bare_s", "ratio"), r)) for r in rows]
    print(f"tracer vs bare embreex, {workers} processes each, same rays (median of {args.repeats} interleaved runs):")
    for kind, n, rays, ts, bs, ratio in rows:
        print(f"  {kind:4s} {n:8,d} points x {rays:3d} rays: tracer {1e3 * ts:8.1f} ms, bare {1e3 * bs:8.1f} ms, "
              f"{n * rays / ts / 1e6:6.2f} vs {n * rays / bs / 1e6:6.2f} Mrays/s")
        v.check(f"tracer / bare embreex throughput, {kind} {n} points x {rays} rays, {workers} processes", ratio,
                ">=", TARGETS[f"tracer_{kind}"])


def _compare(tracer, bare, pos, nrm, ids, s, repeats: int) -> tuple[float, float, float]:
    tracer.visibility(pos, nrm, ids, s)  # warm: pool and buffers
    ts, bs = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        tracer.visibility(pos, nrm, ids, s)
        ts.append(time.perf_counter() - t0)
        bs.append(bare.time(pos, nrm, ids, s))
    t, b = float(np.median(ts)), float(np.median(bs))
    return t, b, b / t


# -------------------------------------------------------------------------------------------- grid
def part_grid(args, v: Verdicts, out: dict) -> None:
    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings, TickSettings
    from psao.server.tick.server_tick import ServerTick

    scene = load_scene(args.skinned)
    density = density_for(scene, args.skinned_points)
    bake = bake_scene(scene, BakeSettings(density=density, rays=4, workers=args.workers), show_progress=False)
    tick = ServerTick(bake, TickSettings(rays=4, workers=args.workers))  # unbudgeted: every moved point traced
    try:
        tick.set_cameras([])
        skinned = sum(int(tick.tracked[tick.ids_of[i]].sum()) for i in tick.kinds.skinned)
        handled, seconds, written, dirty = 0, 0.0, 0, 0
        for k in range(args.grid_ticks):
            s = tick(tick.grid, (k + 1) / 30.0)
            tick.grid.take_dirty()
            handled += s.traced
            seconds += s.seconds_grid
            written += s.changed
            dirty += s.cells_dirty
    finally:
        tick.close()
    rate = handled / max(seconds, 1e-9)
    out["grid"] = {"scene": args.skinned, "points": int(bake.stats["points_kept"]), "skinned_points": skinned,
                   "density": density, "handled": handled, "seconds": seconds, "points_per_s": rate,
                   "written_per_tick": written / args.grid_ticks, "cells_dirty_per_tick": dirty / args.grid_ticks}
    print(f"grid stage, {args.skinned}: {bake.stats['points_kept']:,} points ({skinned:,} skinned), {handled:,} traced "
          f"AO thresholded and written in {args.grid_ticks} ticks, {1e3 * seconds / args.grid_ticks:.2f} ms per tick "
          f"({1e9 * seconds / max(handled, 1):.1f} ns per traced point); {written / args.grid_ticks:,.0f} AO written "
          f"and {dirty / args.grid_ticks:,.0f} cells dirtied per tick")
    v.check(f"traced points through the grid stage per second ({args.skinned})", rate, ">=",
            TARGETS["grid_points_per_s"])


# -------------------------------------------------------------------------------------------- rate
def part_rate(args, v: Verdicts, out: dict) -> None:
    from psao.scene import SceneError, load_scene

    from benchmarks.served import serve_and_watch
    from psao.server.tick.summary import view_wait_quantile

    cases = [(scene, density) for name, scene, density in RATE_CASES if name in args.rate_scenes]
    if "skinned" in args.rate_scenes:
        if Path(args.skinned).exists():
            cases.append((args.skinned, density_for(load_scene(args.skinned), args.skinned_points)))
        else:
            print(f"skinned model {args.skinned} not found: its row is skipped")
    rows = []
    for scene, density in cases:
        try:
            load_scene(scene)  # (the lab needs ../shared/scenes)
        except SceneError as exc:
            print(f"  {scene}: skipped ({exc})", flush=True)
            continue
        dens = ["--density", f"{density:g}"] if density is not None else []
        label = f"{scene} N={density:g}" if density is not None else f"{Path(scene).name} (default density)"
        run = serve_and_watch(scene, ["--animate", *dens, "--rays", str(args.serve_rays), "--tick-hz", "60"],
                              args.seconds)
        row = {"scene": scene, "density": density, "ticks_per_s": run.ticks_per_second,
               "bytes_per_s": run.bytes_per_second, "traced_mean": run.mean("traced"),
               "queue_mean": run.mean("queue"),
               # over the ticks that traced (a tick that pooled its trace into the next has no budget of its own)
               "budget_used_mean": run.mean("budget_used", among="budget_ms"),
               "tick_ms_mean": 1e3 * run.mean("seconds_tick"), "first_snapshot_s": run.first_snapshot_s,
               "prepare_cpu_ms_mean": 1e3 * run.mean("cpu_prepare"),
               "mirror_cells": run.client.get("mirror_cells"),
               **{f"{st}_ms_mean": 1e3 * run.mean(f"seconds_{st}") for st in ("animate", "select", "trace", "grid", "encode")}}
        waits = run.view_waits()
        first_q, last_q = run.thirds("queue")
        on_stream = [r.get("shared_members", 0) >= r.get("clients", 0) for r in run.records if r.get("clients")]
        row.update(view_waits=int(sum(waits)), view_wait_p50_ms=view_wait_quantile(waits, 0.5),
                   view_wait_p95_ms=view_wait_quantile(waits, 0.95), queue_first_third=first_q,
                   queue_last_third=last_q,
                   client_updates_per_s=run.client["updates_per_s"],  # first Update to latest (psao client --json)
                   client_on_shared_stream=sum(on_stream) / max(len(on_stream), 1))
        rows.append(row)
        print(f"  {label}: in-view points waited {row['view_wait_p50_ms']:g} ms (p50) and "
              f"{row['view_wait_p95_ms']:g} ms (p95, bin edges) from their reset to their first re-trace "
              f"({row['view_waits']:,} points); queue {first_q:.0f} -> {last_q:.0f} (first and last third of the "
              f"window); the client received {row['client_updates_per_s']:.1f} Updates/s and was on the shared "
              f"stream {100 * row['client_on_shared_stream']:.0f}% of the ticks", flush=True)
        print(f"  {label}: {row['ticks_per_s']:.1f} ticks/s, {8 * row['bytes_per_s'] / 1e6:.2f} Mbit/s "
              f"({row['bytes_per_s'] / max(row['ticks_per_s'], 1e-9):,.0f} B/tick), traced/tick "
              f"{row['traced_mean']:.0f}, queue {row['queue_mean']:.0f}, budget used {100 * row['budget_used_mean']:.0f}%, "
              f"tick {row['tick_ms_mean']:.1f} ms (animate {row['animate_ms_mean']:.1f}, select {row['select_ms_mean']:.1f}, "
              f"trace {row['trace_ms_mean']:.1f}, grid {row['grid_ms_mean']:.1f}; encode {row['encode_ms_mean']:.1f}; "
              f"CPU of the preparing thread {row['prepare_cpu_ms_mean']:.1f})",
              flush=True)
        v.check(f"{label} ticks per second of psao serve --animate --tick-hz 60 with a client",
                row["ticks_per_s"], ">=", TARGETS["ticks_per_s"])
        v.check(f"{label} p95 wait of in-view points from reset to first re-trace, ms (bin edge)",
                row["view_wait_p95_ms"] if row["view_waits"] else float("nan"), "<=", TARGETS["view_wait_p95_ms"])
        v.check(f"{label} queue over the last third of the window / over the first (+{QUEUE_SLACK} "
                "points)", last_q / (first_q + QUEUE_SLACK), "<=", TARGETS["queue_growth"])
        v.check(f"{label} Updates a second one client received", row["client_updates_per_s"], ">=",
                TARGETS["client_updates_per_s"])
    out["rate"] = rows


# ----------------------------------------------------------------------------------------- quality
def part_quality(args, v: Verdicts, out: dict) -> None:
    rows = {}
    for name in args.quality_scenes:
        rows[name] = quality_scene(name, args)
        r = rows[name]
        w, h = args.frame_size
        print(f"  {name} N={args.quality_density:g}: frames ({w}x{h}, against {args.frame_spp}-spp RTAO, its noise taken "
              f"out): mean PSNR while moving budgeted {r['frames_moving_budgeted_db']:.2f} dB, unbudgeted "
              f"{r['frames_moving_unbudgeted_db']:.2f} dB; 1 s after motion stops {r['frames_rest_budgeted_db']:.2f} vs "
              f"{r['frames_rest_unbudgeted_db']:.2f} dB", flush=True)
        print(f"    points the motion reaches (in view, against {args.ref_rays}-ray traces; the loss where it is, not "
              f"judged): budgeted {r['moving_budgeted_db']:.2f} dB, unbudgeted {r['moving_unbudgeted_db']:.2f} dB while "
              f"moving (loss {r['moving_unbudgeted_db'] - r['moving_budgeted_db']:.2f} dB); 1 s after the stop "
              f"{r['rest_budgeted_db']:.2f} vs {r['rest_unbudgeted_db']:.2f} dB", flush=True)
        m = r["budgeted_ticks_moving"]
        print(f"    budgeted tick while moving: {r['ticks_per_s']:.1f} ticks/s, {m['traced']:.0f} points traced a tick "
              f"({m['exact']:.0f} whole from static hits first, {m['batch']:.0f} picked by the rounds), budget {m['budget_ms']:.1f} ms, "
              f"select {1e3 * m['seconds_select']:.1f} ms, trace {1e3 * m['seconds_trace']:.1f} ms, tick "
              f"{1e3 * m['seconds_total']:.1f} ms, {r['service_ms']:.1f} ms left to the service (a served run's); "
              f"median budget used {100 * r['budget_used_median']:.0f}% (ticks that traced), "
              f"ticks longer than the period {100 * r['late_share']:.0f}%")
        for kind, e in r["error_split_moving"].items():
            print(f"    {kind:30s} {e['points_per_sample']:7.0f} points in view per sample, squared error "
                  f"{e['mse_budgeted']:.2e} budgeted, {e['mse_unbudgeted']:.2e} unbudgeted (mean over all points)")
        if args.fixed_rays:  # a study at a set number of rays a tick, not the real-time target
            print(f"    (--fixed-rays {args.fixed_rays:g}: frames' loss while moving "
                  f"{r['frames_moving_unbudgeted_db'] - r['frames_moving_budgeted_db']:.2f} dB, 1 s after the stop "
                  f"{r['frames_rest_unbudgeted_db'] - r['frames_rest_budgeted_db']:.3f} dB; not judged)")
            continue
        v.check(f"{name} mean PSNR loss of frames while moving, budgeted 60 Hz vs unbudgeted, dB",
                r["frames_moving_unbudgeted_db"] - r["frames_moving_budgeted_db"], "<=", TARGETS["moving_loss_db"])
        v.check(f"{name} PSNR loss of frames 1 s after motion stops, dB",
                r["frames_rest_unbudgeted_db"] - r["frames_rest_budgeted_db"], "<=", TARGETS["rest_loss_db"])
    out["quality"] = rows
    _chart_quality(rows, args.out / "quality_over_time.png", args)


def served_service_s(name: str, args) -> float:
    """Seconds a tick that a real `psao serve --animate` of the scene at the quality part's density and rays,
    with a real client, left its service besides the tick's stages (the median of TickStats.service_ms over
    --service-seconds): the room its automatic budget took off the period for the fan-out and messages."""
    from benchmarks.served import serve_and_watch

    run = serve_and_watch(f"builtin:{name}", ["--animate", "--density", f"{args.quality_density:g}", "--rays",
                                              str(args.quality_rays), "--tick-hz", "60"], args.service_seconds)
    return 1e-3 * float(np.median([r["service_ms"] for r in run.records])) if run.records else 0.0


def quality_scene(name: str, args) -> dict:
    """Run the budgeted tick in real time (scene time = wall time, as the service does) over --move-s of
    motion then --rest-s with the scene held still, its automatic budget leaving the service the room a
    served run of the scene measured (served_service_s: so it traces what a served tick would), sampling the
    stored AO of a fixed random set of the points the motion can reach (near_motion: elsewhere both ticks
    keep the bake's AO) and the grid a client would draw (grid_state); then the unbudgeted tick at the same
    scene times, with the points' reference traced right after each sampled tick; then the frames of both
    (frame_psnrs)."""
    import copy

    from psao.client.connection import scene_camera_feed
    from psao.scene import load_scene
    from psao.server.bake import BakeResult, bake_scene
    from psao.server.settings import BakeSettings, TickSettings, TraceSettings
    from psao.server.tick.selection import camera_planes, in_any_view
    from psao.server.tick.server_tick import ServerTick

    service_s = served_service_s(name, args) if args.service_seconds > 0 and not args.fixed_rays else 0.0
    scene = load_scene(f"builtin:{name}")
    # made once: making a feed takes the scene's bounds (milliseconds), which inside the real-time loop would
    # take the tick's period as a served tick's camera (set by its client) does not
    camera = scene_camera_feed(scene)
    bake = bake_scene(scene, BakeSettings(density=args.quality_density, rays=args.quality_rays, workers=args.workers),
                      show_progress=False)
    bake.tracer.close()
    twin = BakeResult(scene, copy.deepcopy(bake.grid), bake.pointsets, bake.stats, None)
    rng = np.random.default_rng(1)
    sample = np.sort(rng.choice(near_motion(bake, args.move_s), args.sample_points, replace=True))
    sample = np.unique(sample)

    def stored(tick):
        ok = tick.present()[sample]
        codes = np.full(len(sample), -1.0)
        ids = sample[ok]
        codes[ok] = (tick.grid.cells[tick.slot[ids], tick.index[ids]] & 0xFF) / 255.0
        return codes

    tick_hz = 60.0
    period = 1.0 / tick_hz
    budgeted = ServerTick(bake, TickSettings(rays=args.quality_rays, workers=args.workers,
                                             budget=BudgetSettings(round_rays=args.round_rays,
                                                                   exact_share=args.exact_share,
                                                                   rays_per_tick=args.fixed_rays)),
                          tick_hz=tick_hz)
    times, samples_b, states_b, tick_times, sampled_ticks, kinds, stats = [], [], [], [], [], [], []
    try:
        start = time.perf_counter()
        k = 0
        # real time: scene time = wall time; --fixed-rays: scene time k / 60 s, as fast as the ticks go
        clock = (lambda: k * period) if args.fixed_rays else (lambda: time.perf_counter() - start)
        while (wall := clock()) < args.move_s + args.rest_s:
            t = min(wall, args.move_s)  # the scene stops moving at move_s
            budgeted.set_cameras([camera(t)])
            budgeted.observe_service(service_s)  # (constant: the budget takes the median of what it is told)
            stats.append(budgeted(budgeted.grid, t))
            budgeted.grid.take_dirty()
            tick_times.append(t)
            if wall >= len(times) * args.sample_s:  # sampled by wall time: a slow machine still gets its samples
                times.append((wall, t))
                sampled_ticks.append(k)
                samples_b.append(stored(budgeted))
                states_b.append(grid_state(budgeted))
                kinds.append(point_kinds(budgeted, sample))
            k += 1
            if not args.fixed_rays:
                time.sleep(max(0.0, start + k * period - time.perf_counter()))
        ticks_per_s = k / (time.perf_counter() - start)
    finally:
        budgeted.close()
    def reference(tick, t):
        """Each sampled point in the camera's view traced with many rays in the tick's last frame (at t:
        skinned points stand where that tick put them)."""
        frame = tick.last_frame
        here = tick.present()[sample]
        pos, _ = tick.world_points(frame, sample[here])
        seen = np.zeros(len(sample), bool)
        seen[here] = in_any_view(pos, [camera_planes(*camera(t), 0.0)], 0.0)
        tick.pose_tracer(frame)
        ref = np.full(len(sample), -1.0)
        sel = np.flatnonzero(seen)
        p2, n2 = tick.world_points(frame, sample[sel])
        ref[sel] = tick.tracer.visibility(p2, n2, sample[sel], TraceSettings(
            rays=args.ref_rays, ao_distance=scene.ao_distance, seed=12345))
        return ref, seen

    unbudgeted = ServerTick(twin, TickSettings(rays=args.quality_rays, workers=args.workers))
    samples_u, states_u, refs, views = [], [], [], []
    try:
        for k, t in enumerate(tick_times):  # every tick the budgeted one ran, at the same scene times
            unbudgeted.set_cameras([camera(t)])
            unbudgeted(unbudgeted.grid, t)
            unbudgeted.grid.take_dirty()
            if k in sampled_ticks:
                samples_u.append(stored(unbudgeted))
                states_u.append(grid_state(unbudgeted))
                ref, seen = reference(unbudgeted, t)  # now: the skinned points are where they are at t
                refs.append(ref)
                views.append(seen)
    finally:
        unbudgeted.close()

    def psnr(a, ref, seen):
        # a sample with only a few of the points in view (the camera looking away from the motion) has no
        # PSNR: a handful of exact points would count as 120 dB in both means
        ok = seen & (a >= 0)
        if ok.sum() < MIN_SAMPLED:
            return float("nan")
        return 10 * np.log10(1.0 / max(float(np.mean((a[ok] - ref[ok]) ** 2)), 1e-12))

    pb = [psnr(a, r, s) for a, r, s in zip(samples_b, refs, views)]
    moving_k = [k for k, (w, _) in enumerate(times) if w < args.move_s]
    split = error_split([samples_b[k] for k in moving_k], [samples_u[k] for k in moving_k], [refs[k] for k in moving_k],
                        [views[k] for k in moving_k], [kinds[k] for k in moving_k])
    pu = [psnr(a, r, s) for a, r, s in zip(samples_u, refs, views)]
    walls = np.array([w for w, _ in times])
    moving = walls < args.move_s
    rest = np.flatnonzero(walls >= args.move_s + 1.0)
    at_rest = int(rest[0]) if len(rest) else len(walls) - 1
    drawn = np.flatnonzero(moving | (np.arange(len(walls)) == at_rest))  # (the frames the verdicts read)
    fb, fu = frame_psnrs(scene, camera, [t for _, t in times], budgeted.grid.instances, states_b, states_u, drawn,
                         args, picture=args.out / f"quality_frames_{name}.png")
    moving_stats = [st for st, w in zip(stats, tick_times) if w < args.move_s]
    tracing = [st for st in moving_stats if st.budget_ms > 0]  # (not the ticks that pooled their trace into the next)
    return {"ticks_per_s": ticks_per_s, "service_ms": 1e3 * service_s, "wall_s": walls.tolist(),
            "psnr_budgeted": pb, "psnr_unbudgeted": pu,
            "budgeted_ticks_moving": {f: float(np.mean([getattr(st, f) for st in moving_stats]))
                                      for f in TICK_FIELDS} if moving_stats else {},
            # (means above: a few long ticks weigh in them; these say how the ticks held the budget and the period)
            "budget_used_median": float(np.median([st.budget_used for st in tracing])) if tracing else 0.0,
            "late_share": float(np.mean([st.seconds_total > period for st in moving_stats])) if moving_stats else 0.0,
            "error_split_moving": split,
            "frames_budgeted": fb, "frames_unbudgeted": fu,
            "frames_moving_budgeted_db": float(np.nanmean(np.array(fb)[moving])),
            "frames_moving_unbudgeted_db": float(np.nanmean(np.array(fu)[moving])),
            "frames_rest_budgeted_db": fb[at_rest], "frames_rest_unbudgeted_db": fu[at_rest],
            "moving_budgeted_db": float(np.nanmean(np.array(pb)[moving])),
            "moving_unbudgeted_db": float(np.nanmean(np.array(pu)[moving])),
            "rest_budgeted_db": pb[at_rest], "rest_unbudgeted_db": pu[at_rest]}


MIN_SAMPLED = 100  # sampled points in view below which a sample has no PSNR


TICK_FIELDS = ("traced", "exact", "batch", "budget_ms", "seconds_select", "seconds_trace", "seconds_total")


POINT_KINDS = ("mover", "static, reset, no ray since", "static, refining", "static, whole")


def grid_state(tick) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a client in lockstep with `tick` would draw now: copies of its grid's buckets and cells and of
    its instance transforms."""
    return tick.grid.buckets.copy(), tick.grid.cells.copy(), np.array(tick.transforms(), np.float64)


def debiased_psnr(test: np.ndarray, ref: np.ndarray, spp: int) -> float:
    """PSNR (dB) of the AO image `test` against the truth that the reference image `ref` (each pixel the
    mean of `spp` independent rays' visibility) estimates: the squared error against `ref` less the
    reference's own noise, the unbiased estimate sum(ref (1 - ref)) / (spp - 1) of its variance. Left in,
    that noise adds the same error to every image scored against `ref` and shrinks the gap between them."""
    err = float(np.mean((np.asarray(test, np.float64) - ref) ** 2))
    noise = float(np.mean(ref * (1.0 - ref))) / max(spp - 1, 1)
    return float(min(PSNR_CAP, 10 * np.log10(1.0 / max(err - noise, 1e-12))))


def frame_psnrs(scene, camera, scene_times: list, instances, states_b: list, states_u: list, drawn: np.ndarray,
                args, picture: Path | None = None) -> tuple[list, list]:
    """Per sample, the debiased PSNR (debiased_psnr) of the frame a client would draw from the budgeted and
    from the unbudgeted tick's grid (grid_state) at that sample's scene time, with the camera the ticks
    were given, against one RTAO reference frame of --frame-spp rays a pixel; NaN for samples not in
    `drawn` (the frames are drawn after the real-time run, which they would slow down). `picture`: a PNG of
    the drawn sample whose budgeted frame lost most, beside the unbudgeted one, the reference and their
    difference."""
    from types import SimpleNamespace

    from psao.eval.quality import FramePose, QualityRenderer, reference_images
    from psao.eval.reference import ReferenceSettings

    poses = [FramePose(int(k), float(scene_times[k]), *camera(float(scene_times[k]))) for k in drawn]
    grid_of = lambda state: SimpleNamespace(instances=instances, buckets=state[0], cells=state[1])  # noqa: E731
    with QualityRenderer(scene, args.frame_size, methods=("psao",)) as renderer:
        frames = {}
        for name, states in (("budgeted", states_b), ("unbudgeted", states_u)):
            frames[name] = renderer.render(grid_of(states[drawn[0]]), poses, timing_repeats=1,
                                           before_frame=lambda pose: (grid_of(states[pose.index]), states[pose.index][2]))
    refs = reference_images(scene, frames["budgeted"], ReferenceSettings(spp=args.frame_spp, workers=args.workers,
                                                                         cache_dir=None), show_progress=False)
    out = {name: [float("nan")] * len(scene_times) for name in frames}
    for name, rendered in frames.items():
        for f, ref in zip(rendered, refs):
            out[name][f.pose.index] = debiased_psnr(f.ao["psao"], ref, args.frame_spp)
    if picture is not None:
        worst = int(np.argmax([out["unbudgeted"][k] - out["budgeted"][k] for k in drawn]))
        _picture_frames(picture, frames["budgeted"][worst], frames["unbudgeted"][worst], refs[worst], out)
    return out["budgeted"], out["unbudgeted"]


def _picture_frames(path: Path, budgeted, unbudgeted, ref: np.ndarray, psnrs: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = budgeted.pose.index
    diff = np.abs(budgeted.ao["psao"] - unbudgeted.ao["psao"])
    top = max(float(np.percentile(diff, 99.5)), 1e-3)  # (a few pixels at the largest would leave the rest black)
    panels = [(budgeted.ao["psao"], f"budgeted 60 Hz, {psnrs['budgeted'][k]:.2f} dB", "gray"),
              (unbudgeted.ao["psao"], f"unbudgeted, {psnrs['unbudgeted'][k]:.2f} dB", "gray"),
              (ref, "RTAO reference", "gray"),
              (diff, f"|budgeted - unbudgeted|, black 0 to white {top:.3f} (max {diff.max():.3f})", "magma")]
    fig, axes = plt.subplots(1, 4, figsize=(16, 2.8))
    for ax, (img, title, cmap) in zip(axes, panels):
        ax.imshow(img, cmap=cmap, vmin=0.0, vmax=1.0 if cmap == "gray" else top)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(f"scene time {budgeted.pose.time:.2f} s: the sample whose budgeted frame lost most", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def point_kinds(tick, ids: np.ndarray) -> np.ndarray:
    """Per id, its index in POINT_KINDS in the budgeted tick now: a moving instance's point; a static
    point whose history was reset with no fresh ray since; one holding some of its rays; one holding all."""
    q = tick.queue
    return np.where(tick.moving_point[ids], 0,
                    np.where(q.done[ids] < q.slices, np.where(q.rays[ids] == 0, 1, 2), 3))


def error_split(budgeted, unbudgeted, refs, views, kinds) -> dict:
    """Per POINT_KINDS entry, over the given samples: sampled points in view (per sample) and their
    squared error against the reference as a mean over all such points, budgeted and unbudgeted (each
    kind's part of the PSNR's mean squared error)."""
    out = {}
    count = sum(int((s & (b >= 0) & (u >= 0)).sum()) for b, u, s in zip(budgeted, unbudgeted, views))
    for k, name in enumerate(POINT_KINDS):
        n, eb, eu = 0, 0.0, 0.0
        for b, u, r, s, kind in zip(budgeted, unbudgeted, refs, views, kinds):
            m = s & (b >= 0) & (u >= 0) & (kind == k)
            n += int(m.sum())
            eb += float(((b[m] - r[m]) ** 2).sum())
            eu += float(((u[m] - r[m]) ** 2).sum())
        out[name] = {"points_per_sample": n / max(len(views), 1), "mse_budgeted": eb / max(count, 1),
                     "mse_unbudgeted": eu / max(count, 1)}
    return out


def near_motion(bake, seconds: float) -> np.ndarray:
    """Ids of the points the motion can reach in [0, seconds]: points of moving instances, and static
    points within the AO distance of a moving instance's bounds at some time (every 1/30 s)."""
    from psao.server.tick.animate import SceneAnimator
    from psao.server.geometry import to_world
    from psao.server.tick.selection import expand

    anim = SceneAnimator(bake.scene)
    sizes = [len(p) for p in bake.pointsets]
    first = np.concatenate([[0], np.cumsum(sizes)])
    ids = [np.arange(first[i], first[i + 1]) for i in anim.kinds.moving]
    boxes = [expand(b, bake.scene.ao_distance) for t in np.arange(0.0, seconds + 1e-9, 1 / 30)
             for b in anim.frame(float(t)).bounds.values()]
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    for i in anim.kinds.static:
        inst = bake.scene.instances[i]
        pos, _ = to_world(inst.transform, bake.pointsets[i].positions, bake.pointsets[i].normals)
        maybe = np.flatnonzero(np.all((pos >= lo) & (pos <= hi), axis=1))
        hit = np.zeros(len(maybe), bool)
        for b in boxes:
            hit |= np.all((pos[maybe] >= b[0]) & (pos[maybe] <= b[1]), axis=1)
        ids.append(first[i] + maybe[hit])
    return np.concatenate(ids)


def _chart_quality(rows: dict, path: Path, args) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(rows), figsize=(6 * len(rows), 8), squeeze=False)
    w, h = args.frame_size
    measures = (("frames", "frames", f"PSNR vs {args.frame_spp}-spp RTAO, dB"),
                ("psnr", "points the motion reaches", f"PSNR vs {args.ref_rays}-ray traces, dB"))
    for col, (name, r) in enumerate(rows.items()):
        for row, (key, what, label) in enumerate(measures):
            ax = axes[row][col]
            keep = np.isfinite(np.array(r[f"{key}_unbudgeted"], float))
            walls = np.array(r["wall_s"])[keep]
            ax.plot(walls, np.array(r[f"{key}_unbudgeted"])[keep], ".-", label="unbudgeted (time not counted)")
            ax.plot(walls, np.array(r[f"{key}_budgeted"])[keep], ".-",
                    label=f"budgeted, {args.fixed_rays:g} rays a tick at 60 Hz scene time" if args.fixed_rays
                    else f"budgeted, 60 Hz asked ({r['ticks_per_s']:.0f} achieved)")
            ax.axvline(args.move_s, color="k", ls="--", lw=1, label="motion stops")
            ax.set(title=f"{name} N={args.quality_density:g}: {what}" + (f" ({w}x{h}, judged)" if key == "frames" else ""),
                   xlabel="seconds", ylabel=label)
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--workers", type=int, default=0, help="tracer processes (0: all cores)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tracer-density", type=float, default=256.0)
    ap.add_argument("--bake-points", type=int, default=200_000)
    ap.add_argument("--bake-rays", type=int, default=64)
    ap.add_argument("--tick-points", default="6000,20000")
    ap.add_argument("--tick-rays", type=int, default=32)
    ap.add_argument("--skinned", default=SKINNED)
    ap.add_argument("--skinned-points", type=float, default=50_000)
    ap.add_argument("--grid-ticks", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=10.0, help="measured window of each served run")
    ap.add_argument("--serve-rays", type=int, default=32, help="--rays of the served runs (bake and tick target)")
    rate_names = [name for name, _, _ in RATE_CASES] + ["skinned"]
    ap.add_argument("--rate-scenes", default=",".join(rate_names),
                    help=f"comma list of the rate part's served runs ({', '.join(rate_names)})")
    ap.add_argument("--quality-scenes", default=",".join(QUALITY_SCENES),
                    help=f"comma list of the quality part's built-in scenes ({', '.join(QUALITY_SCENES)})")
    ap.add_argument("--quality-density", type=float, default=64.0)
    ap.add_argument("--quality-rays", type=int, default=32)
    ap.add_argument("--round-rays", type=int, default=8)
    ap.add_argument("--exact-share", type=float, default=BudgetSettings.exact_share,
                    help="quality part: the budgeted tick's BudgetSettings.exact_share (share of the trace budget "
                         "for whole traces of static points from their static hits; 0: none)")
    ap.add_argument("--fixed-rays", type=float, default=0.0,
                    help="quality part: instead of real time, tick at scene time k / 60 s with this many rays a tick "
                         "(BudgetSettings.rays_per_tick): the loss at a given tracing throughput, whatever the load "
                         "(reported, not judged)")
    ap.add_argument("--service-seconds", type=float, default=5.0,
                    help="quality part: seconds of a served run of each scene measuring the room its budget leaves "
                         "the service a tick, which the in-process budgeted tick then leaves too (0: none)")
    ap.add_argument("--ref-rays", type=int, default=256)
    ap.add_argument("--frame-size", default="192x108", help="quality part: WxH of the frames scored (16:9, the "
                    "camera's aspect)")
    ap.add_argument("--frame-spp", type=int, default=512, help="quality part: rays a pixel of the RTAO reference frames")
    ap.add_argument("--sample-points", type=int, default=20000)
    ap.add_argument("--sample-s", type=float, default=0.25, help="seconds between samples")
    ap.add_argument("--move-s", type=float, default=4.0)
    ap.add_argument("--rest-s", type=float, default=2.0)
    ap.add_argument("--out", type=Path, default=Path("out/bench_realtime"))
    args = ap.parse_args(argv)
    if not 0 <= args.exact_share <= 1:
        ap.error(f"--exact-share must be within [0, 1], got {args.exact_share}")
    if not (np.isfinite(args.service_seconds) and args.service_seconds >= 0):
        ap.error(f"--service-seconds must be a number >= 0, got {args.service_seconds}")
    if not (np.isfinite(args.fixed_rays) and args.fixed_rays >= 0):
        ap.error(f"--fixed-rays must be a number >= 0, got {args.fixed_rays}")
    from psao.client.errors import RenderError
    from psao.client.render.output import parse_size
    try:
        args.frame_size = parse_size(args.frame_size)
    except RenderError as exc:
        ap.error(f"--frame-size: {exc}")
    if min(args.frame_size) < 8:
        ap.error("--frame-size must be WxH, each at least 8 pixels")
    if args.frame_spp < 2:
        ap.error(f"--frame-spp must be at least 2, got {args.frame_spp}")
    args.tick_points = [int(x) for x in args.tick_points.split(",") if x]
    args.rate_scenes = [x.strip() for x in args.rate_scenes.split(",") if x.strip()]
    args.quality_scenes = [x.strip() for x in args.quality_scenes.split(",") if x.strip()]
    if any(x not in QUALITY_SCENES for x in args.quality_scenes):
        ap.error(f"--quality-scenes: choose from {', '.join(QUALITY_SCENES)}")
    if any(x not in rate_names for x in args.rate_scenes):
        ap.error(f"--rate-scenes: choose from {', '.join(rate_names)}")
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if any(p not in PARTS for p in parts):
        ap.error(f"--parts: choose from {', '.join(PARTS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    import os
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; Warp CUDA tracer: not measured here")
    v = Verdicts("bench_realtime")
    out: dict = {}
    for part in parts:
        print(f"--- {part}", flush=True)
        globals()[f"part_{part}"](args, v, out)
        (args.out / "bench_realtime.json").write_text(json.dumps(out, indent=1, default=float))
    print(f"wrote {args.out / 'bench_realtime.json'}")
    return v.exit_code()


if __name__ == "__main__":
    raise SystemExit(main())
