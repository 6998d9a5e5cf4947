"""Test helper for `psao serve` subprocesses: the URL it prints once it listens, or any line of its log."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

LOOPBACK = r"127\.0\.0\.1"
# Deadline that only stops a hung test: a working run never reaches it, however loaded the machine (tests
# wait for events and counts, never for speed).
HANG_S = 900.0


def server_url(proc: subprocess.Popen, err: Path, timeout: float | None = None, host: str = LOOPBACK) -> str:
    """The ws:// or wss:// URL, once the server wrote its listening line on `host` (a regular expression)
    to `err`; fails if it exits first or `timeout` seconds pass (None: no deadline of its own, the test's
    timeout applies)."""
    return wait_for_log(proc, err, re.compile(rf"listening on (wss?://{host}:\d+)"), timeout).group(1)


def wait_for_log(proc: subprocess.Popen, err: Path, pattern: re.Pattern, timeout: float | None = None) -> re.Match:
    """The first match of `pattern` in the server's log `err`, once it is there; fails if the server exits
    first or `timeout` seconds pass (None: the test's timeout applies)."""
    end = None if timeout is None else time.time() + timeout
    while not (m := pattern.search(err.read_text())):
        assert (end is None or time.time() < end) and proc.poll() is None, err.read_text()
        time.sleep(0.1)
    return m
