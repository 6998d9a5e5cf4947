"""Tracer worker processes end with their server, even when it is killed with SIGKILL (no clean-up runs)."""
from __future__ import annotations

import os
import signal
import time

from test_serve_access import start_serve
from serving import HANG_S, wait_full_grid


def children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(entry))
    return out


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_workers_die_when_the_server_is_killed(tmp_path):
    _, proc, err = start_serve(tmp_path, "--animate", "--tick-rays", "1", "--tick-hz", "5")
    try:
        wait_full_grid(proc, err)  # its tick, and the tick's tracer workers, come with the full grid
        workers = children(proc.pid)
        assert workers, "the animated server runs tracer worker processes"
    except BaseException:  # a failed check leaves no server behind
        proc.terminate()
        proc.wait(30)
        raise
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    end = time.time() + HANG_S  # an event (the workers' exit), waited for with a generous bound
    while any(alive(w) for w in workers) and time.time() < end:
        time.sleep(0.1)
    assert not any(alive(w) for w in workers), [w for w in workers if alive(w)]
