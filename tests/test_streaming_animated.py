"""End to end under animation: `psao serve --animate` (rigid and skinned motion, the real server tick)
and real `psao client` processes; after every message a client's mirror, transforms included, equals the
server's state bit for bit (digest logs, as in test_streaming_mirror)."""
from __future__ import annotations

import json
import signal
import subprocess

from serving import HANG_S, server_url
from support.cli import psao_process as psao  # started, not run to completion
from test_streaming_mirror import matched, read_jsonl

SCENE = "builtin:robots"  # skinned walkers (their AO changes every tick) in a room


def test_mirror_bit_exact_under_animation(tmp_path):
    server_log = tmp_path / "server.jsonl"
    err = tmp_path / "server.err"
    # --no-cull: a client's own Update then takes everything pending, so the server logs a state after each one
    # however far behind a loaded machine leaves the client (with culling, the cells outside its view stay
    # pending and few states are logged; culled sends are checked exactly in test_fanout)
    server = psao("serve", SCENE, "--density", "24", "--rays", "8", "--animate", "--tick-rays", "8", "--port", "0",
                  "--tick-hz", "10", "--no-cull", "--digest-log", str(server_log), stdout=subprocess.DEVNULL,
                  stderr=open(err, "w"))
    procs = [server]
    try:
        url = server_url(server, err, 180)
        common = ["--json", "--reconnect-timeout", "30"]
        logs = {k: tmp_path / f"{k}.jsonl" for k in ("plain", "slow", "sparse")}
        plain = psao("client", url, SCENE, "--frames", "40", "--digest-log", str(logs["plain"]), *common)
        slow = psao("client", url, SCENE, "--frames", "10", "--read-delay", "0.4", "--recv-buffer", "4096",
                    "--digest-log", str(logs["slow"]), *common)
        sparse = psao("client", url, SCENE, "--frames", "12", "--digest-log", str(logs["sparse"]), "--digest-every", "4",
                      *common)
        procs += [plain, slow, sparse]
        reports = {}
        for name, p in (("plain", plain), ("slow", slow), ("sparse", sparse)):
            out, _ = p.communicate(timeout=HANG_S)
            assert p.returncode == 0, f"client {name} failed"
            reports[name] = json.loads(out.strip().splitlines()[-1])
        server.send_signal(signal.SIGTERM)
        server.wait(30)
        assert server.returncode == 0
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()

    slog = read_jsonl(server_log)
    # The server logs a state only where the client has nothing pending (drained): the plain client's 40
    # Updates give several such states, the slow and sparse ones at least one
    for name, path in logs.items():
        compared, differ, _ = matched(slog, read_jsonl(path))
        assert differ == 0, f"{name}: {differ} of {compared} mirror states differ from the server"
        assert compared >= (5 if name == "plain" else 1), f"{name}: only {compared} states compared"
    # --digest-every 4: every snapshot chunk, the first Update, then Updates 4, 8 and 12 only
    sparse = read_jsonl(logs["sparse"])
    assert sum(d["tick"] != sparse[0]["tick"] for d in sparse) == 4
    # The stream really carried animation: the state changed from update to update.
    digests = [d["digest"] for d in read_jsonl(logs["plain"])]
    assert len(set(digests)) >= 10
    assert reports["plain"]["updates"] == 40 and reports["plain"]["mirror_cells"] > 100
