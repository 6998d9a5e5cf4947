"""Real `psao` processes for benchmarks: bake, serve, client.

Every child runs in its own session (process group), so its Embree worker processes go with it: the
`ServerProcess` context manager kills the whole group on exit, on errors and on Ctrl-C alike, and a
benchmark never leaves a server behind.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from psao.eval.errors import EvalError

LISTEN_RE = re.compile(r"listening on (ws://[\w.\-]+:\d+)")
STATS_RE = re.compile(r"tick (\d+) \| ([\d.]+) ticks/s \| tick load (\d+)%")


def psao_command(*args: str) -> list[str]:
    """The `psao` CLI of this interpreter (works without the console script on PATH)."""
    return [sys.executable, "-m", "psao.cli", *map(str, args)]


def _child_setup() -> None:
    """In the child before exec: SIGINT back to its default (a parent started in the background has it
    ignored, and ignored signals survive exec; the client stops on SIGINT), and TERM likewise."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


class _Starting:
    """Interrupt signals that arrive while a child is being started are held here (see spawn)."""
    depth = 0  # spawns in progress
    pending: int | None = None  # the first signal that arrived during them


_LIVE: set[subprocess.Popen] = set()  # children spawned and not yet killed by kill_group


@contextlib.contextmanager
def _holding_interrupts():
    """While inside, interrupt_on_sigterm's handler records a signal instead of raising; on the way out
    the held signal is raised as KeyboardInterrupt (a child started meanwhile is in _LIVE by then)."""
    _Starting.depth += 1
    try:
        yield
    finally:
        _Starting.depth -= 1
        if _Starting.depth == 0 and _Starting.pending is not None:
            signum, _Starting.pending = _Starting.pending, None
            raise KeyboardInterrupt(signal.Signals(signum).name)


def spawn(args: list[str], **kwargs) -> subprocess.Popen:
    """A `psao` child in its own session (process group), so kill_group takes its workers too.

    An interrupt raised inside Popen (after the fork, while it waits for the exec) would lose the
    child: Popen never returns it, and it runs on in its own session. So interrupts are held while the
    child starts and is registered in _LIVE, and raised after; interrupt_on_sigterm kills the children
    of _LIVE that their owner did not get to kill."""
    with _holding_interrupts():
        proc = subprocess.Popen(psao_command(*args), start_new_session=True, preexec_fn=_child_setup, **kwargs)
        _LIVE.add(proc)
    return proc


def kill_group(proc: subprocess.Popen, grace: float = 3.0) -> None:
    """SIGTERM the child's process group, wait up to `grace` s, then SIGKILL whatever is left."""
    _LIVE.discard(proc)
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            pass
    try:  # workers may outlive their parent: the group goes in any case
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    if proc.poll() is None:
        proc.wait(5.0)


@contextlib.contextmanager
def interrupt_on_sigterm():
    """While inside: SIGTERM and SIGHUP (and SIGINT, unless it is ignored or handled elsewhere) raise
    KeyboardInterrupt in the main thread, so the `finally` blocks that kill child servers run when a
    benchmark itself is terminated (the default action would skip them). A signal that arrives while
    spawn starts a child is raised once the child is registered; on the way out, children spawned
    inside and not killed yet are killed. The previous handlers come back on exit."""
    def handler(signum, _frame):
        if _Starting.depth:
            _Starting.pending = _Starting.pending or signum
            return
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signals = [signal.SIGTERM, signal.SIGHUP]
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signals.append(signal.SIGINT)
    before = set(_LIVE)
    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield
    finally:
        try:
            for proc in _LIVE - before:
                kill_group(proc)
        finally:
            for sig, h in previous.items():
                signal.signal(sig, h)


