"""Test helper for `psao serve` subprocesses: the URL it prints once it listens, or any line of its log.

The waiting is psao.eval.processes' (the benchmarks' harness too); here a failure is an assertion that
shows the server's log."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from psao.eval.processes import FULL_GRID_RE, ServeExited, ServeTimeout, listen_pattern
from psao.eval.processes import wait_for_log as _wait_for_log

LOOPBACK = r"127\.0\.0\.1"
# Deadline that only stops a hung test: a working run never reaches it, however loaded the machine (tests
# wait for events and counts, never for speed).
HANG_S = 900.0


def server_url(proc: subprocess.Popen, err: Path, timeout: float | None = None, host: str = LOOPBACK) -> str:
    """The ws:// or wss:// URL, once the server wrote its listening line on `host` (a regular expression)
    to `err`; fails if it exits first or `timeout` seconds pass (None: no deadline of its own, the test's
    timeout applies)."""
    return wait_for_log(proc, err, listen_pattern(host), timeout).group(1)


def wait_for_log(proc: subprocess.Popen, err: Path, pattern: re.Pattern, timeout: float | None = None) -> re.Match:
    """The first match of `pattern` in a line of the server's log `err`, once it is there; fails if the
    server exits first or `timeout` seconds pass (None: the test's timeout applies)."""
    try:
        return _wait_for_log(proc, Path(err), pattern, timeout)
    except (ServeExited, ServeTimeout) as exc:
        raise AssertionError(f"{exc}\n{exc.log}") from None


def wait_full_grid(proc: subprocess.Popen, err: Path, timeout: float | None = None) -> None:
    """Once the server serves its full grid (it listens, and answers, before: while it loads and bakes)."""
    wait_for_log(proc, err, FULL_GRID_RE, timeout)
