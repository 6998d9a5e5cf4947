"""Clients behind impaired links: `python -m benchmarks.bench_links [--quick | --mixed | --stall | --cap | --deaf | --storm | --quality | --fig5] [--seconds 10]`.

A real `psao serve builtin:courtyard --density 256 --animate --tick-hz 30 --stats-json` listens on the
host's end of one impaired link (psao.eval.links: a client network namespace joined to the host through a
packet forwarder with a round-trip delay, random loss and a rate cap). For each link setting of the sweep
(rtt 0/50/150 ms x loss 0/1% x 2/5/20 Mbit/s/unlimited; `--quick`: QUICK) the link is changed, and two
real `psao client` processes start at once: one in the namespace, behind the link, and one on the host
beside it (loopback, the baseline of the same moment). Once both have their snapshot and first Update,
both run `--seconds` more and stop on SIGINT. Before the sweep, the loopback client runs alone once.

Per client: updates/s in the window (its digest log has a line, with the tick and the wall time it was
applied, every DIGEST_EVERY Updates), stream Mbit/s after the snapshot (bytes received less the snapshot,
over the time from its first Update to its stop), snapshot MB and the seconds from its start to its first
Update, and how far behind the server it is: per digest line, its wall time (once the Update is applied
and the mirror hashed) less the wall time at which the server applied that tick (the server's
--stats-json), median and 95th percentile. Per link: the
forwarder's packets forwarded and dropped (loss, full queue), both directions together.

Verdicts, each impaired client against the loopback client of the same run: every impaired client got
its snapshot, stayed connected (no reconnect) and received Updates through the window (nothing stalls);
the loopback client beside it kept at least LOOPBACK_KEEP of its updates/s alone (the fast client loses
nothing); on the unimpaired link (rtt 0, no loss, unlimited) the client gets at least FAST_KEEP of the
loopback client's updates/s; and the issue's target for the link ISSUE_LINK at ISSUE_DENSITY: the client
at most ISSUE_LAG_S behind the server (95th percentile; with 1% loss a retransmission costs a round trip
and more, so this tail varies from run to run). The server runs with its default per-client rate (an
estimate of each client's throughput, psao.server.net.rate): a link slower than the stream gets Updates
paced to what it carries, the cells nearest the camera first.

Scenarios instead of the sweep (each writes its own JSON beside links.json; its clients may reconnect, and
count it, and log a digest after every Update, compared with the server's --digest-log by
psao.eval.digests.compare_digests; the server runs with SCENARIO_SERVE):

- `--mixed` (mixed.json): the server listens on every interface; one loopback client runs alone, then the
  MIXED clients start at once: 4 on loopback (the fast ones), 3 behind ISSUE_LINK and 3 behind 2 Mbit/s,
  every impaired client in a namespace and behind a link of its own. Per client the figures above, its
  digests compared/differing and its link's packets; the server's ticks/s in both windows, and the cores
  the server (its CPU ms per tick), the clients and the rest of the machine used in each (CpuMeter). Verdicts: each
  fast client keeps FAST_KEEP of the lone client's updates/s, every client's digests equal the server's,
  and none reconnects or stops receiving Updates.
- `--cap` (cap.json): `--mixed` against `psao serve --client-mbit CAP_MBIT`, the same figures and verdicts.
- `--stall` (stall.json): a loopback client and one behind STALL_LINK; after `--seconds`, the link stalls
  (STALL: all but every packet lost) for STALL_S, then comes back; both run `--seconds` after the stalled
  client's next Update. Updates/s of both before, during and after the stall, the server's VmRSS
  (/proc/PID/status, the serving process) sampled throughout. Verdicts: the loopback client keeps
  STALL_KEEP of its updates/s during the stall, the stalled client has Updates again, reconnects at most
  STALL_RECONNECTS times, both mirrors' digests equal the server's, and the server's RSS grows by at most
  STALL_RSS_MB during the stall (see stall()).
- `--deaf` (deaf.json), `--storm` (storm.json): a loopback client beside a bad one (bad_client()): a client
  that stops reading and answering pings (SIGSTOP) or a storm of STORM_PER_S connects and drops a second,
  for BAD_S; the loopback client's updates/s before, beside and after, the server's RSS. Verdicts: it keeps
  STALL_KEEP of its updates/s, its digests equal the server's, the RSS grows by at most STALL_RSS_MB.
- `--quality` (quality.json): a loopback client and one behind each of QUALITY_LINKS render their own PSAO
  frames; some of each one's frames are scored against RTAO at the current pose (quality()). Verdicts:
  at ISSUE_LINK within QUALITY_DB of the loopback client's PSNR, nothing stalls, no reconnect.
- `--fig5` (fig5.json, fig5_links.png; `--quick`: FIG5_QUICK's links): the paper's Fig. 5 on real links. Per
  link of FIG5_RTT_MS x FIG5_MBIT, a PSAO client as --quality's, then the video competitor behind the same
  link: the server's AO images (psao.eval.video.VideoServer, H.264 at VIDEO_LINK_SHARE of the link's rate, at
  most VIDEO_MAX_MBIT) sent frame by frame over a TCP socket through the link, each frame when the client
  asks for it (psao.eval.videolink), so the link's delay and rate cap act on them; the client shows the newest
  frame that has arrived. Both scored against RTAO at the current pose; PSNR against Mbit/s received and
  against the round trip in one chart (fig5()).
"""
from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.eval.digests import compare_digests
from psao.eval.errors import EvalError
from psao.eval.links import LinkSettings, impaired_link, links_unavailable
from psao.eval.processes import (ServeExited, ServerProcess, interrupt_on_sigterm, kill_group, set_session_nice,
                                 spawn)

ROOT = Path(__file__).resolve().parents[1]
SCENE = "builtin:courtyard"
SWEEP_RTT_MS = (0.0, 50.0, 150.0)
SWEEP_LOSS = (0.0, 0.01)
SWEEP_MBIT = (2.0, 5.0, 20.0, None)
UNIMPAIRED = LinkSettings()
ISSUE_LINK = LinkSettings(rtt_ms=150.0, loss=0.01, mbit=5.0)  # the headline link: rtt 150 ms, 1% loss, 5 Mbit/s
QUICK = (UNIMPAIRED, LinkSettings(rtt_ms=50.0, mbit=20.0), ISSUE_LINK)
DIGEST_EVERY = 4  # a client's digest-log line (tick, wall time) every this many Updates (each hashes the mirror)
# in the scenarios, a line after every Update: the server logs a digest only after a message that leaves the
# client nothing pending, and every one of those is compared
SCENARIO_DIGEST_EVERY = 1
CLIENT_NICE = 10  # clients run below the server (set_session_nice), as remote machines would not take its CPU
RECONNECT_TIMEOUT_S = 30.0  # a client's --reconnect-timeout: seconds without a message before it gives up
START_TIMEOUT_S = 600.0  # seconds for a client's snapshot and first Update (a hung run's bound only)
LOOPBACK_KEEP = 0.8  # the loopback client's updates/s beside an impaired one over its updates/s alone
FAST_KEEP = 0.9  # the unimpaired link's client's updates/s over the loopback client's beside it
ISSUE_LAG_S = 0.3  # seconds behind the server at ISSUE_LINK (95th percentile), the target
ISSUE_DENSITY = 256.0  # the grid density the lag target is set for (other densities: reported only)
# --mixed: (name, link (None: loopback on the host), clients), every impaired client in a namespace of its own
MIXED = (("fast", None, 4), ("issue", ISSUE_LINK, 3), ("slow", LinkSettings(mbit=2.0), 3))
# --mixed: the loopback clients (alone and among the ten) log a digest every this many Updates, the impaired
# ones after every Update: hashing the mirror after each Update costs a client most of its CPU, and ten such
# clients beside the server need more cores than a small machine has; the fast ones' mirrors are still compared
MIXED_FAST_DIGEST_EVERY = DIGEST_EVERY
CAP_MBIT = 4.0  # --cap: psao serve --client-mbit
STALL_LINK = LinkSettings(rtt_ms=50.0, mbit=20.0)  # --stall: the stalled client's link before and after
STALL = LinkSettings(rtt_ms=50.0, loss=0.9999, mbit=20.0)  # the link while stalled (loss must be < 1)
STALL_S = 10.0  # seconds the link stalls, a bad-input scenario
STALL_KEEP = 0.9  # the loopback client's updates/s during the stall over its updates/s before it
STALL_RECONNECTS = 1  # the most reconnects of the stalled client (no reconnect loop)
STALL_RSS_MB = 50.0  # the most the server's RSS may grow during the stall, MB (see stall())
RESUME_TIMEOUT_S = 120.0  # seconds after the stall for the stalled client's next Update (a hung run's bound)
BAD_S = 10.0  # --deaf / --storm: seconds of the bad client's phase
# --quality: the links, each client's frames (size, its --fps), frames scored per client and the RTAO
# reference's rays per pixel; the issue's bound on ISSUE_LINK's PSNR below the loopback client's
QUALITY_LINKS = (UNIMPAIRED, ISSUE_LINK, LinkSettings(rtt_ms=150.0, loss=0.01, mbit=2.0))
QUALITY_SIZE = (160, 90)
QUALITY_FPS = 4.0
QUALITY_FRAMES = 6
QUALITY_SPP = 64
QUALITY_DB = 1.5  # dB
# --fig5: the links (rtt x rate, no loss; --quick: FIG5_QUICK), PSAO clients as --quality's, and the video
# competitor (psao.eval.video, its default spp and denoise, H.264) at VIDEO_FPS over a socket through the same
# link (psao.eval.videolink); its encoder bitrate per link: VIDEO_LINK_SHARE of the link's rate, at most
# VIDEO_MAX_MBIT (an unlimited link gets VIDEO_MAX_MBIT), as a streamer picks its rate to fit the link
FIG5_RTT_MS = (0.0, 50.0, 150.0)
FIG5_MBIT = (2.0, 5.0, None)
FIG5_QUICK = tuple(LinkSettings(rtt_ms=r, mbit=b) for r in (0.0, 150.0) for b in (2.0, None))
VIDEO_FPS = 30.0  # frames requested and sent per second
VIDEO_LINK_SHARE = 0.8  # the encoder's bitrate over the link's rate
VIDEO_MAX_MBIT = 8.0  # Mbit/s, the encoder's bitrate on an unlimited link
VIDEO_CAP_SLACK = 1.05  # the video's received Mbit/s may exceed its link's rate by this factor (headers)
STORM_PER_S = 20.0  # --storm: connections opened (and dropped) per second
STORM_THREADS = 4  # --storm: threads that open them
RSS_EVERY_S = 0.2  # seconds between the server's VmRSS samples
# the scenarios' server options: --no-cull, so a message can leave a client nothing pending (nothing waits
# for its view) and the server logs the digests its mirror is compared with
SCENARIO_SERVE = ("--no-cull",)
ALL_HOSTS = "0.0.0.0"  # the server's --host when clients reach it from several namespaces


