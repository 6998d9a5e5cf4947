"""Progressive start, the default of `psao serve`, against `psao serve --no-progressive` (whole bake first).

For each scene (the courtyard at N=256, and Sponza from ../shared/scenes at its default density when it is
there), in one run, each server a real `psao serve` process with a real client (in this process) that
connects as soon as the server listens and sends its camera:
  - seconds from process start to the client's complete first snapshot (target: <= 3 s), and to the full
    grid's snapshot after the coarse grid was replaced;
  - the error of what the client shows over time: the AO its mirror reconstructs (paper eq. 2-4, the oracle
    its shader equals, tests/test_render_psao.py) at random surface probes that are not buried, against AO
    traced at the probes with --ref-rays rays, as PSNR (AO in 0..1), at each mark (seconds since process
    start) for the progressive server and from its first snapshot on for the plain one;
  - across the swap to the full grid: PSNR of the mirror the client shows just before the full grid's
    snapshot completes and at it (the client keeps showing the coarse mirror until then: no empty frame);
  - the web page in a headless chromium (psao.eval.browser), opened as soon as the server listens: seconds
    from process start to its first drawn PSAO frame (target: <= 3 s);
  - with --animate: Updates the client receives in the first seconds after its first snapshot (the movers
    are posed and traced on the coarse grid from its first tick);
  - a chart of PSNR against seconds since start per scene (run time against error).

    .venv/bin/python -m benchmarks.bench_progressive [--scenes courtyard,sponza] [--rays 128] [--skip-page]
        [--marks 1,2,3,5,10,20,30] [--out out/bench_progressive]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import signal
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.eval.processes import ServeExited, ServerProcess

TARGET_FIRST_SNAPSHOT_S = 3.0
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
# name -> (scene, psao serve options of both servers besides --rays)
SCENES = {"courtyard": ("builtin:courtyard", ["--density", "256"]),
          "sponza": (str(SHARED / "sponza" / "sponza_s_lod4.glb"), [])}
ANIMATED_SECONDS = 2.0  # Updates counted over this long after the first snapshot of an --animate server
MIN_ANIMATED_UPDATES_S = 10.0  # and at least this many a second (the tick runs at 60 Hz)


def reference(scene, probes: int, rays: int, workers: int):
    """Visible probes and their AO traced with `rays` rays."""
    from psao.server.bake import sample_probes
    from psao.server.geometry import scene_center, scene_world_geometry
    from psao.server.points.buried import visible_probes
    from psao.server.tracer import TraceSettings, make_tracer

    p = visible_probes(scene, sample_probes(scene, probes))
    tracer = make_tracer("embree", scene_center(scene), workers=workers)
    try:
        tracer.set_static(*scene_world_geometry(scene))
        truth = tracer.visibility(p.world_pos, p.world_normal, np.arange(len(p.instance)) + (1 << 30),
                                  TraceSettings(rays=rays, ao_distance=scene.ao_distance, seed=4242))
    finally:
        tracer.close()
    return p, truth


def psnr(state: dict, probes, truth: np.ndarray) -> float:
    """PSNR (dB) of the AO reconstructed from a mirror's arrays at the probes against `truth`."""
    from psao.protocol.reconstruct import reconstruct_ao

    ao, _ = reconstruct_ao(state["instances"], state["buckets"], state["cells"], probes.instance, probes.local_pos,
                           probes.local_normal)
    mse = float(np.mean((np.asarray(ao, np.float64) - truth) ** 2))
    return 10.0 * np.log10(1.0 / max(mse, 1e-12))


