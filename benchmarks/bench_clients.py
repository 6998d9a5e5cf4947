"""Many clients on one server: `python -m benchmarks.bench_clients [--counts 1,10,30,100]`.

A real `psao serve builtin:courtyard --animate` process (N=64 by default); clients are the project's own
MirrorClient (protocol code, real websockets on loopback) in one separate process (`--client-host`),
each sending its camera at 30 Hz along the scene's camera path, shifted in time so the clients look
in different directions. The clients join in stages (1, then 10, 30, 100 in all); at each stage, once
every client has its snapshot, a window of `--seconds` is measured: the server's ticks/s (its own
--stats-json), updates/s per client, server CPU (share of one core) and RSS. Memory per extra client is
the RSS growth from the 1-client stage divided by the clients added. Mirrors: each client checks its
digest against the server's digest log (`--digest-log`) wherever both exist.

Verdicts: 10 clients >= 0.8x and 30 clients >= 0.6x the 1-client tick rate; every client of the last
stage has its snapshot within 60 s of joining; RSS per extra client <= 4 MB; every compared digest equal.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.verdicts import Verdicts

ROOT = Path(__file__).resolve().parents[1]


def proc_stats(pid: int) -> tuple[float, int]:
    """(CPU seconds user+system, RSS bytes) of a process."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    with open(f"/proc/{pid}/statm") as f:
        rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    return cpu, rss


# ------------------------------------------------------------------------------------------ client host
async def client_host(url: str, scene_spec: str, counts: list[int], digest_dir: Path, control: Path) -> None:
    """Run MirrorClients, adding them stage by stage when `control` says so; report per stage on stdout."""
    from protocol.session import scene_hash_bytes
    from psao_client.connection import MirrorClient, scene_camera_feed
    from psao_scene import load_scene

    scene = load_scene(scene_spec)
    feed = scene_camera_feed(scene)
    clients: list[MirrorClient] = []
    tasks = []
    joined: list[float] = []
    def said() -> tuple[int, bool]:  # the driver writes "S" (start stage S) and "Sm" (stage S measured)
        text = control.read_text().strip() if control.exists() else ""
        return (int(text.rstrip("m")), text.endswith("m")) if text.rstrip("m").isdigit() else (-1, False)

    for stage, n in enumerate(counts):
        while said()[0] < stage:
            await asyncio.sleep(0.1)
        for k in range(len(clients), n):
            shift = 7.3 * k  # seconds along the camera path: clients look different ways
            c = MirrorClient(url, scene_hash_bytes(scene.content_hash()), camera=lambda t, s=shift: feed(t + s),
                             digest_log=digest_dir / f"c{k}.jsonl", reconnect_timeout=60.0)
            clients.append(c)
            joined.append(time.perf_counter())
            tasks.append(asyncio.create_task(c.run()))
        while not all(c.stats.snapshot_seconds is not None for c in clients):
            if any(t.done() for t in tasks):
                raise RuntimeError(f"a client ended: {[t.exception() for t in tasks if t.done()][0]}")
            await asyncio.sleep(0.1)
        snap = max(c.stats.snapshot_seconds for c in clients[-(n - (counts[stage - 1] if stage else 0)):])
        print(json.dumps({"stage": stage, "clients": n, "ready": True, "snapshot_s_max": snap,
                          "updates": [c.stats.updates for c in clients]}), flush=True)
        while said() < (stage, True):
            await asyncio.sleep(0.05)
        print(json.dumps({"stage": stage, "clients": n, "measured": True,
                          "updates": [c.stats.updates for c in clients]}), flush=True)
    for c in clients:
        c.stop()
    await asyncio.gather(*tasks, return_exceptions=True)