@dataclass
class ClientResult:
    """One client's window (see the module)."""

    where: str  # "link" or "loopback"
    updates_per_s: float
    stream_mbit_s: float
    snapshot_mb: float
    first_update_s: float  # seconds from its start to its first Update
    behind_p50_s: float
    behind_p95_s: float
    reconnects: int
    exit_ok: bool
    samples: int  # digest lines in the window


class ClientRun:
    """A `psao client` with a digest log, started now (inside `wrap`), stopped by stop()."""

    def __init__(self, url: str, where: str, log: Path, wrap: list[str], reconnect: bool = False,
                 digest_every: int = DIGEST_EVERY, extra: list[str] = ()):
        self.where, self.log, self.every = where, log, digest_every
        self.t0 = time.time()
        self.proc = spawn(["client", url, SCENE, "--json", *([] if reconnect else ["--no-reconnect"]),
                           "--reconnect-timeout", str(RECONNECT_TIMEOUT_S),
                           "--digest-log", log, "--digest-every", str(digest_every), *map(str, extra)],
                          wrap=[*wrap, "nice", "-n", str(CLIENT_NICE)], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True, cwd=ROOT)
        set_session_nice(self.proc.pid, CLIENT_NICE)  # (its nice alone weighs nothing against the server's session)
        self.report: dict = {}
        self.err = ""

    def lines(self) -> list[dict]:
        if not self.log.exists():
            return []
        return [json.loads(ln) for ln in self.log.read_text().splitlines() if ln.strip().endswith("}")]

    def first_update(self) -> float | None:
        """Wall time of its first Update (its first digest line with a tick), None before."""
        return next((d["t"] for d in self.lines() if d["tick"] >= 0), None)

    def last_update(self) -> float | None:
        """Wall time of its latest digest line with a tick, None before its first."""
        return max((d["t"] for d in self.lines() if d["tick"] >= 0), default=None)

    def rate_between(self, t0: float, t1: float) -> float:
        """Updates/s over the wall times [t0, t1]: its digest lines in it, over its length."""
        lines = sum(1 for d in self.lines() if d["tick"] >= 0 and t0 <= d["t"] <= t1)
        return self.every * lines / (t1 - t0) if t1 > t0 else float("nan")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            out, self.err = self.proc.communicate(timeout=60)
            lines = [ln for ln in out.splitlines() if ln.startswith("{")]
            self.report = json.loads(lines[-1]) if lines else {}
        except subprocess.TimeoutExpired:
            pass
        finally:
            kill_group(self.proc)
        self.t_stop = time.time()

    def result(self, t_from: float, tick_wall: dict[int, float]) -> ClientResult:
        """Its figures from t_from (wall time) to its stop."""
        window = [d for d in self.lines() if d["tick"] >= 0 and t_from <= d["t"] <= self.t_stop]
        rate = updates_rate(window, self.every)
        behind = [d["t"] - tick_wall[d["tick"]] for d in window if d["tick"] in tick_wall]
        first = self.first_update() or float("nan")
        rep = self.report
        stream = (rep.get("bytes_received", 0) - rep.get("snapshot_bytes", 0)) * 8 / 1e6 / max(self.t_stop - first, 1e-9)
        pct = (lambda q: float(np.percentile(behind, q))) if behind else (lambda q: float("nan"))
        return ClientResult(self.where, rate, stream, rep.get("snapshot_bytes", 0) / 1e6, first - self.t0, pct(50),
                            pct(95), int(rep.get("reconnects", -1)), self.proc.returncode in (0, 130, -signal.SIGINT),
                            len(window))


def updates_rate(window: list[dict], every: int) -> float:
    """Updates/s over a client's digest lines (one every `every` Updates), first to last."""
    if len(window) < 2 or window[-1]["t"] <= window[0]["t"]:
        return 0.0
    return every * (len(window) - 1) / (window[-1]["t"] - window[0]["t"])


def wait_first_updates(runs: list[ClientRun]) -> float:
    """Wall time by which every run has had its first Update (EvalError if one exits or the bound passes)."""
    end = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < end:
        firsts = [r.first_update() for r in runs]
        if all(f is not None for f in firsts):
            return max(firsts)
        for r in runs:
            if r.proc.poll() is not None:
                raise EvalError(f"the {r.where} client exited ({r.proc.returncode}) before its first Update: "
                                f"{(r.proc.stderr.read() or '').strip()[-300:]}")
        time.sleep(0.1)
    raise EvalError(f"no first Update within {START_TIMEOUT_S:.0f} s")


def measure(clients: dict[str, tuple[str, list[str]]], seconds: float, work: Path, tag: str,
            scenario: bool = False) -> tuple[dict[str, ClientRun], float]:
    """Clients for each of `clients` (where -> (url, wrap)) started together and run `seconds` after the last
    one's first Update; (runs, window start). `scenario`: see start_clients."""
    runs, t_from, _ = measure_cpu(clients, seconds, work, tag, scenario)
    return runs, t_from


def measure_cpu(clients: dict[str, tuple[str, list[str]]], seconds: float, work: Path, tag: str,
                scenario: bool = False, server_pid: int | None = None,
                loopback_every: int | None = None) -> tuple[dict[str, ClientRun], float, dict]:
    """measure(), and with `server_pid` the cores used over the window (CpuMeter: the server, the clients, the
    rest of the machine; empty without). `loopback_every`: start_clients'."""
    runs = start_clients(clients, work, tag, scenario, loopback_every)
    cpu = {}
    try:
        t_from = wait_first_updates(list(runs.values()))
        meter = None if server_pid is None else CpuMeter(server_pid, [r.proc.pid for r in runs.values()])
        if meter:
            meter.start()
        time.sleep(seconds)
        if meter:
            cpu = meter.stop()
    finally:
        for r in runs.values():
            r.stop()
    return runs, t_from, cpu


