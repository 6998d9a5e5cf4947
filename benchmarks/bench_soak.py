"""Soak: `python -m benchmarks.bench_soak [--minutes 10] [--clients 10]`.

A real `psao serve builtin:courtyard --animate` process (N=16 by default) and `--clients` MirrorClients
(protocol code and a mirror, no renderer) in one client process, each sending its camera at 30 Hz along
the scene's camera path. For `--minutes`, each client in turn, at random moments (on average every
`--event-seconds`), is dropped (its task cancelled mid-stream) and comes back, says Bye and comes back,
or reads slowly for a while (`--slow-delay` seconds per message); and every `--host-kill-seconds` the
whole client process is killed with SIGKILL and started again. The server's RSS is sampled every
second.

Verdicts: every mirror digest the clients logged that the server also logged (`--digest-log`) is equal,
and there are some; the server's RSS at the end is within 10% of its RSS after the warm-up (the first
`--warmup` share of the run; median of the last minute against the median of the minute after the
warm-up, or a fifth of the run when that is shorter); no traceback in the server's log; a fresh client still gets its snapshot at the end.
Output: `--out`/rss.png (RSS over time) and soak.json.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_clients import proc_stats
from benchmarks.verdicts import Verdicts
from psao.eval.digests import compare_digests
from psao.eval.processes import ServeExited, ServerProcess

ROOT = Path(__file__).resolve().parents[1]


async def soak_host(url: str, scene_spec: str, clients: int, digest_dir: Path, seed: int, event_s: float,
                    slow_delay: float, generation: int) -> None:
    """Run `clients` slots forever; each slot's client is dropped, leaves or reads slowly at random."""
    from psao.protocol.session import scene_hash_bytes
    from psao.client.connection import MirrorClient, scene_camera_feed
    from psao.scene import load_scene

    scene = load_scene(scene_spec)
    feed = scene_camera_feed(scene)
    hash_ = scene_hash_bytes(scene.content_hash())
    rng = random.Random(seed * 1000 + generation)

    async def slot(k: int) -> None:
        while True:
            c = MirrorClient(url, hash_, camera=lambda t, s=7.3 * k: feed(t + s), reconnect_timeout=60.0,
                             digest_log=digest_dir / f"s{k}.jsonl", digest_every=4)
            task = asyncio.create_task(c.run())
            await asyncio.sleep(rng.expovariate(1.0 / event_s))
            what = rng.choice(("dropped", "bye", "slow"))
            if what == "slow":
                c.read_delay = slow_delay
                await asyncio.sleep(rng.expovariate(1.0 / event_s))
                c.read_delay = 0.0
                await asyncio.sleep(rng.expovariate(1.0 / event_s))
                c.stop()
            elif what == "bye":
                c.stop()
            else:
                task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    await asyncio.gather(*(slot(k) for k in range(clients)))


def start_host(args, url: str, work: Path, generation: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "benchmarks.bench_soak", "--host", url, str(work), str(generation),
                             "--scene", args.scene, "--clients", str(args.clients), "--seed", str(args.seed),
                             "--event-seconds", str(args.event_seconds), "--slow-delay", str(args.slow_delay)],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


async def fresh_snapshot(url: str, scene_spec: str, timeout: float) -> bool:
    from psao.protocol.session import scene_hash_bytes
    from psao.client.connection import MirrorClient
    from psao.scene import load_scene

    c = MirrorClient(url, scene_hash_bytes(load_scene(scene_spec).content_hash()), reconnect=False)
    task = asyncio.create_task(c.run())
    t0 = time.perf_counter()
    while c.stats.snapshot_seconds is None and not task.done() and time.perf_counter() - t0 < timeout:
        await asyncio.sleep(0.1)
    ok = c.stats.snapshot_seconds is not None
    c.stop()
    await asyncio.gather(task, return_exceptions=True)
    return ok


def median_between(samples: list[tuple[float, float]], t0: float, t1: float) -> float:
    vals = [r for t, r in samples if t0 <= t <= t1]
    return float(np.median(vals)) if vals else float("nan")