# ------------------------------------------------------------------------------------------ driver
def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass  # a line being written
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_clients", description=__doc__.splitlines()[0])
    p.add_argument("--counts", default="1,10,30,100")
    p.add_argument("--density", type=float, default=64.0)
    p.add_argument("--seconds", type=float, default=10.0, help="measured window per stage")
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--client-host", nargs=4, metavar=("URL", "SCENE", "COUNTS", "DIR"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.client_host:
        url, scene, counts, d = args.client_host
        asyncio.run(client_host(url, scene, [int(c) for c in counts.split(",")], Path(d), Path(d) / "control"))
        return 0
    counts = [int(c) for c in args.counts.split(",")]
    work = Path(tempfile.mkdtemp(prefix="bench_clients_"))
    stats, slog = work / "stats.jsonl", work / "server_digests.jsonl"
    server = subprocess.Popen([sys.executable, "-m", "psao", "serve", args.scene, "--animate", "--density",
                               str(args.density), "--port", "0", "--max-clients", str(max(counts) + 8),
                               "--stats-json", str(stats), "--digest-log", str(slog)],
                              cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    import re

    port = None
    while port is None:
        line = server.stderr.readline()
        if not line and server.poll() is not None:
            print("bench_clients: error: psao serve exited", file=sys.stderr)
            return 2
        if m := re.search(r"listening on ws://[^:]+:(\d+)", line):
            port = int(m.group(1))
    # drain the server's log so it never blocks on a full pipe
    log_lines: list[str] = []
    import threading

    threading.Thread(target=lambda: log_lines.extend(iter(server.stderr.readline, "")), daemon=True).start()
    control = work / "control"
    control.write_text("0")
    host = subprocess.Popen([sys.executable, "-m", "benchmarks.bench_clients", "--client-host",
                             f"ws://127.0.0.1:{port}", args.scene, args.counts, str(work)],
                            cwd=ROOT, stdout=subprocess.PIPE, text=True)
    rows = []
    try:
        for stage, n in enumerate(counts):
            control.write_text(str(stage))
            line = host.stdout.readline()
            if not line:  # the client host ended (its error is on stderr): judge what was measured
                print(f"bench_clients: the client process ended during the {n}-client stage", flush=True)
                rows.append({"clients": n, "ticks_per_s": 0.0, "updates_per_s_per_client": 0.0, "server_cpu": 0.0,
                             "server_rss_mb": proc_stats(server.pid)[1] / 2**20, "snapshot_s_max": float("inf")})
                break
            ready = json.loads(line)
            t0 = time.time()
            recs0 = read_jsonl(stats)
            cpu0, _ = proc_stats(server.pid)
            time.sleep(args.seconds)
            recs1 = read_jsonl(stats)
            cpu1, rss = proc_stats(server.pid)
            wall = time.time() - t0
            control.write_text(f"{stage}m")
            measured = json.loads(host.stdout.readline())
            a, b = recs0[-1], recs1[-1]
            ticks = (b["service_tick"] - a["service_tick"]) / max(b["time"] - a["time"], 1e-9)
            ups = [(u1 - u0) / wall for u0, u1 in zip(ready["updates"], measured["updates"])]
            rows.append({"clients": n, "ticks_per_s": ticks, "updates_per_s_per_client": sum(ups) / len(ups),
                         "server_cpu": (cpu1 - cpu0) / wall, "server_rss_mb": rss / 2**20,
                         "snapshot_s_max": ready["snapshot_s_max"]})
            print(f"{n:4d} clients: {ticks:6.1f} ticks/s, {rows[-1]['updates_per_s_per_client']:5.1f} updates/s per "
                  f"client, server CPU {100 * rows[-1]['server_cpu']:.0f}% of a core, RSS {rss / 2**20:.0f} MB, "
                  f"slowest snapshot {ready['snapshot_s_max']:.1f} s", flush=True)
    finally:
        control.write_text(f"{len(counts)}m")
        try:
            host.wait(60)
        except subprocess.TimeoutExpired:
            host.kill()
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(60)
        except subprocess.TimeoutExpired:
            server.kill()
    # mirrors: every (connection, message) both logged must agree
    ours = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(slog)}
    compared = differ = 0
    for f in work.glob("c*.jsonl"):
        for d in read_jsonl(f):
            if (d["conn"], d["seq"]) in ours:
                compared += 1
                differ += ours[d["conn"], d["seq"]] != d["digest"]
    print(f"mirror digests compared: {compared}, different: {differ}")
    traceback = any("Traceback" in line for line in log_lines)
    v = Verdicts("bench_clients")
    base = rows[0]
    for r in rows[1:]:
        target = {10: 0.8, 30: 0.6}.get(r["clients"])
        if target:
            v.check(f"{r['clients']} clients / 1 client tick rate", r["ticks_per_s"] / base["ticks_per_s"], ">=", target)
    last = rows[-1]
    v.check(f"slowest snapshot of the {last['clients']}-client stage (s)", last["snapshot_s_max"], "<=", 60)
    if len(rows) > 1:
        per = (last["server_rss_mb"] - base["server_rss_mb"]) / (last["clients"] - base["clients"])
        v.check("server RSS per extra client (MB)", per, "<=", 4)
    v.check("mirror digests compared", compared, ">=", 1)
    v.check("mirror digests different", differ, "<=", 0)
    v.check("tracebacks in the server log", int(traceback), "<=", 0)
    (work / "table.json").write_text(json.dumps(rows, indent=1))
    print(f"table: {work / 'table.json'}")
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