def start_clients(clients: dict[str, tuple[str, list[str]]], work: Path, tag: str,
                  scenario: bool = False, loopback_every: int | None = None) -> dict[str, ClientRun]:
    """ClientRuns of `clients` (where -> (url, wrap)); `scenario`: they may reconnect (and count it), and log
    a digest every SCENARIO_DIGEST_EVERY Updates; `loopback_every`: the clients in no namespace (empty wrap)
    every this many instead."""
    every = SCENARIO_DIGEST_EVERY if scenario else DIGEST_EVERY
    return {where: ClientRun(url, where, work / f"{tag}-{where}.jsonl", wrap, scenario,
                             loopback_every if loopback_every is not None and not wrap else every)
            for where, (url, wrap) in clients.items()}


def server_ticks_per_s(walls: dict[int, float], t0: float, t1: float) -> float:
    """The server's ticks/s over the wall times [t0, t1] (its --stats-json; NaN with fewer than two ticks)."""
    ticks = sorted(k for k, t in walls.items() if t0 <= t <= t1)
    if len(ticks) < 2 or walls[ticks[-1]] <= walls[ticks[0]]:
        return float("nan")
    return (ticks[-1] - ticks[0]) / (walls[ticks[-1]] - walls[ticks[0]])


def tick_walls(stats: Path) -> dict[int, float]:
    """Service tick -> wall time it was applied, from the server's --stats-json."""
    out = {}
    for ln in stats.read_text().splitlines():
        if ln.strip():
            d = json.loads(ln)
            out.setdefault(int(d["service_tick"]), float(d["wall"]))
    return out


def sweep(quick: bool) -> list[LinkSettings]:
    if quick:
        return list(QUICK)
    return [LinkSettings(rtt_ms=r, loss=p, mbit=b) for r, p, b in itertools.product(SWEEP_RTT_MS, SWEEP_LOSS, SWEEP_MBIT)]


def row(label: str, c: ClientResult, drops: str = "") -> str:
    return (f"{label:<34} {c.where:<8} {c.updates_per_s:7.1f} {c.stream_mbit_s:7.2f} {c.snapshot_mb:6.2f} "
            f"{c.first_update_s:7.1f} {c.behind_p50_s:7.3f} {c.behind_p95_s:7.3f} {c.reconnects:3d}  {drops}")


def start_server(args, host: str, stats: Path, extra: list[str] = (), digest_log: Path | None = None) -> ServerProcess:
    """`psao serve SCENE --density --animate --tick-hz --stats-json [--digest-log] [extra]` on `host`, started
    and serving its full grid (ServeExited: it exited first)."""
    opts = ["--density", str(args.density), "--animate", "--tick-hz", str(args.tick_hz), "--stats-json", str(stats),
            *([] if digest_log is None else ["--digest-log", str(digest_log)]),
            *extra]
    return ServerProcess(SCENE, opts, host=host, log_stdout=False, cwd=ROOT, start_timeout=None).start()


class RssSampler:
    """A process's VmRSS (/proc/PID/status), sampled every RSS_EVERY_S on a thread: (wall time, MB)."""

    def __init__(self, pid: int):
        self.pid, self.samples = pid, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                text = Path(f"/proc/{self.pid}/status").read_text()
            except OSError:
                return
            if m := re.search(r"^VmRSS:\s+(\d+) kB", text, re.MULTILINE):
                self.samples.append((time.time(), int(m.group(1)) / 1e3))
            self._stop.wait(RSS_EVERY_S)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def peak(self, t0: float, t1: float) -> float:
        """The largest sample in [t0, t1], MB (NaN: none)."""
        return max((mb for t, mb in self.samples if t0 <= t <= t1), default=float("nan"))

    def at(self, t: float) -> float:
        """The last sample at or before wall time t, MB (NaN: none)."""
        return next((mb for ts, mb in reversed(self.samples) if ts <= t), float("nan"))


def cpu_seconds(pid: int) -> float:
    """CPU seconds (user + system) of a process, its threads and its live descendants (/proc; 0 when gone)."""
    total, todo = 0.0, [pid]
    tick = os.sysconf("SC_CLK_TCK")
    while todo:
        p = todo.pop()
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError, IndexError):
            continue
    return total


def machine_busy_seconds() -> float:
    """CPU seconds every core of the machine spent busy since boot (/proc/stat: all but idle and iowait)."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    return (sum(values) - values[3] - values[4]) / os.sysconf("SC_CLK_TCK")


class CpuMeter:
    """Cores used (CPU seconds per second) by the server, by the clients and by the whole machine between
    start() and stop()."""

    def __init__(self, server_pid: int, client_pids: list[int]):
        self.server_pid, self.client_pids = server_pid, client_pids

    def _read(self) -> tuple[float, float, float, float]:
        return (time.monotonic(), cpu_seconds(self.server_pid), sum(map(cpu_seconds, self.client_pids)),
                machine_busy_seconds())

    def start(self) -> None:
        self._t0 = self._read()

    def stop(self) -> dict:
        t1 = self._read()
        dt = t1[0] - self._t0[0]
        server, clients, machine = ((b - a) / dt for a, b in zip(self._t0[1:], t1[1:]))
        return {"server_cores": server, "clients_cores": clients, "machine_busy_cores": machine,
                "others_cores": machine - server - clients, "machine_cores": os.cpu_count()}


def digests_of(server_log: Path, run: ClientRun) -> dict:
    """Its mirror's digests against the server's (psao.eval.digests.compare_digests)."""
    compared, differ, conns = compare_digests(server_log, [run.log])
    return {"compared": compared, "differ": differ, "connections": len(conns)}


def record_digests(v: Verdicts, where: str, d: dict) -> None:
    v.record(f"{where}: mirror digests equal the server's", d["compared"] > 0 and d["differ"] == 0,
             f"{d['compared']} compared, {d['differ']} differ")


def packets(counts: dict) -> dict:
    """A link's forwarder counts, both directions together."""
    return {"forwarded": sum(c["forwarded"] for c in counts.values()),
            "lost": sum(c["dropped_loss"] for c in counts.values()),
            "queue_dropped": sum(c["dropped_queue"] for c in counts.values())}


def drops(pk: dict | None) -> str:
    return "" if pk is None else f"{pk['forwarded']}/{pk['lost']}/{pk['queue_dropped']}"


def header(last: str) -> str:
    return (f"{'link':<34} {'client':<8} {'upd/s':>7} {'Mbit/s':>7} {'snapMB':>6} {'first_s':>7} {'p50_s':>7} "
            f"{'p95_s':>7} {'rc':>3}  {last}")


