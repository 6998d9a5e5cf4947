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


def spawn(args: list[str], wrap: list[str] = (), **kwargs) -> subprocess.Popen:
    """A `psao` child in its own session (process group), so kill_group takes its workers too; `wrap`: a
    command that execs it (e.g. psao.eval.links.Link.prefix: inside a network namespace).

    An interrupt raised inside Popen (after the fork, while it waits for the exec) would lose the
    child: Popen never returns it, and it runs on in its own session. So interrupts are held while the
    child starts and is registered in _LIVE, and raised after; interrupt_on_sigterm kills the children
    of _LIVE that their owner did not get to kill."""
    with _holding_interrupts():
        proc = subprocess.Popen([*wrap, *psao_command(*args)], start_new_session=True, preexec_fn=_child_setup, **kwargs)
        _LIVE.add(proc)
    return proc


def set_session_nice(pid: int, nice: int) -> bool:
    """Give the session that `pid` leads (a spawn()ed child: a session of its own) the CPU weight of `nice`.
    With the kernel's autogroup scheduling every session is one group that gets an equal share of the CPU
    whatever its processes' nice values (a nice value only weighs a process against the others of its own
    session), so `nice -n` alone does not put a child in a session of its own below its parent's other
    children; the autogroup's own nice (/proc/PID/autogroup) does. False where there is none (no autogroup:
    the process's own nice is what counts)."""
    try:
        Path(f"/proc/{pid}/autogroup").write_text(f"{int(nice)}\n")
    except OSError:
        return False
    return True


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


def listen_pattern(host: str = r"[^\s/]+") -> re.Pattern:
    """`psao serve`'s listening line on `host` (a regular expression): group 1 the ws:// or wss:// URL,
    group 2 its port."""
    return re.compile(rf"listening on (wss?://(?:{host}):(\d+))")


LISTEN_RE = listen_pattern()
# `psao serve`'s line once it serves the full grid (it listens before it has one: psao.server.net.service)
FULL_GRID_RE = re.compile(r"(?:serving|grid replaced by) the full grid")


class ServeExited(EvalError):
    """The server exited before its log showed what was waited for; `returncode`, `log` (its whole log)."""

    def __init__(self, message: str, returncode: int | None, log: str):
        super().__init__(message)
        self.returncode, self.log = returncode, log


class ServeTimeout(EvalError):
    """The server's log did not show what was waited for within the timeout; `log`: its log so far."""

    def __init__(self, message: str, log: str):
        super().__init__(message)
        self.log = log