def watch(spec: str, scene, serve_args: list[str], marks: list[float], until_snapshots: int, hang_s: float,
          linger_s: float = 0.0) -> dict:
    """Start `psao serve SPEC ... --port 0` and connect a client as soon as it listens. Returns the seconds
    since process start of every complete snapshot and of every Update, a copy of the mirror the client
    shows (its last complete snapshot and the updates since) at each mark and just before each new
    snapshot replaces it; ends after the last mark, `until_snapshots` complete snapshots and `linger_s`
    seconds after the first one."""
    from psao.protocol.session import scene_hash_bytes
    from psao.client.connection import MirrorClient, scene_camera_feed
    from psao.client.errors import ConnectError

    server = ServerProcess(spec, serve_args, start_timeout=None, host=None, log_stdout=False, until_full_grid=False,
                           stop_signal=signal.SIGINT, stop_grace=120.0)
    try:
        server.start()
    except ServeExited as exc:
        raise RuntimeError(f"psao serve {' '.join(serve_args)} exited:\n" + exc.log) from None
    started, port, listening_s = server.started, server.port, server.listen_s
    shown: dict = {"mirror": None}
    result: dict = {"listening_s": listening_s, "snapshots_s": [], "snapshot_cells": [], "captured": {},
                    "at_snapshots": [], "before_snapshots": [], "updates_s": []}

    def copy(mirror) -> dict:
        return {k: np.array(getattr(mirror, k), copy=True) for k in ("instances", "buckets", "cells")}

    def on_snapshot(mirror):
        result["before_snapshots"].append(copy(shown["mirror"]) if shown["mirror"] is not None else None)
        result["snapshots_s"].append(time.perf_counter() - started)
        result["snapshot_cells"].append(int(mirror.allocated_cells()))
        result["at_snapshots"].append(copy(mirror))
        shown["mirror"] = mirror  # a new connection's mirror is shown once its snapshot is complete

    def on_update(mirror, transforms, tick):
        result["updates_s"].append(time.perf_counter() - started)

    client = MirrorClient(f"ws://127.0.0.1:{port}", scene_hash_bytes(scene.content_hash()),
                          camera=scene_camera_feed(scene), on_snapshot=on_snapshot, on_update=on_update)

    async def run():
        task = asyncio.create_task(client.run())
        pending = sorted(marks)
        while not task.done():
            now = time.perf_counter() - started
            while pending and now >= pending[0]:
                mark = pending.pop(0)
                result["captured"][mark] = copy(shown["mirror"]) if shown["mirror"] is not None else None
            lingered = bool(result["snapshots_s"]) and now >= result["snapshots_s"][0] + linger_s
            if (not pending and len(result["snapshots_s"]) >= until_snapshots and lingered) or now > hang_s:
                break
            await asyncio.sleep(0.02)
        client.stop()
        try:
            await asyncio.wait_for(task, 30)
        except (ConnectError, asyncio.TimeoutError):  # the connection dropping as the client stops is not a result
            pass
        if shown["mirror"] is not None:
            result["final"] = copy(shown["mirror"])

    try:
        asyncio.run(run())
    finally:
        server.close()  # SIGINT, up to 120 s to stop, then its process group is killed
    result["log"] = server.log()
    result["grid_replacements"] = client.stats.grid_replacements
    return result


def page_first_frame(spec: str, serve_args: list[str], hang_s: float) -> dict:
    """Start `psao serve SPEC ... --port 0` with a headless chromium already running, open the web page as
    soon as the server listens, and return the seconds since process start to the page's first drawn PSAO
    frame (the page streaming, its frame counter at 1), by the page's own clock at the end of that frame (its
    pixels read back): the script notices the frame later, when the busy page answers its poll."""
    from psao.eval.browser import launched

    with launched() as browser:
        page = browser.new_page(viewport={"width": 680, "height": 400})
        server = ServerProcess(spec, serve_args, start_timeout=None, log_stdout=False, until_full_grid=False,
                               stop_signal=signal.SIGINT, stop_grace=120.0)
        try:
            server.start()
            page.goto(f"http://127.0.0.1:{server.port}/")
            page.wait_for_function("window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1",
                                   timeout=hang_s * 1e3, polling=20)
            seen_s = time.perf_counter() - server.started
            # how long ago the page drew it, by its own clock; counted back from after the answer came (an
            # upper bound: the page read its clock before that)
            ago_ms = page.evaluate("() => performance.now() - window.psao.timings.firstDraw")
            drawn_s = time.perf_counter() - server.started - ago_ms / 1e3
            return {"page_first_frame_s": drawn_s, "page_first_frame_seen_s": seen_s, "page_listening_s": server.listen_s}
        finally:
            server.close()