def chart(samples: list[tuple[float, float]], warm: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot([t / 60 for t, _ in samples], [r / 2**20 for _, r in samples])
    ax.axvline(warm / 60, color="grey", ls="--", label="end of warm-up")
    ax.set_xlabel("minutes")
    ax.set_ylabel("server RSS (MB)")
    ax.set_title("psao serve under kills, reconnects and slow readers")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_soak", description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--clients", type=int, default=10)
    p.add_argument("--density", type=float, default=16.0)
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--event-seconds", type=float, default=8.0, help="mean seconds between a client's events")
    p.add_argument("--slow-delay", type=float, default=0.3, help="seconds a slow reader waits after each message")
    p.add_argument("--host-kill-seconds", type=float, default=60.0, help="seconds between SIGKILLs of the client process")
    p.add_argument("--warmup", type=float, default=0.25, help="share of the run before RSS counts")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("out") / "bench_soak")
    p.add_argument("--host", nargs=3, metavar=("URL", "DIR", "GENERATION"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.host:
        url, d, gen = args.host
        asyncio.run(soak_host(url, args.scene, args.clients, Path(d), args.seed, args.event_seconds, args.slow_delay,
                              int(gen)))
        return 0
    if not (args.minutes > 0 and args.clients >= 1 and args.event_seconds > 0 and 0 < args.warmup < 1):
        print("bench_soak: error: --minutes, --clients, --event-seconds must be > 0 and --warmup within (0, 1)",
              file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_soak_"))
    slog = work / "server_digests.jsonl"
    server = ServerProcess(args.scene, ["--animate", "--density", str(args.density), "--digest-log", str(slog)],
                           start_timeout=None, host=None, log_stdout=False, cwd=ROOT, stop_signal=signal.SIGTERM,
                           stop_grace=60.0)
    try:
        server.start()
    except ServeExited as exc:
        print("bench_soak: error: psao serve exited:\n" + "".join(exc.log.splitlines(keepends=True)[-10:]),
              file=sys.stderr)
        return 2
    port = server.port
    url = f"ws://127.0.0.1:{port}"
    duration = 60.0 * args.minutes
    generation = 0
    host = start_host(args, url, work, generation)
    samples: list[tuple[float, float]] = []
    t0 = next_kill = time.perf_counter()
    next_kill += args.host_kill_seconds
    kills = 0
    fresh = False
    try:
        while (now := time.perf_counter()) - t0 < duration:
            samples.append((now - t0, float(proc_stats(server.pid)[1])))
            if now >= next_kill:
                host.send_signal(signal.SIGKILL)
                host.wait(30)
                kills += 1
                generation += 1
                host = start_host(args, url, work, generation)
                next_kill = now + args.host_kill_seconds
            if len(samples) % 60 == 0:
                print(f"{(now - t0) / 60:5.1f} min: server RSS {samples[-1][1] / 2**20:.0f} MB, "
                      f"{kills} client process kills", flush=True)
            time.sleep(1.0)
        host.send_signal(signal.SIGKILL)
        host.wait(30)
        fresh = asyncio.run(fresh_snapshot(url, args.scene, timeout=300.0))
    finally:
        if host.poll() is None:
            host.kill()
        server.close()
    log_lines = server.log().splitlines(keepends=True)  # in a file: the server never blocks on a full pipe
    compared, differ, conns = compare_digests(slog, work.glob("s*.jsonl"))
    warm = args.warmup * duration
    span = min(60.0, 0.2 * duration)
    after_warm = median_between(samples, warm, warm + span)
    end = median_between(samples, duration - span, duration)
    growth = (end - after_warm) / after_warm
    tracebacks = sum("Traceback" in line for line in log_lines)
    chart(samples, warm, args.out / "rss.png")
    summary = {"minutes": args.minutes, "clients": args.clients, "client_process_kills": kills,
               "connections_compared": len(conns), "digests_compared": compared, "digests_different": differ,
               "rss_after_warmup_mb": after_warm / 2**20, "rss_end_mb": end / 2**20, "rss_growth": growth,
               "tracebacks": tracebacks, "fresh_client_snapshot": fresh}
    (args.out / "soak.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary))
    print(f"chart: {args.out / 'rss.png'}")
    v = Verdicts("bench_soak")
    v.check(f"{args.minutes:g} min, {args.clients} clients: mirror digests compared", compared, ">=", 1)
    v.check("mirror digests different", differ, "<=", 0)
    v.check("server RSS growth after warm-up", growth, "<", 0.10)
    v.check("tracebacks in the server log", tracebacks, "<=", 0)
    v.record("a fresh client gets its snapshot at the end", fresh)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