class LogFollower:
    """A child's log file as it grows, in complete lines (a line being written is left for the next read,
    so a pattern never matches half a port number)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.text = ""  # the complete lines read so far
        self._offset = 0  # bytes of the file in self.text
        self._searched = 0  # characters of self.text that wait_for searched already

    def read(self, final: bool = False) -> str:
        """Read what the file gained; the complete lines so far (final: the writer has exited, a last line
        without its newline counts too)."""
        try:
            with open(self.path, "rb") as f:
                f.seek(self._offset)
                new = f.read()
        except OSError:
            return self.text
        end = len(new) if final else new.rfind(b"\n") + 1
        if end:
            self.text += new[:end].decode(errors="replace")
            self._offset += end
        return self.text

    def search(self, pattern: re.Pattern) -> re.Match | None:
        """The first match of `pattern` in the text after the previous match or failed search (each line is
        searched once, as a whole)."""
        m = pattern.search(self.text, self._searched)
        self._searched = m.end() if m else len(self.text)
        return m

    def wait_for(self, proc: subprocess.Popen, pattern: re.Pattern, timeout: float | None = None,
                 what: str = "psao serve", poll: float = 0.01) -> re.Match:
        """The first match of `pattern` in a line of the log, as soon as that line is there. Raises
        ServeExited when `proc` exits without writing it, ServeTimeout after `timeout` seconds (None: no
        deadline). It only waits for the line: the poll interval is no assumption about speed."""
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            self.read()
            if m := self.search(pattern):
                return m
            if proc.poll() is not None:  # what it wrote before exiting is in the file by now
                self.read(final=True)
                if m := self.search(pattern):
                    return m
                raise ServeExited(f"{what} exited ({proc.returncode}) before its log said {pattern.pattern!r}: "
                                  f"{_tail(self.text)}", proc.returncode, self.text)
            if end is not None and time.monotonic() >= end:
                raise ServeTimeout(f"{what} did not say {pattern.pattern!r} within {timeout:g} s", self.text)
            time.sleep(poll)


def wait_for_log(proc: subprocess.Popen, log_path: Path, pattern: re.Pattern, timeout: float | None = None,
                 what: str = "psao serve") -> re.Match:
    """The first match of `pattern` in a line of the log file `log_path` of a running `proc` (started by the
    caller), once that line is written; see LogFollower.wait_for."""
    return LogFollower(log_path).wait_for(proc, pattern, timeout, what)


@dataclass
class ServerProcess:
    """`psao serve SCENE --port 0 [EXTRA]` started and waited for until it listens (the URL read from its
    log), in its own process group; stopped by close() (or the with block's end), which kills the group.

    By default it listens on 127.0.0.1 (--host), logs stderr and stdout to a temporary file removed on
    close (log() still returns the text afterwards), and close() SIGTERMs the group with a 3 s grace.
    host=None passes no --host (the server's default); log_path keeps the log in that file; log_stdout=False
    sends stdout to /dev/null; stop_signal sends that signal to the server alone (so it stops its tracer
    workers itself) and waits stop_grace seconds before what is left of the group is killed.

        with ServerProcess("builtin:cornell", ["--density", "8"]) as server:
            server.url, server.port, server.listen_s, server.wait_for(re.compile(r"tick \\d+"), 60)
    """

    scene_spec: str
    extra: list[str] = field(default_factory=list)
    start_timeout: float | None = 600.0  # seconds to listen and (until_full_grid) bake (None: no deadline)
    host: str | None = "127.0.0.1"
    log_path: Path | None = None
    log_stdout: bool = True
    cwd: Path | str | None = None
    stop_signal: int | None = None
    stop_grace: float = 3.0
    # start() returns once the full grid is served (the server listens, and answers, before: while it
    # loads and bakes, then with a coarse grid); False: once it listens
    until_full_grid: bool = True
    proc: subprocess.Popen | None = None
    url: str = ""
    started: float = 0.0  # time.perf_counter() just before the process started
    listen_s: float = 0.0  # seconds from the start to the listening line
    full_grid_s: float | None = None  # seconds from the start to the full grid served (until_full_grid)
    _follow: LogFollower | None = field(default=None, repr=False)
    _temporary_log: bool = field(default=False, repr=False)
    _closed_log: str | None = field(default=None, repr=False)

    def command(self) -> list[str]:
        """The `psao` arguments it runs."""
        host = ["--host", self.host] if self.host is not None else []
        return ["serve", self.scene_spec, *host, "--port", "0", *map(str, self.extra)]

    def start(self) -> "ServerProcess":
        """Start the server and wait until it listens, and serves its full grid unless until_full_grid is
        False (ServeExited, ServeTimeout: it is stopped first)."""
        if self.log_path is None:
            fd, name = tempfile.mkstemp(prefix="psao-serve-", suffix=".log")
            os.close(fd)
            self.log_path, self._temporary_log = Path(name), True
        self.log_path = Path(self.log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._follow = LogFollower(self.log_path)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        with open(self.log_path, "w") as log:
            self.started = time.perf_counter()
            self.proc = spawn(self.command(), stdout=log if self.log_stdout else subprocess.DEVNULL,
                              stderr=log, stdin=subprocess.DEVNULL, cwd=self.cwd, env=env)
        try:
            self.url = self.wait_for(LISTEN_RE, self.start_timeout, "before listening").group(1)
            self.listen_s = time.perf_counter() - self.started
            if self.until_full_grid:
                left = None if self.start_timeout is None else max(self.start_timeout - self.listen_s, 0.0)
                self.wait_for(FULL_GRID_RE, left, "before serving its full grid")
                self.full_grid_s = time.perf_counter() - self.started
        except ServeTimeout as exc:
            self.close()
            raise ServeTimeout(f"psao serve {self.scene_spec} did not listen and serve its full grid within "
                               f"{self.start_timeout:.0f} s", exc.log) from None
        except BaseException:
            self.close()
            raise
        return self

    def __enter__(self) -> "ServerProcess":
        return self.start()

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    @property
    def pid(self) -> int:
        return self.proc.pid

    def wait_for(self, pattern: re.Pattern, timeout: float | None = None, when: str = "") -> re.Match:
        """The first match of `pattern` in a line of its log not searched by an earlier wait_for (the
        listening line was one), once written; ServeExited if the server exits first, ServeTimeout after
        `timeout` seconds."""
        try:
            return self._follow.wait_for(self.proc, pattern, timeout, f"psao serve {self.scene_spec}")
        except ServeExited as exc:
            if not when:
                raise
            raise ServeExited(f"psao serve {self.scene_spec} exited ({exc.returncode}) {when}: {_tail(exc.log)}",
                              exc.returncode, exc.log) from None

    def log(self) -> str:
        """Its whole log so far (after close, the log it left)."""
        if self._closed_log is not None:
            return self._closed_log
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

    def stop(self) -> int | None:
        """Stop the server (see the class) and its process group; its exit status. Idempotent."""
        if self.proc is None:
            return None
        grace = self.stop_grace
        if self.stop_signal is not None:
            if self.proc.poll() is None:
                try:
                    self.proc.send_signal(self.stop_signal)
                    self.proc.wait(self.stop_grace)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    pass
            grace = 0.0  # it had its grace: what is left of the group is killed now
        kill_group(self.proc, grace)
        return self.proc.returncode

    def close(self) -> None:
        self.stop()
        if self.log_path is not None and self._temporary_log and self._closed_log is None:
            self._closed_log = self.log()
            try:
                self.log_path.unlink()
            except OSError:
                pass

    def __exit__(self, *exc) -> None:
        self.close()


def run_client(url: str, scene_spec: str, seconds: float, extra: list[str] = (), connect_timeout: float = 300.0,
               wrap: list[str] = ()) -> dict:
    """A headless `psao client URL --json --no-reconnect`, stopped by SIGINT `seconds` after its snapshot
    arrived (seen in its --digest-log; a static scene sends no update at all, so an update count would
    never be reached). The client then prints its statistics and exits. `wrap`: as spawn's."""
    what = f"psao client {url}"
    fd, name = tempfile.mkstemp(prefix="psao-client-", suffix=".jsonl")
    os.close(fd)
    digests = Path(name)
    proc = spawn(["client", url, scene_spec, "--json", "--no-reconnect", "--reconnect-timeout", "20",
                  "--digest-log", str(digests), *extra], wrap=wrap, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
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