def mixed(args, work: Path, extra: list[str], name: str) -> int:
    """--mixed (--cap: the server with `extra`): one loopback client alone, then the MIXED clients at once,
    each impaired one in a namespace of its own; `name`.json. Verdicts: each fast (loopback) client keeps
    FAST_KEEP of the lone client's updates/s, every client's mirror digests equal the server's, and no
    client reconnects or stops receiving Updates."""
    stats, server_digests = work / "stats.jsonl", work / f"{name}-server-digests.jsonl"
    v = Verdicts("bench_links")
    wheres = [(f"{group}{k + 1}", s) for group, s, n in MIXED for k in range(n)]
    with interrupt_on_sigterm(), contextlib.ExitStack() as stack:
        links = {where: stack.enter_context(impaired_link(s)) for where, s in wheres if s is not None}
        server = start_server(args, ALL_HOSTS, stats, [*SCENARIO_SERVE, *extra], server_digests)
        try:
            loop = f"ws://127.0.0.1:{server.port}"
            print(f"server {' '.join([loop, *extra])}: full grid after {server.full_grid_s:.1f} s; "
                  f"{len(links)} links", flush=True)
            alone, t_alone, cpu_alone = measure_cpu({"alone": (loop, [])}, args.seconds, work, f"{name}-alone",
                                                    scenario=True, server_pid=server.pid,
                                                    loopback_every=MIXED_FAST_DIGEST_EVERY)
            clients = {where: ((f"ws://{links[where].host_address}:{server.port}", links[where].prefix)
                               if where in links else (loop, [])) for where, _ in wheres}
            runs, t_from, cpu_mixed = measure_cpu(clients, args.seconds, work, name, scenario=True,
                                                  server_pid=server.pid, loopback_every=MIXED_FAST_DIGEST_EVERY)
            counts = {where: packets(link.change(link.settings)) for where, link in links.items()}
        finally:
            server.close()
    walls = tick_walls(stats)
    base = alone["alone"].result(t_alone, walls)
    # over the measured windows (`seconds` from their start: the clients' stops come after)
    ticks = {"alone": server_ticks_per_s(walls, t_alone, t_alone + args.seconds),
             "mixed": server_ticks_per_s(walls, t_from, t_from + args.seconds)}
    fast_rates = [runs[where].result(t_from, walls).updates_per_s for where, s in wheres if s is None]
    per_tick = {"alone": base.updates_per_s / ticks["alone"], "fast": float(np.mean(fast_rates)) / ticks["mixed"]}
    print(f"server ticks/s: {ticks['alone']:.1f} beside the lone client, {ticks['mixed']:.1f} beside the "
          f"{len(wheres)}; Updates per server tick: the lone client {per_tick['alone']:.2f}, the fast ones "
          f"{per_tick['fast']:.2f} (mean)")
    cpu = {"alone": cpu_alone, "mixed": cpu_mixed}
    for phase, c in cpu.items():
        c["server_ms_per_tick"] = 1e3 * c["server_cores"] / ticks[phase]
        print(f"cores used beside {'the lone client' if phase == 'alone' else f'the {len(wheres)}'}: server "
              f"{c['server_cores']:.2f} ({c['server_ms_per_tick']:.0f} CPU ms per tick), clients "
              f"{c['clients_cores']:.2f}, the rest of the machine {c['others_cores']:.2f}; busy "
              f"{c['machine_busy_cores']:.2f} of {c['machine_cores']}")
    print(header("digests compared/differ  packets fwd/lost/queue-dropped"))
    print(row("(loopback alone)", base))
    results = []
    for where, s in wheres:
        c, d = runs[where].result(t_from, walls), digests_of(server_digests, runs[where])
        print(row("loopback" if s is None else s.label(), c, f"{d['compared']}/{d['differ']}  {drops(counts.get(where))}"))
        results.append({"link": None if s is None else asdict(s), "client": asdict(c), "digests": d,
                        "packets": counts.get(where)})
    for where, s in wheres:
        c = next(r["client"] for r in results if r["client"]["where"] == where)
        if s is None:
            v.check(f"{where}: updates/s among {len(wheres)} / one fast client alone", c["updates_per_s"]
                    / base.updates_per_s, ">=", FAST_KEEP)
        v.record(f"{where}: connected, no reconnect, Updates through the window",
                 c["exit_ok"] and c["reconnects"] == 0 and c["samples"] >= 2,
                 f"exit ok {c['exit_ok']}, {c['reconnects']} reconnects, {c['samples']} samples")
        record_digests(v, where, next(r["digests"] for r in results if r["client"]["where"] == where))
    (args.out / f"{name}.json").write_text(json.dumps({
        "scenario": name, "server_options": extra, "alone": asdict(base), "clients": results,
        "server_ticks_per_s": ticks, "updates_per_tick": per_tick, "cpu": cpu,
        "density": args.density, "tick_hz": args.tick_hz, "seconds": args.seconds}, indent=1))
    return v.exit_code()