def chart(r: dict, name: str, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    pts = sorted([(m, v) for m, v in r["progressive_psnr_at_s"].items() if v is not None]
                 + list(zip(r["progressive_snapshots_s"], r["progressive_psnr_at_snapshots"])))
    # what the client shows holds until the next sample: a step at each snapshot and mark
    ax.step([m for m, _ in pts], [v for _, v in pts], "-", where="post", color="C0")
    ax.plot([m for m, _ in pts], [v for _, v in pts], "o", color="C0", label="psao serve, progressive (client's view)")
    full_s, full_db = r["plain_first_snapshot_s"], r["full_bake_psnr_db"]
    end = max([x for x in (full_s, *r["progressive_psnr_at_s"]) if np.isfinite(x)]) * 1.05
    if np.isfinite(full_s):
        ax.plot([full_s, end], [full_db, full_db], "r-", lw=2, label=f"--no-progressive: full {r['rays']}-ray bake")
        ax.axvline(full_s, color="r", ls="--", label=f"--no-progressive first snapshot {full_s:.1f} s")
    ax.axvline(r["progressive_first_snapshot_s"], color="g", ls=":",
               label=f"progressive first snapshot {r['progressive_first_snapshot_s']:.2f} s")
    if r.get("progressive_full_grid_s"):
        ax.axvline(r["progressive_full_grid_s"], color="b", ls=":",
                   label=f"progressive full grid {r['progressive_full_grid_s']:.1f} s")
    ax.set(xlabel="seconds since psao serve started", ylabel=f"PSNR vs {r['ref_rays']}-ray AO at probes, dB",
           title=f"{name}: run time against error", xlim=(0, end))
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_scene(name: str, args, marks: list[float], v: Verdicts) -> dict:
    """Both servers (and the animated one) on one scene: the figures, the chart and the verdicts."""
    from psao.scene import load_scene
    from psao.server.tick.animate import classify_instances

    spec, options = SCENES[name]
    scene = load_scene(spec)
    probes, truth = reference(scene, args.probes, args.ref_rays, args.workers)
    print(f"{name}: reference {len(truth):,} visible probes x {args.ref_rays} rays", flush=True)
    common = [*options, "--rays", str(args.rays)]
    prog = watch(spec, scene, common, marks, 2, args.hang_s)
    at = {m: (psnr(s, probes, truth) if s is not None else None) for m, s in prog["captured"].items()}
    snaps = prog["snapshots_s"]
    r = {"scene": name, "rays": args.rays, "ref_rays": args.ref_rays, "probes": int(len(truth)),
         "progressive_listening_s": prog["listening_s"],
         "progressive_first_snapshot_s": snaps[0] if snaps else float("nan"),
         "progressive_full_grid_s": snaps[1] if len(snaps) > 1 else None,
         "progressive_snapshot_cells": prog["snapshot_cells"], "grid_replacements": prog["grid_replacements"],
         "progressive_psnr_at_s": at, "progressive_snapshots_s": snaps,
         "progressive_psnr_at_snapshots": [psnr(st, probes, truth) for st in prog["at_snapshots"]],
         "progressive_psnr_before_snapshots": [psnr(st, probes, truth) if st is not None else None
                                               for st in prog["before_snapshots"]]}
    print(f"{name} progressive: listening {prog['listening_s']:.2f} s, first snapshot "
          f"{r['progressive_first_snapshot_s']:.2f} s ({prog['snapshot_cells'][0] if snaps else 0:,} cells), full grid "
          f"{r['progressive_full_grid_s'] or float('nan'):.1f} s after start; PSNR at each snapshot "
          + ", ".join(f"{db:.2f} dB" for db in r["progressive_psnr_at_snapshots"]), flush=True)
    live = [ln for ln in prog["log"].splitlines() if "ticks/s" in ln]
    if live:  # the server's own live statistics near the end: how fast it refined
        print(f"{name} progressive server, last live line: " + live[-1].split("psao serve: ", 1)[-1], flush=True)
    if args.skip_plain:
        r.update(plain_first_snapshot_s=float("nan"), full_bake_psnr_db=float("nan"))
    else:
        plain = watch(spec, scene, ["--no-progressive", *common], [], 1, args.hang_s)
        r.update(plain_first_snapshot_s=plain["snapshots_s"][0] if plain["snapshots_s"] else float("nan"),
                 full_bake_psnr_db=psnr(plain["final"], probes, truth) if "final" in plain else float("nan"))
    print(f"\n{name}, --rays {args.rays}: PSNR of the client's view vs {args.ref_rays}-ray AO at {len(truth):,} probes")
    print("| seconds since start | progressive (default) | --no-progressive (full bake first) |\n|---:|---:|---:|")
    for m in marks:
        plain_db = r["full_bake_psnr_db"] if m >= r["plain_first_snapshot_s"] else None
        print(f"| {m:g} | {'%.2f dB' % at[m] if at[m] is not None else 'no snapshot yet'} | "
              f"{'%.2f dB' % plain_db if plain_db is not None else 'no snapshot yet'} |")
    print(f"--no-progressive: first snapshot {r['plain_first_snapshot_s']:.1f} s after start, "
          f"{r['full_bake_psnr_db']:.2f} dB from then on")
    chart(r, name, args.out / f"progressive_start_{name}.png")
    print(f"chart: {args.out / f'progressive_start_{name}.png'}")
    v.check(f"{name} psao serve: seconds from start to the client's first snapshot", r["progressive_first_snapshot_s"],
            "<=", TARGET_FIRST_SNAPSHOT_S)
    v.record(f"{name}: the coarse grid was replaced by the full grid while the client watched",
             prog["grid_replacements"] == 1 and len(snaps) >= 2 and prog["snapshot_cells"][0] < prog["snapshot_cells"][1],
             f"{prog['grid_replacements']} replacements, cells per snapshot {prog['snapshot_cells']}")
    if len(snaps) >= 2 and r["progressive_psnr_before_snapshots"][1] is not None:
        before, after = r["progressive_psnr_before_snapshots"][1], r["progressive_psnr_at_snapshots"][1]
        r["swap_psnr_change_db"] = after - before
        print(f"{name} across the swap: {before:.2f} dB just before the full grid's snapshot, {after:.2f} dB at it")
        v.check(f"{name}: PSNR of the client's view at the full grid's snapshot minus just before it, dB (no drop "
                "across the swap)", after - before, ">=", -args.swap_tolerance_db)
    # the run ends after the last mark and the full grid's snapshot: what the client shows then against its
    # first snapshot (a mark may fall before the full grid arrives on a slow machine)
    r["progressive_psnr_at_end_db"] = psnr(prog["final"], probes, truth) if "final" in prog else float("nan")
    first = r["progressive_psnr_at_snapshots"][0] if r["progressive_psnr_at_snapshots"] else float("nan")
    print(f"{name} progressive at the end of its run: {r['progressive_psnr_at_end_db']:.2f} dB (first snapshot "
          f"{first:.2f} dB)")
    v.check(f"{name}: PSNR of the client's view at the end of the progressive run minus at its first snapshot, dB "
            "(the full grid and its refinement improve it)", r["progressive_psnr_at_end_db"] - first, ">", 0.0)
    if not args.skip_page:
        from psao.eval.browser import missing_browser

        why = missing_browser()
        if why:
            print(f"{name}: the page is not measured: {why}", flush=True)
        else:
            r.update(page_first_frame(spec, common, args.hang_s))
            print(f"{name} web page: first drawn PSAO frame {r['page_first_frame_s']:.2f} s after psao serve started",
                  flush=True)
            v.check(f"{name} psao serve: seconds from start to the web page's first drawn frame",
                    r["page_first_frame_s"], "<=", TARGET_FIRST_SNAPSHOT_S)
    if classify_instances(scene).moving:
        moving = watch(spec, scene, ["--animate", *common], [], 1, args.hang_s, linger_s=ANIMATED_SECONDS)
        first_s = moving["snapshots_s"][0] if moving["snapshots_s"] else float("nan")
        early = [u for u in moving["updates_s"] if first_s <= u <= first_s + ANIMATED_SECONDS]
        r.update(animated_first_snapshot_s=first_s, animated_updates_early=len(early),
                 animated_first_update_s=moving["updates_s"][0] if moving["updates_s"] else float("nan"))
        print(f"{name} --animate: first snapshot {first_s:.2f} s after start, first Update "
              f"{r['animated_first_update_s']:.2f} s, {len(early)} Updates in the {ANIMATED_SECONDS:g} s after the first "
              "snapshot", flush=True)
        v.check(f"{name} psao serve --animate: Updates a second in the {ANIMATED_SECONDS:g} s after the first "
                "snapshot (the coarse grid is live)", len(early) / ANIMATED_SECONDS, ">=", MIN_ANIMATED_UPDATES_S)
        v.check(f"{name} psao serve --animate: seconds from start to the client's first snapshot", first_s, "<=",
                TARGET_FIRST_SNAPSHOT_S)
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="courtyard,sponza", help=f"comma list of {', '.join(SCENES)} (Sponza: skipped "
                    "when ../shared/scenes lacks it)")
    ap.add_argument("--rays", type=int, default=128, help="--rays of both servers (the full bake's rays)")
    ap.add_argument("--marks", default="1,2,3,5,10,20,30", help="seconds since start at which the client's view is scored")
    ap.add_argument("--probes", type=int, default=20000)
    ap.add_argument("--ref-rays", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=0, help="tracer processes of the reference (0: all cores)")
    ap.add_argument("--hang-s", type=float, default=400.0, help="give up on a server after this many seconds")
    ap.add_argument("--swap-tolerance-db", type=float, default=1.0,
                    help="the PSNR the client's view may lose across the swap to the full grid")
    ap.add_argument("--skip-page", action="store_true", help="no web page in chromium")
    ap.add_argument("--skip-plain", action="store_true", help="only the progressive server (no --no-progressive baseline)")
    ap.add_argument("--out", type=Path, default=Path("out/bench_progressive"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    marks = sorted(float(x) for x in args.marks.split(",") if x)
    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        ap.error(f"--scenes: unknown {', '.join(unknown)} (known: {', '.join(SCENES)})")
    v = Verdicts("bench_progressive")
    results = {}
    for name in names:
        if SCENES[name][0].endswith(".glb") and not Path(SCENES[name][0]).is_file():
            print(f"{name}: {SCENES[name][0]} is not there: skipped", flush=True)
            continue
        results[name] = run_scene(name, args, marks, v)
    (args.out / "progressive.json").write_text(json.dumps(results, indent=1))
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
