"""Test helper for `psao serve` subprocesses: the URL it prints once it listens."""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

LISTENING = re.compile(r"listening on (ws://127\.0\.0\.1:\d+)")


def server_url(proc: subprocess.Popen, err: Path, timeout: float | None = None) -> str:
    """Wait until the server writes its listening line to `err`; fails if it exits first or `timeout`
    seconds pass (None: no deadline of its own, the test's timeout applies)."""
    return wait_for_log(proc, err, LISTENING, timeout).group(1)


def wait_for_log(proc: subprocess.Popen, err: Path, pattern: re.Pattern, timeout: float | None = None) -> re.Match:
    """The first match of `pattern` in the server's log `err`, once it is there; fails if the server exits
    first or `timeout` seconds pass (None: the test's timeout applies)."""
    end = None if timeout is None else time.time() + timeout
    while not (m := pattern.search(err.read_text())):
        assert (end is None or time.time() < end) and proc.poll() is None, err.read_text()
        time.sleep(0.1)
    return m