def last_json_line(text: str, what: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                break
    raise EvalError(f"{what} printed no JSON result")


def _tail(text: str, lines: int = 3) -> str:
    got = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return " | ".join(got[-lines:]) or "(no output)"


def run_cli(args: list[str], what: str, timeout: float) -> dict:
    """Run a `psao ...` command in its own process group to completion; its --json result."""
    proc = spawn(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise EvalError(f"{what} did not finish within {timeout:.0f} s") from None
    finally:
        kill_group(proc)
    if proc.returncode != 0:
        raise EvalError(f"{what} failed (exit {proc.returncode}): {_tail(err)}")
    return last_json_line(out, what)


def bake_grid(scene_spec: str, settings, out: Path, timeout: float = 1800.0) -> dict:
    """`psao bake SCENE [bake options of settings] --out FILE --json` (no accuracy probes); its statistics."""
    from psao.server.cli.bake import bake_arguments

    return run_cli(["bake", scene_spec, *bake_arguments(settings), "--probes", "0", "--out", str(out), "--json"],
                   f"psao bake {scene_spec} at N={settings.density:g}", timeout)


@dataclass
class ServerProcess:
    """`psao serve` on 127.0.0.1 with a free port (--port 0; the URL is read from its log)."""

    scene_spec: str
    extra: list[str] = field(default_factory=list)
    start_timeout: float = 600.0  # seconds to bake/load and listen
    proc: subprocess.Popen | None = None
    url: str = ""
    log_path: Path | None = None

    def __enter__(self) -> "ServerProcess":
        fd, name = tempfile.mkstemp(prefix="psao-serve-", suffix=".log")
        self.log_path = Path(name)
        with os.fdopen(fd, "w") as log:
            self.proc = spawn(["serve", self.scene_spec, "--host", "127.0.0.1", "--port", "0", *self.extra],
                              stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        try:
            self.url = self._wait_listening()
        except BaseException:
            self.close()
            raise
        return self

    def _wait_listening(self) -> str:
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            m = LISTEN_RE.search(self.log())
            if m:
                return m.group(1)
            if self.proc.poll() is not None:
                raise EvalError(f"psao serve {self.scene_spec} exited ({self.proc.returncode}) before listening: "
                                f"{_tail(self.log())}")
            time.sleep(0.1)
        raise EvalError(f"psao serve {self.scene_spec} did not listen within {self.start_timeout:.0f} s")

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace") if self.log_path else ""
        except OSError:
            return ""

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def tick_ms(self) -> float:
        """Mean server milliseconds per tick from its live statistics lines (busy fraction / tick rate);
        NaN when it logged none."""
        loads = [(float(rate), float(load) / 100.0) for _, rate, load in STATS_RE.findall(self.log())]
        loads = [(r, b) for r, b in loads if r > 0]
        if not loads:
            return float("nan")
        return 1e3 * sum(b for _, b in loads) / sum(r for r, _ in loads)

    def close(self) -> None:
        if self.proc is not None:
            kill_group(self.proc)
        if self.log_path is not None:
            try:
                self.log_path.unlink()
            except OSError:
                pass

    def __exit__(self, *exc) -> None:
        self.close()


def run_client(url: str, scene_spec: str, seconds: float, extra: list[str] = (), connect_timeout: float = 300.0) -> dict:
    """A headless `psao client URL --json --no-reconnect`, stopped by SIGINT `seconds` after its snapshot
    arrived (seen in its --digest-log; a static scene sends no update at all, so an update count would
    never be reached). The client then prints its statistics and exits."""
    what = f"psao client {url}"
    fd, name = tempfile.mkstemp(prefix="psao-client-", suffix=".jsonl")
    os.close(fd)
    digests = Path(name)
    proc = spawn(["client", url, scene_spec, "--json", "--no-reconnect", "--reconnect-timeout", "20",
                  "--digest-log", str(digests), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t_snapshot = _wait_for_snapshot(proc, digests, connect_timeout, what)
        try:
            proc.wait(seconds)  # returns early when the client stops by itself (a lost server)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30.0)
        except subprocess.TimeoutExpired:
            raise EvalError(f"{what} did not stop on SIGINT") from None
        # The stream's window: from the snapshot to the last message the client logged. The client's
        # own `seconds` also counts its shutdown (closing the websocket can take seconds), which
        # would dilute the rate.
        t_last = digests.stat().st_mtime
    finally:
        kill_group(proc)
        digests.unlink(missing_ok=True)
    if proc.returncode not in (0, 130, -signal.SIGINT):
        raise EvalError(f"{what} failed (exit {proc.returncode}): {_tail(err)}")
    stats = last_json_line(out, what)
    if not stats.get("snapshot_bytes"):
        raise EvalError(f"{what} received no snapshot: {_tail(err)}")
    stats["window_seconds"] = max(t_last - t_snapshot, 1e-3) if stats.get("updates") else float(seconds)
    return stats


def _wait_for_snapshot(proc: subprocess.Popen, digests: Path, timeout: float, what: str) -> float:
    """Wall-clock time (time.time(), as file times) at which the client logged its snapshot."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if digests.stat().st_size > 0:
            return digests.stat().st_mtime
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            raise EvalError(f"{what} exited ({proc.returncode}) before its snapshot: {_tail(err)}")
        time.sleep(0.05)
    raise EvalError(f"{what}: no snapshot within {timeout:.0f} s")


def client_has_render() -> bool:
    """Whether this `psao client` can render frames (--render), i.e. the streaming renderer is wired in."""
    try:
        out = subprocess.run(psao_command("client", "--help"), capture_output=True, text=True, timeout=60).stdout
    except (OSError, subprocess.TimeoutExpired):
        return False
    return "--render" in out


def welcome_bytes(scene) -> int:
    """Size of the server's Welcome for this scene (sent uncompressed before the snapshot: the client
    counts it in bytes_received, it is not part of the stream after the snapshot). Its size depends on
    the instance count only."""
    import numpy as np

    from psao.protocol import messages as m
    from psao.protocol.codecs import Codec
    from psao.protocol.gridformat import INSTANCE_DTYPE
    from psao.protocol.session import scene_hash_bytes
    from psao.protocol.updates import Layout

    msg = m.Welcome(scene_hash_bytes(scene.content_hash()), 1, Codec.NONE, Layout.PACKED, 60.0, 0, 0,
                    np.zeros(len(scene.instances), INSTANCE_DTYPE))
    return len(m.encode(msg))


def stream_rates(stats: dict, welcome: int = 0) -> dict:
    """Bandwidth figures from the client's statistics: the snapshot and the steady stream after it
    (everything else the client received, less the Welcome)."""
    total = float(stats.get("bytes_received", 0)) - welcome
    snap = float(stats.get("snapshot_bytes", 0))
    seconds = float(stats.get("seconds", 0.0))
    snap_s = float(stats.get("snapshot_seconds") or 0.0)
    steady_s = float(stats.get("window_seconds") or max(seconds - snap_s, 1e-9))
    return {
        "snapshot_mb": snap / 1e6,
        "snapshot_s": snap_s,
        "stream_mbit_s": (total - snap) * 8.0 / 1e6 / steady_s,
        "updates": int(stats.get("updates", 0)),
        "updates_per_s": float(stats.get("updates", 0)) / steady_s,
    }