def wait_update_after(run: ClientRun, t: float, timeout: float) -> float | None:
    """Wall time of the run's first digest line after wall time `t`, waited for up to `timeout` s (None)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and run.proc.poll() is None:
        if later := [d["t"] for d in run.lines() if d["tick"] >= 0 and d["t"] > t]:
            return min(later)
        time.sleep(0.1)
    return None


def stall(args, work: Path) -> int:
    """--stall: a loopback client and one behind STALL_LINK; after `seconds`, the link stalls (STALL) for
    STALL_S, then comes back; once the stalled client has an Update again, both run `seconds` more;
    stall.json. The server's RSS is sampled throughout.

    The RSS bound STALL_RSS_MB, on the rise of the server's RSS high-water mark while the link is stalled
    over its high-water mark while both clients streamed before: what the server keeps for a
    client that reads nothing is its pending buckets and cells (bool masks of a fixed size:
    psao.server.net.clients.PendingSet), at most FanoutSettings.max_queued shared Updates in its outbox,
    its websocket write buffer and its socket's send buffer (--send-buffer): none of it grows with the
    stall's length. 50 MB is far above those; the samples themselves swing by a few hundred MB as the
    server streams, hence high-water marks. A server that kept a copy of the state per tick for the
    client (3 MB or more each, 30 ticks/s) would exceed it within a second. It is no test of a queue of encoded Updates: at this scene's stream (under 1 Mbit/s) the
    Updates of a whole stall come to about a megabyte. The growth through the stalled client's catch-up
    (one Update of its own with everything pending) is reported beside it."""
    stats, server_digests = work / "stats.jsonl", work / "stall-server-digests.jsonl"
    v = Verdicts("bench_links")
    with interrupt_on_sigterm(), impaired_link(STALL_LINK) as link:
        server = start_server(args, link.host_address, stats, list(SCENARIO_SERVE), server_digests)
        try:
            print(f"server {server.url}: full grid after {server.full_grid_s:.1f} s; link {STALL_LINK.label()}, "
                  f"stalls at {STALL.label()} for {STALL_S:g} s", flush=True)
            rss = RssSampler(server.pid)
            runs = start_clients({"loopback": (server.url, []), "stalled": (server.url, link.prefix)}, work,
                                 "stall", scenario=True)
            try:
                t_from = wait_first_updates(list(runs.values()))
                time.sleep(args.seconds)
                t_stall = time.time()
                before = packets(link.change(STALL))
                time.sleep(STALL_S)
                during = packets(link.change(STALL_LINK))
                t_back = time.time()
                resumed = wait_update_after(runs["stalled"], t_back, RESUME_TIMEOUT_S)
                time.sleep(args.seconds)
                t_end = time.time()  # the clients' stops come after
            finally:
                for r in runs.values():
                    r.stop()
                rss.stop()
            after = packets(link.change(STALL_LINK))
        finally:
            server.close()
    walls = tick_walls(stats)
    fast, slow = runs["loopback"], runs["stalled"]
    fast_c, slow_c = fast.result(t_from, walls), slow.result(t_from, walls)
    phases = {"before": (t_from, t_stall), "stall": (t_stall, t_back), "after": (t_back, t_end)}
    rates = {where: {ph: r.rate_between(*span) for ph, span in phases.items()} for where, r in runs.items()}
    ticks = {ph: server_ticks_per_s(walls, *span) for ph, span in phases.items()}
    rss_mb = {"before": rss.peak(t_from, t_stall), "stall": rss.peak(t_stall, t_back),
              "after": rss.peak(t_back, slow.t_stop), "at_stall": rss.at(t_stall),
              "stall_s_before": rss.at(t_stall - STALL_S)}
    # the high-water mark's rise over the one of streaming before the stall (RSS swings by a few hundred MB
    # within a window as the server streams; a high-water mark does not): while the link is stalled, and
    # from the stall's start to the end (the stalled client's catch-up included); and the drift of the
    # samples over as long a time just before the stall
    growth = {"stall": rss_mb["stall"] - rss_mb["before"], "to_end": max(rss_mb["stall"], rss_mb["after"])
              - rss_mb["before"], "before": rss_mb["at_stall"] - rss_mb["stall_s_before"]}
    resume_s = float("nan") if resumed is None else resumed - t_back
    after_samples = sum(1 for d in slow.lines() if d["tick"] >= 0 and d["t"] > t_back)
    digests = {where: digests_of(server_digests, r) for where, r in runs.items()}
    print(header("digests compared/differ"))
    for label, c in (("loopback", fast_c), (STALL_LINK.label() + " (stalls)", slow_c)):
        print(row(label, c, f"{digests[c.where]['compared']}/{digests[c.where]['differ']}"))
    for where in runs:
        print(f"{where:<8} updates/s before {rates[where]['before']:.1f}, during the stall {rates[where]['stall']:.1f}, "
              f"after {rates[where]['after']:.1f}")
    print(f"stalled client: first Update {resume_s:.1f} s after the link came back, {after_samples} digest lines after; "
          f"packets fwd/lost/queue-dropped before {drops(before)}, stall {drops(during)}, after {drops(after)}")
    per_tick = {ph: rates["loopback"][ph] / ticks[ph] for ph in phases}
    print(f"server ticks/s before {ticks['before']:.1f}, during the stall {ticks['stall']:.1f}, "
          f"after {ticks['after']:.1f}; the loopback client's Updates per server tick {per_tick['before']:.2f}, "
          f"{per_tick['stall']:.2f}, {per_tick['after']:.2f}")
    print(f"server RSS peak MB: before {rss_mb['before']:.1f}, during the stall {rss_mb['stall']:.1f}, "
          f"after {rss_mb['after']:.1f}; peak over the peak before, MB: {growth['stall']:.1f} during the stall, "
          f"{growth['to_end']:.1f} from its start to the end (catch-up included); samples drift "
          f"{growth['before']:.1f} MB over the {STALL_S:g} s before it")
    v.check("loopback client's updates/s during the stall / before it", rates["loopback"]["stall"]
            / rates["loopback"]["before"], ">=", STALL_KEEP)
    v.record("stalled client resumed: Updates after the stall", resumed is not None and after_samples >= 2,
             f"first {resume_s:.1f} s after, {after_samples} digest lines")
    v.check("stalled client's reconnects", slow_c.reconnects if slow_c.reconnects >= 0 else float("nan"), "<=",
            STALL_RECONNECTS)
    v.record("loopback client: connected, no reconnect", fast_c.exit_ok and fast_c.reconnects == 0,
             f"exit ok {fast_c.exit_ok}, {fast_c.reconnects} reconnects")
    for where, d in digests.items():
        record_digests(v, where, d)
    v.check("server RSS peak during the stall over the peak before it, MB", growth["stall"], "<=", STALL_RSS_MB)
    (args.out / "stall.json").write_text(json.dumps({
        "scenario": "stall", "link": asdict(STALL_LINK), "stall": asdict(STALL), "stall_s": STALL_S,
        "clients": {"loopback": asdict(fast_c), "stalled": asdict(slow_c)}, "rates": rates, "resume_s": resume_s,
        "after_samples": after_samples, "digests": digests, "rss_mb": rss_mb, "rss_growth_mb": growth, "loopback_updates_per_tick": per_tick,
        "rss_trace": [(round(t - t_stall, 2), mb) for t, mb in rss.samples],
        "server_ticks_per_s": ticks,
        "packets": {"before": before, "stall": during, "after": after},
        "density": args.density, "tick_hz": args.tick_hz, "seconds": args.seconds}, indent=1))
    return v.exit_code()


class Storm:
    """A reconnect storm: STORM_THREADS threads opening websocket connections to `url` at STORM_PER_S in all,
    each one's Hello unsent and the connection dropped as soon as it opened (its TCP reset, no close
    handshake), until stop(). Counts the connections opened and the ones that failed."""

    def __init__(self, url: str):
        self.url, self.opened, self.failed = url, 0, 0
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._run, args=(k,), daemon=True) for k in range(STORM_THREADS)]
        for t in self._threads:
            t.start()

    def _run(self, k: int) -> None:
        from websockets.sync.client import connect

        every = STORM_THREADS / STORM_PER_S
        due = time.monotonic() + k * every / STORM_THREADS
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            due += every
            try:
                ws = connect(self.url, open_timeout=10)
                ws.socket.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                ws.socket.close()  # a reset, as a client that vanishes
                self.opened += 1
            except Exception:  # a refused or timed-out handshake counts, and the storm goes on
                self.failed += 1

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join()


def bad_client(args, work: Path, kind: str) -> int:
    """--deaf / --storm (`kind`): a loopback client streams for `seconds`; then, for BAD_S, a bad client:
    `deaf`, a second `psao client` that had its snapshot and Updates, then SIGSTOPped (it never reads and
    never answers a ping again: its kernel's receive buffer fills, then the server's send buffer), or
    `storm`, a Storm of STORM_PER_S connections a second; then `seconds` after (the deaf client is killed
    at the phase's end). The server's RSS is sampled throughout; KIND.json. Verdicts: the loopback
    client keeps STALL_KEEP of its updates/s during the bad phase and after it, its digests equal the
    server's, it never reconnects, and the server's RSS high-water mark rises by at most STALL_RSS_MB over the
    one before (the bound of --stall, see stall(): what the server keeps per connection does not grow
    with time)."""
    stats, server_digests = work / "stats.jsonl", work / f"{kind}-server-digests.jsonl"
    v = Verdicts("bench_links")
    deaf, storm = None, None
    with interrupt_on_sigterm():
        server = start_server(args, "127.0.0.1", stats, list(SCENARIO_SERVE), server_digests)
        try:
            print(f"server {server.url}: full grid after {server.full_grid_s:.1f} s; bad client: {kind}", flush=True)
            rss = RssSampler(server.pid)
            runs = start_clients({"loopback": (server.url, [])}, work, kind, scenario=True)
            if kind == "deaf":
                deaf = start_clients({"deaf": (server.url, [])}, work, kind, scenario=True)["deaf"]
            try:
                t_from = wait_first_updates([*runs.values(), *([deaf] if deaf else [])])
                time.sleep(args.seconds)
                t_bad = time.time()
                if deaf:
                    deaf.proc.send_signal(signal.SIGSTOP)
                else:
                    storm = Storm(server.url)
                time.sleep(BAD_S)
                t_back = time.time()
                if storm:
                    storm.stop()
                time.sleep(args.seconds)
                t_end = time.time()
            finally:
                if deaf:
                    kill_group(deaf.proc)
                for r in runs.values():
                    r.stop()
                rss.stop()
            alive = server.alive()
        finally:
            server.close()
    walls = tick_walls(stats)
    fast = runs["loopback"]
    fast_c = fast.result(t_from, walls)
    phases = {"before": (t_from, t_bad), "bad": (t_bad, t_back), "after": (t_back, t_end)}
    rates = {ph: fast.rate_between(*span) for ph, span in phases.items()}
    ticks = {ph: server_ticks_per_s(walls, *span) for ph, span in phases.items()}
    rss_mb = {ph: rss.peak(*span) for ph, span in phases.items()}
    growth = max(rss_mb["bad"], rss_mb["after"]) - rss_mb["before"]
    digests = digests_of(server_digests, fast)
    print(header("digests compared/differ"))
    print(row("loopback", fast_c, f"{digests['compared']}/{digests['differ']}"))
    print(f"loopback updates/s before {rates['before']:.1f}, beside the {kind} client {rates['bad']:.1f}, after "
          f"{rates['after']:.1f}; server ticks/s {ticks['before']:.1f}, {ticks['bad']:.1f}, {ticks['after']:.1f}")
    if storm:
        print(f"storm: {storm.opened} connections opened and reset in {BAD_S:g} s "
              f"({storm.opened / BAD_S:.1f}/s), {storm.failed} failed")
    print(f"server RSS peak MB: before {rss_mb['before']:.1f}, beside the {kind} client {rss_mb['bad']:.1f}, "
          f"after {rss_mb['after']:.1f}; rise over the peak before {growth:.1f} MB")
    for ph in ("bad", "after"):
        v.check(f"{kind}: loopback client's updates/s {'beside it' if ph == 'bad' else 'after it'} / before",
                rates[ph] / rates["before"], ">=", STALL_KEEP)
    v.record(f"{kind}: loopback client connected, no reconnect; server alive", fast_c.exit_ok and
             fast_c.reconnects == 0 and alive, f"exit ok {fast_c.exit_ok}, {fast_c.reconnects} reconnects, "
             f"server alive {alive}")
    record_digests(v, f"{kind}: loopback", digests)
    if storm:
        v.check("storm: connections opened per second", storm.opened / BAD_S, ">=", 0.5 * STORM_PER_S)
    v.check(f"{kind}: server RSS peak beside it and after over the peak before, MB", growth, "<=", STALL_RSS_MB)
    (args.out / f"{kind}.json").write_text(json.dumps({
        "scenario": kind, "bad_s": BAD_S, "client": asdict(fast_c), "rates": rates, "server_ticks_per_s": ticks,
        "digests": digests, "rss_mb": rss_mb, "rss_growth_mb": growth,
        "storm": None if storm is None else {"opened": storm.opened, "failed": storm.failed, "per_s": STORM_PER_S},
        "rss_trace": [(round(t - t_bad, 2), mb) for t, mb in rss.samples],
        "density": args.density, "tick_hz": args.tick_hz, "seconds": args.seconds}, indent=1))
    return v.exit_code()


def server_clock(stats: Path) -> tuple[np.ndarray, np.ndarray]:
    """(wall times, server times) of the server's ticks (its --stats-json), for np.interp."""
    rows = sorted({int(d["service_tick"]): (float(d["wall"]), float(d["time"]))
                   for d in map(json.loads, filter(str.strip, stats.read_text().splitlines()))}.values())
    return np.array([w for w, _ in rows]), np.array([t for _, t in rows])


def quality_run(args, scene, link, s: LinkSettings | None, url: str, work: Path, tag: str) -> tuple:
    """One client behind `link` changed to `s` (None: on the host, loopback) rendering its PSAO frames
    (QUALITY_SIZE at QUALITY_FPS) for `seconds` after its first Update; (ClientRun, window start, frames dir)."""
    frames = work / f"{tag}-frames"
    wrap = [] if s is None else link.prefix
    if s is not None:
        link.change(s)
    run = ClientRun(url, "loopback" if s is None else "link", work / f"{tag}.jsonl", wrap, extra=[
        "--render", frames, "--ao", "psao", "--size", f"{QUALITY_SIZE[0]}x{QUALITY_SIZE[1]}", "--fps", QUALITY_FPS])
    try:
        t_from = wait_first_updates([run])
        time.sleep(args.seconds)
    finally:
        run.stop()
    return run, t_from, frames


def quality_chart(results: list[dict], path: Path) -> None:
    """PSNR of each scored frame per client (points) and their mean (bar), the stream's Mbit/s beside."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ["loopback" if r["link"] is None else LinkSettings(**r["link"]).label().replace(", ", "\n", 1)
              for r in results]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    x = np.arange(len(results))
    ax.bar(x, [r["psnr_mean"] for r in results], color="#9ecae1", label="mean of the scored frames")
    for k, r in enumerate(results):
        ax.plot(np.full(len(r["psnr"]), k), r["psnr"], "o", color="#08519c", ms=4)
    low = min((p for r in results for p in r["psnr"]), default=0.0)
    ax.set_ylim(max(0.0, low - 3), None)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("PSNR against RTAO at the current pose, dB")
    ax.set_title("PSAO client frames behind impaired links")
    ax.legend(fontsize=8)
    bx.bar(x, [r["client"]["stream_mbit_s"] for r in results], color="#fdae6b")
    bx.set_xticks(x, labels, fontsize=8)
    bx.set_ylabel("stream after the snapshot, Mbit/s")
    bx.set_title("what each client received")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def score_psao_runs(scene, stats: Path, runs: list[tuple], v: Verdicts) -> list[dict]:
    """Per (link settings or None: loopback, ClientRun, window start, frames dir) of quality_run: QUALITY_FRAMES
    of the frames it wrote in its window scored against RTAO (QUALITY_SPP) at the scene's pose at the server's
    time when it wrote them (the server's --stats-json); its row, and a verdict that it stayed connected without
    a reconnect and had Updates through its window."""
    from psao.eval.client_frames import load_client_frames, score_client_frames
    from psao.eval.reference import ReferenceSettings
    from psao.scene.rigid import instance_transform

    walls, times = server_clock(stats)

    def pose(f):
        t = float(np.interp(f.wall, walls, times))
        return np.stack([instance_transform(scene, i, t) for i in range(len(scene.instances))]), t

    tick_wall = tick_walls(stats)
    settings = ReferenceSettings(spp=QUALITY_SPP, cache_dir=None)
    results = []
    print(header("PSNR dB (mean, min) of its frames against RTAO at the current pose"))
    for s, run, t_from, frames in runs:
        c = run.result(t_from, tick_wall)
        window = [f for f in load_client_frames(frames) if f.wall is not None and t_from <= f.wall <= run.t_stop]
        scores = score_client_frames(scene, frames, QUALITY_FRAMES, settings, pose=pose, frames=window)
        psnr = [sc.psao.psnr for sc in scores]
        mean = float(np.mean(psnr)) if psnr else float("nan")
        print(row("loopback" if s is None else s.label(), c, f"{mean:.2f} ({min(psnr, default=float('nan')):.2f}), "
                  f"{len(psnr)} frames"), flush=True)
        results.append({"link": None if s is None else asdict(s), "client": asdict(c), "psnr": psnr,
                        "psnr_mean": mean, "frames_in_window": len(window)})
        v.record(f"{'loopback' if s is None else s.label()}: connected, no reconnect, Updates through the window",
                 c.exit_ok and c.reconnects == 0 and c.samples >= 2 and len(psnr) > 0,
                 f"exit ok {c.exit_ok}, {c.reconnects} reconnects, {c.samples} samples, {len(psnr)} frames scored")
    return results


def quality(args, work: Path) -> int:
    """--quality (quality.json): per link of QUALITY_LINKS and for a loopback client (on the host, the same
    server), a client rendering its own PSAO frames; QUALITY_FRAMES of the frames it wrote in its window
    scored against RTAO (QUALITY_SPP) at the current pose: the scene's transforms and skinning at the
    server's time when the client wrote the frame (the server's --stats-json gives its time per wall
    time), so a client whose mirror lags (stale AO, stale transforms) loses PSNR for it. Verdicts: at
    ISSUE_LINK the frames' mean PSNR within QUALITY_DB of the loopback client's, every client
    connected without a reconnect and with Updates through its window (nothing stalls)."""
    from psao.scene import load_scene

    scene = load_scene(SCENE)
    stats = work / "stats.jsonl"
    v = Verdicts("bench_links")
    runs = []
    with interrupt_on_sigterm(), impaired_link() as link:
        server = start_server(args, ALL_HOSTS, stats)
        try:
            print(f"server: full grid after {server.full_grid_s:.1f} s", flush=True)
            loop = f"ws://127.0.0.1:{server.port}"
            runs.append((None, *quality_run(args, scene, link, None, loop, work, "q-loopback")))
            for i, s in enumerate(QUALITY_LINKS):
                runs.append((s, *quality_run(args, scene, link, s, f"ws://{link.host_address}:{server.port}", work,
                                             f"q{i}")))
        finally:
            server.close()
    results = score_psao_runs(scene, stats, runs, v)
    loop_db = results[0]["psnr_mean"]
    for r in results[1:]:
        if r["link"] == asdict(ISSUE_LINK):
            v.check(f"{ISSUE_LINK.label()}: PSNR below the loopback client's, dB", loop_db - r["psnr_mean"],
                    "<=", QUALITY_DB)
    quality_chart(results, args.chart or args.out / "quality.png")
    (args.out / "quality.json").write_text(json.dumps({
        "scenario": "quality", "loopback_psnr": loop_db, "clients": results, "size": QUALITY_SIZE, "fps": QUALITY_FPS,
        "spp": QUALITY_SPP, "density": args.density, "tick_hz": args.tick_hz, "seconds": args.seconds}, indent=1))
    return v.exit_code()


def fig5_links(quick: bool) -> list[LinkSettings]:
    """--fig5's links: FIG5_QUICK, or every rtt of FIG5_RTT_MS with every rate of FIG5_MBIT."""
    if quick:
        return list(FIG5_QUICK)
    return [LinkSettings(rtt_ms=r, mbit=b) for r, b in itertools.product(FIG5_RTT_MS, FIG5_MBIT)]


def video_bitrate(s: LinkSettings) -> float:
    """The video encoder's bitrate for link `s`, Mbit/s (see VIDEO_LINK_SHARE)."""
    return VIDEO_MAX_MBIT if s.mbit is None else min(VIDEO_LINK_SHARE * s.mbit, VIDEO_MAX_MBIT)


def scene_pose(scene, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(view, proj, transforms) of the scene at time t: the default camera path and the instances' animation."""
    from psao.client.render.views import path_matrices
    from psao.scene import scene_camera
    from psao.scene.rigid import instance_transform

    view, proj = path_matrices(scene, scene_camera(scene, None), t, QUALITY_SIZE)
    return view, proj, np.stack([instance_transform(scene, i, t) for i in range(len(scene.instances))])


def draw(renderer, scene, t: float):
    """A RenderedFrame of the scene at time t (G-buffer only: the AO comes from elsewhere)."""
    from psao.eval.quality import FramePose, RenderedFrame

    view, proj, transforms = scene_pose(scene, t)
    renderer.set_transforms(transforms)
    renderer.set_skin_time(t)
    gb = renderer.render(view, proj).gbuffer
    return RenderedFrame(FramePose(0, t, view, proj), {}, gb.mask, gb, {}, transforms=transforms, skin_time=t)


def video_frames(scene, count: int) -> list[np.ndarray]:
    """The video server's AO images of frames 0..count-1: frame k for the scene and camera at k / VIDEO_FPS
    (psao.eval.video.VideoServer: Embree, its default rays and denoise), drawn here before the streams run."""
    from psao.client.render.renderer import FrameRenderer
    from psao.eval.video import VideoServer, VideoSettings

    aos = []
    with FrameRenderer(scene, QUALITY_SIZE, "ssao") as r, VideoServer(scene, VideoSettings(fps=VIDEO_FPS)) as server:
        for k in range(count):
            aos.append(server.render(draw(r, scene, k / VIDEO_FPS))[0])
    return aos


def video_run(link, s: LinkSettings, aos: list[np.ndarray], work: Path, tag: str) -> dict:
    """The video stream behind `link` changed to `s`: aos encoded at video_bitrate(s), served on the link's host
    end (psao.eval.videolink), requested from inside the namespace at VIDEO_FPS; the receive log and the bitrate."""
    from psao.eval.video import VideoSettings, encode_stream
    from psao.eval.videolink import VideoLinkServer, read_receive_log

    link.change(s)
    bitrate = video_bitrate(s)
    stream = encode_stream(aos, VideoSettings(bitrate_mbit=bitrate, fps=VIDEO_FPS))
    packets = [list(ps) for ps in stream.packets]
    log_path = work / f"{tag}-video.json"
    with VideoLinkServer(packets, link.host_address) as server:
        proc = subprocess.run([*link.prefix, "nice", "-n", str(CLIENT_NICE), sys.executable, "-m", "psao.eval.videolink",
                               link.host_address, str(server.port), "--fps", str(VIDEO_FPS), "--frames", str(len(aos)),
                               "--out", str(log_path)], capture_output=True, text=True, cwd=ROOT,
                              timeout=len(aos) / VIDEO_FPS + 120)
    if proc.returncode != 0:
        raise EvalError(f"the video client behind {s.label()} failed ({proc.returncode}): {proc.stderr.strip()[-300:]}")
    return {"log": read_receive_log(log_path), "bitrate_mbit": bitrate, "codec": stream.codec, "size": stream.size}


def score_video_run(scene, run: dict, renderer, settings) -> dict:
    """What the video client showed, scored: at QUALITY_FRAMES display times spread over its requests after its
    first frame arrived, the newest frame that had arrived (decoded from the packets it received) against RTAO
    at the scene's pose at the display time (its own clock: request k at start + k / VIDEO_FPS asks for the pose
    at k / VIDEO_FPS). Its Mbit/s received, and per frame its round trip (request to arrival)."""
    from psao.eval.metrics import composite_ao, score
    from psao.eval.reference import FrameKey, reference_ao
    from psao.eval.video import EncodedStream, decode_stream

    log = run["log"]
    t0 = log.requests[0]
    arrived = [a for a in log.arrivals if a is not None]
    decoded = decode_stream(EncodedStream(run["codec"], tuple(run["size"]), VIDEO_FPS, log.packets, [0.0] * len(log.packets)))
    trips = [a - r for r, a in zip(log.requests, log.arrivals) if a is not None]
    psnr = []
    if arrived:
        for T in np.linspace(arrived[0], log.requests[-1], QUALITY_FRAMES + 1)[1:]:
            k = max(i for i, a in enumerate(log.arrivals) if a is not None and a <= T)
            now = draw(renderer, scene, float(T - t0))
            ref = reference_ao(scene, now.gbuffer, now.transforms, replace(settings, skin_time=now.skin_time),
                               FrameKey(now.pose.view, now.pose.proj, now.pose.time))
            psnr.append(score(composite_ao(ref, now.mask), composite_ao(decoded[k], now.mask))[0].psnr)
    span = (arrived[-1] - t0) if arrived else float("nan")
    pct = (lambda q: float(np.percentile(trips, q))) if trips else (lambda q: float("nan"))
    return {"psnr": psnr, "psnr_mean": float(np.mean(psnr)) if psnr else float("nan"),
            "stream_mbit_s": 8e-6 * log.bytes_received / span if arrived else 0.0, "frames_requested": len(log.requests),
            "frames_arrived": len(arrived), "round_trip_p50_s": pct(50), "round_trip_p95_s": pct(95),
            "bitrate_mbit": run["bitrate_mbit"]}


def fig5_chart(rows: list[dict], path: Path) -> None:
    """The paper's Fig. 5 on real links: PSNR against the stream's Mbit/s (left) and against the link's
    round trip (right, a line per rate cap), PSAO and video."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    style = {"psao": ("o", "-", "PSAO"), "video": ("s", "--", "video (H.264)")}
    caps = sorted({r["link"]["mbit"] or 0.0 for r in rows})
    colours = dict(zip(caps, plt.cm.viridis(np.linspace(0.1, 0.8, len(caps)))))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.4))
    for r in rows:
        mk, _, _ = style[r["method"]]
        ax.plot(r["stream_mbit_s"], r["psnr_mean"], mk, color=colours[r["link"]["mbit"] or 0.0], ms=7,
                mfc="none" if r["method"] == "video" else None)
        ax.annotate(f"{r['link']['rtt_ms']:g} ms", (r["stream_mbit_s"], r["psnr_mean"]), fontsize=7,
                    textcoords="offset points", xytext=(4, 3))
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("stream received, Mbit/s (log)")
    ax.set_ylabel("PSNR against RTAO at the current pose, dB")
    ax.set_title("quality against bitrate (labels: link round trip)")
    for method, (mk, ls, name) in style.items():
        for cap in caps:
            sel = sorted((r for r in rows if r["method"] == method and (r["link"]["mbit"] or 0.0) == cap),
                         key=lambda r: r["link"]["rtt_ms"])
            if sel:
                bx.plot([r["link"]["rtt_ms"] for r in sel], [r["psnr_mean"] for r in sel], marker=mk, ls=ls,
                        color=colours[cap], mfc="none" if method == "video" else None,
                        label=f"{name}, {'unlimited' if cap == 0.0 else f'{cap:g} Mbit/s'}")
    bx.set_xlabel("link round trip, ms")
    bx.set_title("quality against latency")
    bx.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def fig5(args, work: Path) -> int:
    """--fig5 (fig5.json): per link of fig5_links, a PSAO client rendering its own frames (as --quality's) and
    the video competitor's frames over a socket through the same link (video_run), each scored against RTAO at
    the current pose (score_psao_runs, score_video_run); the chart fig5_chart. Verdicts: every PSAO client
    connected without a reconnect and with Updates through its window; every video stream delivered frames
    through its window, no faster than its link's rate (VIDEO_CAP_SLACK) and no sooner than its round trip
    (so its frames did cross the link)."""
    from psao.client.render.renderer import FrameRenderer
    from psao.eval.reference import ReferenceSettings
    from psao.scene import load_scene

    scene = load_scene(SCENE)
    stats = work / "stats.jsonl"
    v = Verdicts("bench_links")
    links = fig5_links(args.quick)
    runs, videos = [], []
    with interrupt_on_sigterm(), impaired_link() as link:
        server = start_server(args, ALL_HOSTS, stats)
        try:
            print(f"server: full grid after {server.full_grid_s:.1f} s", flush=True)
            for i, s in enumerate(links):
                runs.append((s, *quality_run(args, scene, link, s, f"ws://{link.host_address}:{server.port}", work,
                                             f"f{i}")))
                print(f"PSAO behind {s.label()}: done", flush=True)
        finally:
            server.close()
        aos = video_frames(scene, int(np.ceil(args.seconds * VIDEO_FPS)))
        for i, s in enumerate(links):
            videos.append((s, video_run(link, s, aos, work, f"f{i}")))
            print(f"video behind {s.label()}: done", flush=True)
    rows = [{"method": "psao", "link": r["link"], "psnr": r["psnr"], "psnr_mean": r["psnr_mean"],
             "stream_mbit_s": r["client"]["stream_mbit_s"], "behind_p50_s": r["client"]["behind_p50_s"],
             "behind_p95_s": r["client"]["behind_p95_s"], "reconnects": r["client"]["reconnects"]}
            for r in score_psao_runs(scene, stats, runs, v)]
    settings = ReferenceSettings(spp=QUALITY_SPP, cache_dir=None)
    print(f"{'video link':<34} {'Mbit/s':>7} {'enc':>5} {'arrived':>9} {'rt p50':>7} {'rt p95':>7}  PSNR dB (mean)")
    with FrameRenderer(scene, QUALITY_SIZE, "ssao") as renderer:
        for s, run in videos:
            r = score_video_run(scene, run, renderer, settings)
            print(f"{s.label():<34} {r['stream_mbit_s']:7.2f} {r['bitrate_mbit']:5.2g} {r['frames_arrived']:4d}/"
                  f"{r['frames_requested']:<4d} {r['round_trip_p50_s']:7.3f} {r['round_trip_p95_s']:7.3f}  "
                  f"{r['psnr_mean']:.2f}", flush=True)
            rows.append({"method": "video", "link": asdict(s), **r})
            v.record(f"video {s.label()}: frames through the window", r["frames_arrived"] >= 2 and len(r["psnr"]) > 0,
                     f"{r['frames_arrived']} of {r['frames_requested']} arrived, {len(r['psnr'])} scored")
            if s.mbit is not None:
                v.check(f"video {s.label()}: received Mbit/s / the link's rate", r["stream_mbit_s"] / s.mbit, "<=",
                        VIDEO_CAP_SLACK)
            v.check(f"video {s.label()}: frame round trip p50 - the link's rtt, s", r["round_trip_p50_s"]
                    - s.rtt_ms / 1e3, ">=", 0.0)
    fig5_chart(rows, args.chart or args.out / "fig5_links.png")
    (args.out / "fig5.json").write_text(json.dumps({
        "scenario": "fig5", "rows": rows, "size": QUALITY_SIZE, "psao_fps": QUALITY_FPS, "video_fps": VIDEO_FPS,
        "video_link_share": VIDEO_LINK_SHARE, "video_max_mbit": VIDEO_MAX_MBIT, "spp": QUALITY_SPP,
        "density": args.density, "tick_hz": args.tick_hz, "seconds": args.seconds}, indent=1))
    return v.exit_code()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_links", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help=f"{len(QUICK)} link settings instead of the whole sweep "
                   f"(--fig5: {len(FIG5_QUICK)})")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--mixed", action="store_true", help=f"scenario: {sum(n for _, _, n in MIXED)} clients at once "
                       "on mixed links (mixed.json) instead of the sweep")
    which.add_argument("--stall", action="store_true", help=f"scenario: a link that stalls for {STALL_S:g} s beside a "
                       "loopback client (stall.json) instead of the sweep")
    which.add_argument("--cap", action="store_true", help=f"scenario: --mixed with psao serve --client-mbit {CAP_MBIT:g} "
                       "(cap.json) instead of the sweep")
    which.add_argument("--deaf", action="store_true", help=f"scenario: a client that stops reading and answering "
                       f"pings for {BAD_S:g} s beside a loopback client (deaf.json) instead of the sweep")
    which.add_argument("--storm", action="store_true", help=f"scenario: {STORM_PER_S:g} connects and drops a second "
                       f"for {BAD_S:g} s beside a loopback client (storm.json) instead of the sweep")
    which.add_argument("--quality", action="store_true", help="scenario: PSNR of clients' own frames against RTAO "
                       "at the current pose, loopback and behind QUALITY_LINKS (quality.json) instead of the sweep")
    which.add_argument("--fig5", action="store_true", help="scenario: the paper's Fig. 5 on real links, PSNR of "
                       "PSAO clients and of the video competitor behind the same links against bitrate and latency "
                       "(fig5.json, fig5_links.png) instead of the sweep; with --quick FIG5_QUICK's links")
    p.add_argument("--no-adapt-rate", action="store_true", help="the sweep, --mixed, --cap: the server runs psao serve "
                   "--no-adapt-rate (no per-client rate estimate: a baseline)")
    p.add_argument("--seconds", type=float, default=10.0, help="measured window per link setting (scenarios: per "
                   "phase), s")
    p.add_argument("--density", type=float, default=256.0)
    p.add_argument("--chart", type=Path, default=None, help="--quality's chart PNG (default OUT/quality.png), --fig5's "
                   "(default OUT/fig5_links.png)")
    p.add_argument("--tick-hz", type=float, default=30.0, help="the server's tick rate")
    p.add_argument("--out", type=Path, default=Path("out") / "bench_links")
    args = p.parse_args(argv)
    if not args.seconds > 0:
        print("bench_links: error: --seconds must be > 0", file=sys.stderr)
        return 2
    if args.no_adapt_rate and (args.stall or args.deaf or args.storm or args.quality or args.fig5):
        print("bench_links: error: --no-adapt-rate is for the sweep, --mixed and --cap", file=sys.stderr)
        return 2
    if args.quick and (args.mixed or args.stall or args.cap or args.deaf or args.storm
                       or args.quality):
        print("bench_links: error: --quick selects link settings of the sweep or --fig5; the other scenarios have "
              "their own", file=sys.stderr)
        return 2
    if why := links_unavailable():
        print(f"SKIPPED bench_links: {why}")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench_links_"))
    try:
        if args.mixed or args.cap:
            extra = [*(["--client-mbit", str(CAP_MBIT)] if args.cap else []), *(["--no-adapt-rate"] if args.no_adapt_rate else [])]
            return mixed(args, work, extra, "cap" if args.cap else "mixed")
        if args.stall:
            return stall(args, work)
        if args.quality:
            return quality(args, work)
        if args.fig5:
            return fig5(args, work)
        if args.deaf or args.storm:
            return bad_client(args, work, "deaf" if args.deaf else "storm")
        return run_sweep(args, work)
    except ServeExited as exc:
        print(f"bench_links: error: psao serve exited: {exc}", file=sys.stderr)
        return 2


def run_sweep(args, work: Path) -> int:
    """The sweep of single links (see the module); links.json."""
    stats = work / "stats.jsonl"
    v = Verdicts("bench_links")
    results = []
    with interrupt_on_sigterm(), impaired_link() as link:
        server = start_server(args, link.host_address, stats, ["--no-adapt-rate"] if args.no_adapt_rate else [])
        try:
            url = server.url
            print(f"server {url}: full grid after {server.full_grid_s:.1f} s; links: {link.namespace}", flush=True)
            alone, t_alone = measure({"loopback": (url, [])}, args.seconds, work, "alone")
            runs = []
            for i, s in enumerate(sweep(args.quick)):
                link.change(s)
                pair, t_from = measure({"link": (url, link.prefix), "loopback": (url, [])}, args.seconds, work, f"s{i}")
                runs.append((s, pair, t_from, link.change(s)))  # the forwarder's counts of this setting
        finally:
            server.close()
    walls = tick_walls(stats)
    base = alone["loopback"].result(t_alone, walls)
    print(header("packets fwd/lost/queue-dropped"))
    print(row("(loopback alone)", base))
    for s, pair, t_from, counts in runs:
        fast, slow = pair["loopback"].result(t_from, walls), pair["link"].result(t_from, walls)
        pk = packets(counts)
        print(row(s.label(), slow, drops(pk)))
        print(row("", fast))
        results.append({"link": asdict(s), "client": asdict(slow), "loopback": asdict(fast), "packets": pk})
        v.record(f"{s.label()}: snapshot, connected, Updates through the window",
                 slow.exit_ok and slow.reconnects == 0 and slow.samples >= 2,
                 f"exit ok {slow.exit_ok}, {slow.reconnects} reconnects, {slow.samples} samples")
        v.check(f"{s.label()}: loopback client's updates/s beside it / alone", fast.updates_per_s / base.updates_per_s,
                ">=", LOOPBACK_KEEP)
        if s == UNIMPAIRED:
            v.check(f"{s.label()}: its updates/s / the loopback client's", slow.updates_per_s / fast.updates_per_s,
                    ">=", FAST_KEEP)
        if s == ISSUE_LINK and args.density == ISSUE_DENSITY:
            v.check(f"{s.label()}: seconds behind the server, p95", slow.behind_p95_s, "<=",
                    ISSUE_LAG_S)
    (args.out / "links.json").write_text(json.dumps({"alone": asdict(base), "runs": results,
                                                     "density": args.density, "tick_hz": args.tick_hz,
                                                     "seconds": args.seconds}, indent=1))
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
