"""A real `psao serve` process and a real `psao client` process on loopback, for the benchmarks that
judge the server by its own statistics (ticks per second, bytes on the wire, time to first snapshot).

    run = serve_and_watch("builtin:courtyard", ["--animate", "--density", "256"], seconds=10)
    run.ticks_per_second, run.bytes_per_second, run.first_snapshot_s

The server is psao.eval.processes.ServerProcess (its own process group, the port read from its log). It
writes one JSON line per tick (--stats-json); the client sends its camera along the scene's
camera path (as `psao client` always does) and reports its own statistics (--json). The window measured
starts when the client has its snapshot and a first Update, and lasts `seconds`. The client logs its
mirror's digest (which is how the first Update is seen) only for the snapshot, the first Update and then
one Update in DIGEST_EVERY: each digest hashes the whole mirror, and one per Update would keep a core of
this machine busy hashing beside the server being measured.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from psao.eval.processes import LISTEN_RE, ServeExited, ServerProcess, ServeTimeout

DIGEST_EVERY = 60  # Updates per digest the client logs after its first Update


@dataclass
class ServedRun:
    scene: str
    serve_args: list[str]
    start_to_listen_s: float  # serve process started -> listening
    first_snapshot_s: float  # serve process started -> the client's first Update (its snapshot is complete)
    window_s: float  # the measured window (service time)
    ticks: int  # ticks the server ran in the window
    bytes_sent: int  # bytes the server sent in the window (all clients; here one)
    client: dict  # the client's own --json report
    records: list[dict] = field(repr=False, default_factory=list)  # the server's per-tick records in the window
    log_tail: str = ""

    @property
    def ticks_per_second(self) -> float:
        return self.ticks / self.window_s if self.window_s > 0 else 0.0

    @property
    def bytes_per_second(self) -> float:
        return self.bytes_sent / self.window_s if self.window_s > 0 else 0.0

    def view_waits(self) -> list[int]:
        """The window's in-view wait histogram (TickStats.view_waits summed; bins of VIEW_WAIT_EDGES_MS)."""
        from psao.server.tick.summary import VIEW_WAIT_EDGES_MS

        total = [0] * (len(VIEW_WAIT_EDGES_MS) + 1)
        for r in self.records:
            for k, c in enumerate(r.get("view_waits") or ()):
                total[k] += c
        return total

    def thirds(self, key: str) -> tuple[float, float]:
        """Mean of `key` over the first and over the last third of the window's records."""
        vals = [r[key] for r in self.records if key in r]
        k = max(len(vals) // 3, 1)
        return (sum(vals[:k]) / k, sum(vals[-k:]) / k) if vals else (0.0, 0.0)

    def mean(self, key: str, among: str | None = None) -> float:
        """Mean of `key` over the window's records that hold it (and a true `among`, when given)."""
        vals = [r[key] for r in self.records if key in r and (among is None or r.get(among))]
        return sum(vals) / len(vals) if vals else 0.0


def serve_and_watch(scene: str, serve_args: list[str], seconds: float, start_timeout: float = 900.0,
                    client_args: list[str] | None = None) -> ServedRun:
    """Start `psao serve SCENE --port 0 ... --stats-json`, connect one `psao client`, keep both running
    `seconds` after the client's first Update, stop both with SIGINT and read the statistics."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with tempfile.TemporaryDirectory() as tmp:
        stats = Path(tmp) / "stats.jsonl"
        digest = Path(tmp) / "client.jsonl"
        server = ServerProcess(scene, ["--stats-json", str(stats), *serve_args], start_timeout=start_timeout,
                               host=None, log_stdout=False, stop_signal=signal.SIGINT, stop_grace=60.0)
        client = None
        try:
            try:
                server.start()
            except ServeExited as exc:
                raise RuntimeError(f"psao serve exited ({exc.returncode}):\n" + _last_lines(exc.log, 20)) from None
            except ServeTimeout:
                raise TimeoutError(f"psao serve did not say {LISTEN_RE.pattern!r} within {start_timeout:g} s") from None
            port = server.port
            listen_s = server.listen_s
            client = subprocess.Popen([sys.executable, "-m", "psao", "client", f"ws://127.0.0.1:{port}", scene,
                                       "--json", "--digest-log", str(digest), "--digest-every", str(DIGEST_EVERY),
                                       *(client_args or [])],
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
            while not _updated(digest):  # a line per snapshot chunk, then per update: wait for an update
                if client.poll() is not None:
                    raise RuntimeError("psao client exited before its snapshot")
                time.sleep(0.02)
            snapshot_s = time.perf_counter() - server.started
            window_start = _last_time(stats)
            time.sleep(seconds)
            window_end = _last_time(stats)
            client.send_signal(signal.SIGINT)
            out, _ = client.communicate(timeout=60)
            report = json.loads(out.strip().splitlines()[-1])
        finally:
            if client is not None and client.poll() is None:
                client.kill()
            server.close()  # SIGINT, up to 60 s to stop, then its process group is killed
        records = [json.loads(x) for x in stats.read_text().splitlines() if x.strip()]
    window = [r for r in records if window_start < r["time"] <= window_end]
    return ServedRun(scene, serve_args, listen_s, snapshot_s, window_end - window_start, len(window),
                     sum(r.get("bytes_sent", 0) for r in window), report, window, server.log()[-3000:])


def _last_lines(text: str, n: int) -> str:
    return "".join(text.splitlines(keepends=True)[-n:])


def _updated(digest: Path) -> bool:
    """Whether the client's digest log shows an Update (its tick differs from the snapshot's lines')."""
    if not digest.exists():
        return False
    lines = [json.loads(x) for x in digest.read_text().splitlines() if x.strip()]
    return any(d["tick"] != lines[0]["tick"] for d in lines)


def _last_time(stats: Path) -> float:
    """Service time of the last tick record written so far (0 before the first)."""
    if not stats.exists():
        return 0.0
    lines = [x for x in stats.read_text().splitlines() if x.strip()]
    return json.loads(lines[-1])["time"] if lines else 0.0
