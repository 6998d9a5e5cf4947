"""Many clients on one server: `python -m benchmarks.bench_clients [--counts 1,10,30,100]`; one client
keeping up at 60 Hz: `python -m benchmarks.bench_clients --rate`.

A real `psao serve builtin:courtyard --animate` process (N=64 by default); clients are the project's own
MirrorClient (protocol code and a mirror, no renderer; real websockets on loopback), `--per-process` of
them in each client process (`--client-host`; the clients fill the processes in order, each process started
at the first stage that has one of its clients, so a stage runs as few processes as its clients need: every
process costs CPU of its own on the server's machine), each
sending its camera at 30 Hz along the scene's camera path, shifted in time so the clients look in
different directions. The clients join in stages
(1, then 10, 30, 100 in all); at each stage, once every client has its snapshot, a window of `--seconds`
is measured: the server's ticks/s (its own --stats-json), updates/s per client, clients on the shared
stream, server CPU (its process and its tracer processes, share of one core; per extra client, its growth from the 1-client stage over the
clients added) and RSS. Memory per extra client is the RSS growth from the 1-client stage divided by the
clients added. The client processes run at a lower CPU priority (nice CLIENT_NICE): in a deployment the
clients run on other machines, so here they stand in for remote machines and take only the CPU the
server leaves; whether every client keeps up is checked (it stays connected, the slowest client's
updates/s is at least KEEP_UP of the server's ticks/s, an Update folding the ticks a client was not sent,
and when the window ends the slowest client's mirror holds a tick at most MAX_LAG_S seconds older than
the server's latest). Mirrors: each client logs the digest of a message the server logged one for
(ServerDigests), for each connection's first such message and then, per client process, at most one
every DIGEST_GAP_S (`--digest-every k`: also every k-th message), and the driver checks them against the
server's digest log (`--digest-log`) wherever both exist (the server logs a digest after a message that
leaves nothing pending for that client: with culling, a client whose view leaves cells behind has none;
`--no-cull` sends every change). Output: `--out`/table.md, table.json, clients.png and server.log.

Verdicts: 10 clients >= 0.8x and 30 clients >= 0.6x the 1-client tick rate; at every stage every client
keeps up (all connected through the window, no reconnect, slowest updates/s >= KEEP_UP x ticks/s, slowest
mirror at most MAX_LAG_S behind); every
client of the last stage has its snapshot within 60 s of joining; RSS per extra client <= 4 MB; every
compared digest equal, and at the end (every client turned to a camera that sees the whole scene, so
that nothing stays pending for it) a digest of every client of the last stage compared.

ONE CLIENT (`--rate [--updates 600] [--no-cull] [--no-camera]`): a real `psao serve builtin:courtyard
--density 256 --tick-hz 60 --animate --stats-json` and, once it serves the full grid, one MirrorClient in
this process sending its camera at 30 Hz along the scene's camera path, as a headless `psao client` does.
After RATE_WARM_UPDATES Updates it counts `--updates` more, each stamped with the server tick it carries:
the window's server ticks (last tick - first tick) are the baseline measured in the same run, so a verdict
is Updates received per tick served (an Update that folds ticks counts once). The server's --stats-json says
per tick how many clients are on the shared stream: the share of the window's ticks with this client on it
is reported, and the client's CPU (this process) as a share of one core. Exactness, on a second server with
--digest-log (its digests cost it a whole-grid copy and sha256 per tick that leaves nothing pending, which
would slow the first run): the client digests a message the server logged a digest for, at most one every
DIGEST_GAP_S, and at the end, with a camera that sees the whole scene, until one more came; every compared
digest must equal the server's. Verdicts: updates/s >= RATE_UPDATES_S, updates per server tick >=
RATE_UPDATES_S / RATE_TICK_HZ, on the shared stream for RATE_ON_STREAM of the window's ticks, no reconnect,
at least one digest compared and none different.
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

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.eval.digests import compare_digests, read_jsonl
from psao.eval.processes import LISTEN_RE, ServeExited, ServerProcess

ROOT = Path(__file__).resolve().parents[1]
CLIENT_NICE = 10  # client processes' nice value: below the server (0), above other niced work on the machine
KEEP_UP = 0.5  # the slowest client's updates/s over the server's ticks/s: at least every other tick's changes
MAX_LAG_S = 2.0  # seconds of scene time the slowest client's mirror may trail the server's latest tick
FINAL_S = 60.0  # seconds the clients have, at the end, to be sent an Update after which nothing is pending
DIGEST_GAP_S = 2.0  # seconds between the mirror digests one client process works out (after each connection's first)
SERVER_DIGESTS = "server_digests.jsonl"  # in the run's folder: the server's --digest-log
RATE_TICK_HZ = 60.0  # --rate: the server's tick rate
RATE_UPDATES_S = 55.0  # --rate: Updates a second the client receives at that tick rate
RATE_ON_STREAM = 0.95  # --rate: share of the window's server ticks with the client on the shared stream
RATE_WARM_UPDATES = 120  # --rate: Updates after the snapshot before the window starts
RATE_START_S = 900.0  # --rate: seconds for the server to bake and serve the full grid
RATE_DENSITY = 256.0  # --rate: the grid density without --density


class ServerDigests:
    """The (connection, message) pairs the server logged a state digest for, read from its log as it grows.
    The server writes a message's line before it sends the message, so when a client has a message, its
    line (if any) is in the file. A digest hashes the whole mirror (~25 MB at N=64, ~40 ms of a client
    process's CPU): clients work one out only for messages the server vouches for, and not for each of
    those (client_host's `vouched`), as that left the co-located client processes too little CPU."""

    def __init__(self, path: Path):
        self.path = path
        self.logged: set[tuple[int, int]] = set()
        self._file = None
        self._offset = 0

    def __call__(self, conn: int, seq: int) -> bool:
        if self._file is None and self.path.exists():
            self._file = open(self.path, "rb")
        if (conn, seq) not in self.logged and self._file is not None:
            self._file.seek(self._offset)
            data = self._file.read()
            whole = data[: data.rfind(b"\n") + 1]  # a line being written is read next time
            self._offset += len(whole)
            for line in whole.splitlines():
                d = json.loads(line)
                self.logged.add((d["conn"], d["seq"]))
        return (conn, seq) in self.logged


def proc_stats(pid: int) -> tuple[float, int]:
    """(CPU seconds user+system, RSS bytes) of a process."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    with open(f"/proc/{pid}/statm") as f:
        rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    return cpu, rss


def tree_cpu(pid: int) -> float:
    """CPU seconds of a process and its children (the server's tracer worker processes)."""
    total = proc_stats(pid)[0]
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid:
                total += proc_stats(int(stat.parent.name))[0]
        except (OSError, ValueError, IndexError):
            pass  # a process that ended meanwhile
    return total


# ------------------------------------------------------------------------------------------ client host
async def client_host(url: str, scene_spec: str, counts: list[int], digest_dir: Path, control: Path, host: int,
                      per_host: int, digest_every: int) -> None:
    """Run the MirrorClients k with k // per_host == host, adding them stage by stage when `control` says so;
    report per stage on stdout, from the first stage that has one of them (the driver starts the process
    then). Runs at a lower CPU priority than the server (CLIENT_NICE)."""
    os.nice(CLIENT_NICE)
    from psao.protocol.session import scene_hash_bytes
    from psao.client.connection import MirrorClient, scene_camera_feed
    from psao.scene import load_scene

    scene = load_scene(scene_spec)
    feed = scene_camera_feed(scene)
    server_vouched = ServerDigests(digest_dir / SERVER_DIGESTS)
    digested_conns: set[int] = set()
    last_digest = [-float("inf")]

    def vouched(conn: int, seq: int) -> bool:
        """A message the server logged a digest for: each connection's first, then one per host every
        DIGEST_GAP_S (a digest costs as much CPU as dozens of Updates)."""
        if not server_vouched(conn, seq):
            return False
        now = time.perf_counter()
        if conn in digested_conns and now - last_digest[0] < DIGEST_GAP_S and (
                overview[0] is None or conn in final_conns):
            return False
        digested_conns.add(conn)
        last_digest[0] = now
        if overview[0] is not None:
            final_conns.add(conn)
        return True

    overview: list = [None]  # at the end: a camera that sees the whole scene, for every client
    final_conns: set[int] = set()  # connections whose mirror was digested after that
    clients: list[MirrorClient] = []
    tasks = []

    def said() -> tuple[int, bool]:  # the driver writes "S" (start stage S) and "Sm" (stage S measured)
        text = control.read_text().strip() if control.exists() else ""
        return (int(text.rstrip("m")), text.endswith("m")) if text.rstrip("m").isdigit() else (-1, False)

    for stage, n in enumerate(counts):
        if n <= host * per_host:  # none of this process's clients yet: it was not started for this stage
            continue
        while said()[0] < stage:
            await asyncio.sleep(0.1)
        new = []
        for k in range(counts[stage - 1] if stage else 0, n):
            if k // per_host != host:
                continue
            shift = 7.3 * k  # seconds along the camera path: clients look different ways
            c = MirrorClient(url, scene_hash_bytes(scene.content_hash()),
                             camera=lambda t, s=shift: overview[0] or feed(t + s),
                             digest_log=digest_dir / f"c{k}.jsonl", reconnect_timeout=60.0, open_timeout=30.0,
                             digest_if=(lambda conn, seq: seq % digest_every == 0 or vouched(conn, seq))
                             if digest_every else vouched)
            clients.append(c)
            new.append(c)
            tasks.append(asyncio.create_task(c.run()))
        while not all(c.stats.snapshot_seconds is not None for c in clients):
            if any(t.done() for t in tasks):
                raise RuntimeError(f"a client ended: {[t.exception() for t in tasks if t.done()][0]}")
            await asyncio.sleep(0.1)
        snap = max((c.stats.snapshot_seconds for c in new), default=0.0)
        print(json.dumps({"stage": stage, "clients": n, "ready": True, "snapshot_s_max": snap, "at": time.monotonic(),
                          "updates": [c.stats.updates for c in clients],
                          "reconnects": [c.stats.reconnects for c in clients]}), flush=True)
        while said() < (stage, True):
            await asyncio.sleep(0.05)
        print(json.dumps({"stage": stage, "clients": n, "measured": True, "at": time.monotonic(),
                          "updates": [c.stats.updates for c in clients],
                          "reconnects": [c.stats.reconnects for c in clients],
                          "ticks": [c.mirror.tick if c.mirror is not None else -1 for c in clients]}), flush=True)
    # Every client now looks at the whole scene, so an Update leaves nothing pending for it (whatever its
    # view kept back) and the server vouches for its mirror: each one's digest is compared once more.
    overview[0] = overview_camera(scene)
    end = time.perf_counter() + FINAL_S
    while time.perf_counter() < end and not all(c.stats.connection_id in final_conns for c in clients):
        await asyncio.sleep(0.1)
    print(json.dumps({"final": True, "digested": [c.stats.connection_id in final_conns for c in clients],
                      "conns": [c.stats.connection_id for c in clients]}), flush=True)
    for c in clients:
        c.stop()
    await asyncio.gather(*tasks, return_exceptions=True)


def overview_camera(scene) -> tuple[np.ndarray, np.ndarray]:
    """(view, projection) that sees the whole scene: its bounding sphere inside a 60 degree frustum."""
    from psao.scene.camera import look_at, perspective

    lo, hi = (np.asarray(b, np.float64) for b in scene.world_bounds())
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2 + 1e-3
    eye = centre + 3.0 * radius * np.array([0.3, 0.6, 1.0]) / np.linalg.norm([0.3, 0.6, 1.0])
    return (look_at(eye, centre).astype(np.float32),
            perspective(60.0, 16 / 9, 0.01 * radius, 10.0 * radius).astype(np.float32))


# ------------------------------------------------------------------------------------------ driver
def host_lines(hosts: list[subprocess.Popen]) -> dict | None:
    """One JSON line from every client host, merged (updates in host order); None when one has ended."""
    parts = []
    for h in hosts:
        line = h.stdout.readline()
        if not line:
            return None
        parts.append(json.loads(line))
    return {"updates": [u for p in parts for u in p["updates"]],
            "reconnects": [r for p in parts for r in p["reconnects"]],
            "ticks": [t for p in parts for t in p.get("ticks", [])],
            "at": [p["at"] for p in parts for _ in p["updates"]],  # when its host counted each client's updates
            "snapshot_s_max": max(p.get("snapshot_s_max", 0.0) for p in parts)}


def chart(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["clients"] for r in rows]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    ax[0].plot(n, [r["ticks_per_s"] for r in rows], "o-", label="server ticks/s")
    ax[0].plot(n, [r["updates_per_s_per_client"] for r in rows], "s--", label="updates/s per client")
    ax[0].set_ylabel("per second")
    ax[1].plot(n, [100 * r["server_cpu"] for r in rows], "o-", label="server CPU (% of a core)")
    ax[1].plot(n, [100 * r["clients_cpu"] for r in rows], "s--", label="client processes CPU (% of a core)")
    ax[2].plot(n, [r["server_rss_mb"] for r in rows], "o-", label="server RSS (MB)")
    for a in ax:
        a.set_xscale("log")
        a.set_xlabel("clients")
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.suptitle("psao serve builtin:courtyard --animate: clients sending cameras at 30 Hz")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(rows: list[dict]) -> str:
    out = ["| clients | ticks/s | updates/s per client (slowest) | slowest mirror behind (s) | on the shared stream | "
           "server CPU (% of a core) | server CPU per extra client | client processes CPU | server RSS (MB) | "
           "slowest snapshot (s) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    base = rows[0] if rows else None
    for r in rows:
        per = (f"{100 * (r['server_cpu'] - base['server_cpu']) / (r['clients'] - base['clients']):.1f}"
               if r["clients"] > base["clients"] else "")
        out.append(f"| {r['clients']} | {r['ticks_per_s']:.2f} | {r['updates_per_s_per_client']:.2f} "
                   f"({r['updates_per_s_min']:.2f}) | {r['lag_s_max']:.2f} | {r['shared_members']:.1f} | {100 * r['server_cpu']:.0f} | {per} | "
                   f"{100 * r['clients_cpu']:.0f} | {r['server_rss_mb']:.0f} | {r['snapshot_s_max']:.1f} |")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------ one client
async def measure_one(url: str, scene_spec: str, n_updates: int, digest_dir: Path, camera: bool,
                      exact: bool) -> dict:
    """Run one MirrorClient: the window's (wall seconds, updates, first and last tick, CPU seconds); with
    `exact`, its digests (of messages the server vouched for) and then the overview phase until one was taken
    after it began."""
    from psao.client.connection import MirrorClient, scene_camera_feed
    from psao.protocol.session import scene_hash_bytes
    from psao.scene import load_scene

    scene = load_scene(scene_spec)
    feed = scene_camera_feed(scene)
    overview: list = [None]
    vouched = ServerDigests(digest_dir / SERVER_DIGESTS)
    last_digest = [-float("inf")]
    final_digests = [0]  # digests taken once the overview camera was on

    def digest_if(conn: int, seq: int) -> bool:
        if not vouched(conn, seq):
            return False
        now = time.perf_counter()
        if now - last_digest[0] < DIGEST_GAP_S and not (overview[0] is not None and not final_digests[0]):
            return False
        last_digest[0] = now
        final_digests[0] += overview[0] is not None
        return True

    stamps: list[tuple[float, int]] = []  # (wall, tick) of every Update
    window: dict = {}

    def on_update(_mirror, _transforms, tick: int) -> None:
        stamps.append((time.perf_counter(), tick))
        if len(stamps) == RATE_WARM_UPDATES:
            window["cpu0"] = time.process_time()
        elif len(stamps) == RATE_WARM_UPDATES + n_updates:
            window["cpu1"] = time.process_time()

    client = MirrorClient(url, scene_hash_bytes(scene.content_hash()),
                          camera=(lambda t: overview[0] or feed(t)) if camera else None,
                          on_update=on_update, digest_log=digest_dir / "client.jsonl" if exact else None,
                          digest_if=digest_if,
                          reconnect_timeout=60.0, open_timeout=30.0)
    task = asyncio.create_task(client.run())
    while len(stamps) < RATE_WARM_UPDATES + n_updates and not task.done():
        await asyncio.sleep(0.05)
    if task.done():
        task.result()  # (an error ends the benchmark with it)
        raise RuntimeError("the client stopped before the window was complete")
    overview[0] = overview_camera(scene)
    end = time.perf_counter() + (FINAL_S if exact else 0.0)
    while not final_digests[0] and time.perf_counter() < end and not task.done():
        await asyncio.sleep(0.1)
    client.stop()
    await asyncio.gather(task, return_exceptions=True)
    (t0, k0), (t1, k1) = stamps[RATE_WARM_UPDATES - 1], stamps[RATE_WARM_UPDATES + n_updates - 1]
    return {"seconds": t1 - t0, "updates": n_updates, "tick0": k0, "tick1": k1,
            "cpu": window["cpu1"] - window["cpu0"], "reconnects": client.stats.reconnects,
            "final_digests": final_digests[0]}


def rate_main(args: argparse.Namespace) -> int:
    """--rate: one client beside the server at 60 Hz (see ONE CLIENT in the module docstring)."""
    if args.updates < 2:
        print("bench_clients: error: --updates must be >= 2", file=sys.stderr)
        return 2
    density = args.density or RATE_DENSITY
    work = Path(tempfile.mkdtemp(prefix="bench_client_rate_"))
    stats, slog = work / "stats.jsonl", work / SERVER_DIGESTS
    served = ["--density", f"{density:g}", "--tick-hz", f"{RATE_TICK_HZ:g}", "--animate"] + (
        ["--no-cull"] if args.no_cull else [])
    # Two servers: the rate without --digest-log (a server digest after every message that leaves nothing
    # pending is a whole-grid copy and sha256 a tick, which slows its loop and encode thread), then the
    # mirror's exactness with it.
    runs = {}
    for exact, extra in ((False, ["--stats-json", str(stats)]), (True, ["--digest-log", str(slog)])):
        with ServerProcess(args.scene, served + extra, start_timeout=RATE_START_S, cwd=ROOT) as server:
            print(f"psao serve {args.scene} {' '.join(served)}{' --digest-log' if exact else ''} at {server.url}; "
                  f"one MirrorClient {'without a camera' if args.no_camera else 'sending its camera'}", flush=True)
            runs[exact] = asyncio.run(measure_one(server.url, args.scene, args.updates if not exact else 2, work,
                                                  camera=not args.no_camera, exact=exact))
    r = runs[False]
    ticks = r["tick1"] - r["tick0"]
    recs = [x for x in read_jsonl(stats) if r["tick0"] < x["service_tick"] <= r["tick1"]]
    on_stream = sum(x.get("shared_members", 0) >= 1 for x in recs) / max(len(recs), 1)
    compared, differ, _ = compare_digests(slog, [work / "client.jsonl"])
    updates_s = r["updates"] / r["seconds"]
    print(f"window: {r['updates']} updates over {ticks} server ticks in {r['seconds']:.2f} s: "
          f"{updates_s:.1f} updates/s, server {ticks / r['seconds']:.1f} ticks/s, "
          f"{r['updates'] / max(ticks, 1):.3f} updates per tick; on the shared stream {100 * on_stream:.0f}% of "
          f"the ticks; client CPU {100 * r['cpu'] / r['seconds']:.0f}% of a core; {r['reconnects']} reconnects; "
          f"digests compared {compared} ({runs[True]['final_digests']} after the overview camera), "
          f"different {differ}",
          flush=True)
    name = f"one client, {args.scene.removeprefix('builtin:')} N={density:g}"
    v = Verdicts("bench_clients")
    v.check(f"{name}: updates/s at {RATE_TICK_HZ:g} Hz", updates_s, ">=", RATE_UPDATES_S)
    v.check(f"{name}: updates per server tick", r["updates"] / max(ticks, 1), ">=", RATE_UPDATES_S / RATE_TICK_HZ)
    v.check(f"{name}: share of the ticks on the shared stream", on_stream, ">=", RATE_ON_STREAM)
    v.check(f"{name}: reconnects in the window", r["reconnects"], "<=", 0)
    v.check(f"{name}: mirror digests compared", compared, ">=", 1)
    v.check(f"{name}: mirror digests different", differ, "<=", 0)
    return v.exit_code()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_clients", description=__doc__.splitlines()[0])
    p.add_argument("--counts", default="1,10,30,100")
    p.add_argument("--density", type=float, default=None, help="grid density (default 64; with --rate 256)")
    p.add_argument("--seconds", type=float, default=10.0, help="measured window per stage")
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--per-process", type=int, default=10, help="clients per client process (at most; each runs at "
                   "nice CLIENT_NICE beside the server, so a small one keeps up with the tick rate)")
    p.add_argument("--digest-every", type=int, default=0, help="clients log the digest of every message the server "
                   "logged one for, and (k > 0) of every k-th message")
    p.add_argument("--out", type=Path, default=Path("out") / "bench_clients")
    p.add_argument("--no-cull", action="store_true", help="serve with --no-cull (every client is sent every change)")
    p.add_argument("--client-host", nargs=7, metavar=("URL", "SCENE", "COUNTS", "DIR", "HOST", "PER_HOST", "EVERY"),
                   help=argparse.SUPPRESS)
    p.add_argument("--rate", action="store_true",
                   help="one client at 60 Hz instead of the stages (ONE CLIENT in this module's docstring)")
    p.add_argument("--updates", type=int, default=600, help="with --rate: Updates counted in the window")
    p.add_argument("--no-camera", action="store_true", help="with --rate: the client sends no camera (sees every cell)")
    args = p.parse_args(argv)
    if args.rate:
        return rate_main(args)
    args.density = args.density or 64.0
    if args.client_host:
        url, scene, counts, d, host, per_host, every = args.client_host
        asyncio.run(client_host(url, scene, [int(c) for c in counts.split(",")], Path(d), Path(d) / "control",
                                int(host), int(per_host), int(every)))
        return 0
    counts = [int(c) for c in args.counts.split(",")]
    if not counts or counts[0] < 1 or args.per_process < 1 or args.digest_every < 0:
        print("bench_clients: error: counts and --per-process must be >= 1, --digest-every >= 0", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_clients_"))
    stats, slog = work / "stats.jsonl", work / SERVER_DIGESTS
    server = ServerProcess(args.scene, ["--animate", "--density", str(args.density), "--max-clients",
                                        str(max(counts) + 8), "--stats-json", str(stats), "--digest-log", str(slog)]
                           + (["--no-cull"] if args.no_cull else []), start_timeout=None, host=None,
                           log_stdout=False, cwd=ROOT, stop_signal=signal.SIGTERM, stop_grace=60.0)
    try:
        server.start()
    except ServeExited:
        print("bench_clients: error: psao serve exited", file=sys.stderr)
        return 2
    port = server.port
    control = work / "control"
    control.write_text("0")
    hosts: list[subprocess.Popen] = []  # started as the stages need them (idle ones would take CPU too)
    rows, finals = [], []
    try:
        for stage, n in enumerate(counts):
            while len(hosts) < -(-n // args.per_process):
                hosts.append(subprocess.Popen([sys.executable, "-m", "benchmarks.bench_clients", "--client-host",
                                               f"ws://127.0.0.1:{port}", args.scene, args.counts, str(work),
                                               str(len(hosts)), str(args.per_process), str(args.digest_every)],
                                              cwd=ROOT, stdout=subprocess.PIPE, text=True))
            print(f"{n} clients in {len(hosts)} client processes of up to {args.per_process} (MirrorClient: protocol "
                  f"and mirror, no renderer)", flush=True)
            control.write_text(str(stage))
            ready = host_lines(hosts)
            if ready is None:  # a client host ended (its error is on stderr): judge what was measured
                print(f"bench_clients: a client process ended during the {n}-client stage", flush=True)
                rows.append({"clients": n, "ticks_per_s": 0.0, "updates_per_s_per_client": 0.0, "server_cpu": 0.0,
                             "clients_cpu": 0.0, "shared_members": 0.0, "updates_per_s_min": 0.0, "reconnects": float("inf"),
                             "lag_s_max": float("inf"),
                             "connected_min": 0,
                             "server_rss_mb": proc_stats(server.pid)[1] / 2**20, "snapshot_s_max": float("inf")})
                break
            t0 = time.time()
            recs0 = read_jsonl(stats)
            cpu0 = tree_cpu(server.pid)
            ccpu0 = sum(proc_stats(h.pid)[0] for h in hosts)
            time.sleep(args.seconds)
            recs1 = read_jsonl(stats)
            cpu1, rss = tree_cpu(server.pid), proc_stats(server.pid)[1]
            ccpu1 = sum(proc_stats(h.pid)[0] for h in hosts)
            wall = time.time() - t0
            control.write_text(f"{stage}m")
            measured = host_lines(hosts)
            recs2 = read_jsonl(stats)  # the server's latest tick, just after every client said where it is
            time_of = {r["service_tick"]: r["time"] for r in recs2}
            lags = [recs2[-1]["time"] - time_of[t] if t in time_of else float("inf") for t in measured["ticks"]]
            a, b = recs0[-1], recs1[-1]
            window = [r for r in recs1 if a["service_tick"] < r["service_tick"] <= b["service_tick"]]
            ticks = (b["service_tick"] - a["service_tick"]) / max(b["time"] - a["time"], 1e-9)
            # each client's updates over the span its host counted them in (hosts report ready as their own
            # clients have their snapshots, before the window starts: over `wall` they would count too many)
            ups = [(u1 - u0) / max(t1 - t0, 1e-9)
                   for u0, u1, t0, t1 in zip(ready["updates"], measured["updates"], ready["at"], measured["at"])]
            rows.append({"clients": n, "ticks_per_s": ticks, "updates_per_s_per_client": sum(ups) / len(ups),
                         "shared_members": sum(r.get("shared_members", 0) for r in window) / max(len(window), 1),
                         "server_cpu": (cpu1 - cpu0) / wall, "clients_cpu": (ccpu1 - ccpu0) / wall,
                         "server_rss_mb": rss / 2**20, "snapshot_s_max": ready["snapshot_s_max"],
                         "updates_per_s_min": min(ups), "lag_s_max": max(lags, default=float("inf")),
                         "reconnects": sum(m - r for r, m in zip(ready["reconnects"], measured["reconnects"])),
                         "connected_min": min((r["clients"] for r in window), default=0)})
            r = rows[-1]
            print(f"{n:4d} clients: {ticks:6.2f} ticks/s, {r['updates_per_s_per_client']:5.2f} updates/s per client "
                  f"(slowest {r['updates_per_s_min']:.2f}), slowest mirror {r['lag_s_max']:.2f} s behind, "
                  f"{r['reconnects']} reconnects, at least "
                  f"{r['connected_min']} connected, "
                  f"{r['shared_members']:.1f} on the shared stream, server CPU {100 * r['server_cpu']:.0f}% of a core, "
                  f"client processes {100 * r['clients_cpu']:.0f}%, RSS {rss / 2**20:.0f} MB, slowest snapshot "
                  f"{ready['snapshot_s_max']:.1f} s", flush=True)
        finals = [json.loads(h.stdout.readline() or "{}") for h in hosts] if len(rows) == len(counts) else []
    finally:
        control.write_text(f"{len(counts)}m")
        for h in hosts:
            try:
                h.wait(60)
            except subprocess.TimeoutExpired:
                h.kill()
        server.close()
    # the server's log after its listening line (it is in a file, so the server never blocks on a full pipe)
    log_lines = server.log().splitlines(keepends=True)
    log_lines = log_lines[next((i + 1 for i, ln in enumerate(log_lines) if LISTEN_RE.search(ln)), 0):]
    compared, differ, conns = compare_digests(slog, work.glob("c*.jsonl"))
    final_ok = sum(d and c in conns for f in finals for d, c in zip(f.get("digested", []), f.get("conns", [])))
    print(f"mirror digests compared: {compared}, different: {differ}; at the end, seeing the whole scene, "
          f"{final_ok} of {counts[-1]} clients' mirrors compared")
    traceback = any("Traceback" in line for line in log_lines)
    (args.out / "server.log").write_text("".join(log_lines))
    print(table(rows))
    (args.out / "table.md").write_text(table(rows) + "\n")
    (args.out / "table.json").write_text(json.dumps(rows, indent=1))
    chart(rows, args.out / "clients.png")
    print(f"table and chart: {args.out}/table.md, {args.out}/clients.png")
    v = Verdicts("bench_clients")
    base = rows[0]
    for r in rows[1:]:
        target = {10: 0.8, 30: 0.6}.get(r["clients"])
        if target:
            v.check(f"{r['clients']} clients / 1 client tick rate", r["ticks_per_s"] / base["ticks_per_s"], ">=", target)
    for r in rows:  # every client keeps up: connected throughout, no reconnect, updates at the tick rate's pace
        v.check(f"{r['clients']} clients: fewest connected during the window", r["connected_min"], ">=", r["clients"])
        v.check(f"{r['clients']} clients: reconnects during the window", r["reconnects"], "<=", 0)
        v.check(f"{r['clients']} clients: slowest client's updates/s / ticks/s",
                r["updates_per_s_min"] / max(r["ticks_per_s"], 1e-9), ">=", KEEP_UP)
        v.check(f"{r['clients']} clients: slowest mirror's lag behind the server's latest tick (s)",
                r["lag_s_max"], "<=", MAX_LAG_S)
    last = rows[-1]
    v.check(f"slowest snapshot of the {last['clients']}-client stage (s)", last["snapshot_s_max"], "<=", 60)
    if len(rows) > 1:
        per = (last["server_rss_mb"] - base["server_rss_mb"]) / (last["clients"] - base["clients"])
        v.check("server RSS per extra client (MB)", per, "<=", 4)
    v.check("mirror digests compared", compared, ">=", 1)
    v.check(f"clients of the {counts[-1]}-client stage whose mirror was compared at the end", final_ok, ">=", counts[-1])
    v.check("mirror digests different", differ, "<=", 0)
    v.check("tracebacks in the server log", int(traceback), "<=", 0)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
