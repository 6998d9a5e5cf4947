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
    end = None if timeout is None else time.time() + timeout
    while not (m := LISTENING.search(err.read_text())):
        assert (end is None or time.time() < end) and proc.poll() is None, err.read_text()
        time.sleep(0.1)
    return m.group(1)
