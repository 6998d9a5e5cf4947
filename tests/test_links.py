"""Impaired links (psao.eval.links): a real `psao serve` and a real `psao client` in a network namespace
behind a link with delay, loss and a rate cap; the link's floors (delay, rate) and its teardown.

Nothing here depends on the machine's speed: the client runs to a count of updates, the link's delay and
rate are floors the forwarder never beats, and the waits are bounded only to stop a hung test.
"""
from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import threading
import time

import pytest
from serving import HANG_S

from psao.eval.links import LinkError, LinkSettings, impaired_link, links_unavailable, namespaces
from psao.eval.processes import ServerProcess, kill_group, spawn

SCENE = "builtin:courtyard"
UNAVAILABLE = links_unavailable()
needs_links = pytest.mark.skipif(UNAVAILABLE is not None, reason=UNAVAILABLE or "")


def read_jsonl(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []


def link_devices() -> str:
    """The host's interfaces, one a line."""
    return subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True).stdout


@pytest.mark.parametrize("settings, field", [
    (LinkSettings(rtt_ms=-1), "rtt_ms"),
    (LinkSettings(loss=1.0), "loss"),
    (LinkSettings(loss=-0.1), "loss"),
    (LinkSettings(mbit=0), "mbit"),
    (LinkSettings(mbit=-5), "mbit"),
    (LinkSettings(rtt_ms=float("nan")), "rtt_ms"),
])
def test_bad_settings_are_one_clear_error(settings, field):
    with pytest.raises(ValueError) as err:
        settings.check()
    assert isinstance(err.value, LinkError) and field in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(LinkError, match=field):  # refused before anything is made
        with impaired_link(settings):
            pass


def test_forwarder_refuses_bad_settings_in_one_line():
    proc = subprocess.run([sys.executable, "-m", "psao.eval.linkrelay", "a", "b", "--loss", "1.5", "--queue-ms", "100"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "loss" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr


@needs_links
def test_teardown_leaves_nothing_behind_also_after_an_error():
    with pytest.raises(RuntimeError):
        with impaired_link(LinkSettings(rtt_ms=10)) as link:
            assert link.namespace in namespaces()
            assert f" {link.host_device}:" in link_devices() and link.host_address != link.ns_address
            # the namespace sees its end of the link
            shown = subprocess.run(link.command(["ip", "-o", "-4", "addr", "show"]), capture_output=True,
                                   text=True, timeout=60).stdout
            assert link.ns_address in shown and link.host_address not in shown
            raise RuntimeError("boom")
    assert link.namespace not in namespaces()
    assert f" {link.host_device}:" not in link_devices()


def _receive_all(link, port: int, nbytes: int) -> dict:
    """Inside the namespace: connect to the host's end, read `nbytes`; the connect and transfer seconds."""
    code = f"""
import json, socket, time
t0 = time.monotonic()
s = socket.create_connection(({link.host_address!r}, {port}), timeout=60)
t1 = time.monotonic()
n = 0
while n < {nbytes}:
    d = s.recv(1 << 16)
    if not d:
        break
    n += len(d)
print(json.dumps({{"connect_s": t1 - t0, "transfer_s": time.monotonic() - t1, "bytes": n}}))
"""
    out = subprocess.run(link.command([sys.executable, "-c", code]), capture_output=True, text=True, timeout=HANG_S)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@needs_links
def test_link_delay_and_rate_are_floors():
    settings = LinkSettings(rtt_ms=200, mbit=8)
    nbytes = 1_000_000
    with impaired_link(settings) as link:
        srv = socket.create_server((link.host_address, 0))
        port = srv.getsockname()[1]

        def serve():
            conn, _ = srv.accept()
            with conn:
                conn.sendall(b"\0" * nbytes)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        got = _receive_all(link, port, nbytes)
        thread.join(HANG_S)
        srv.close()
    assert got["bytes"] == nbytes
    assert got["connect_s"] >= 0.2  # SYN out, SYN-ACK back: one round trip
    # the payload (its headers on top) at 8 Mbit/s; the connection's last packet needs half a round trip
    assert got["transfer_s"] >= nbytes * 8 / 8e6
    assert link.counters["down"]["forwarded"] > nbytes // 1500 and link.counters["up"]["forwarded"] > 0




@needs_links
def test_video_frames_cross_the_link_whole_and_no_sooner_than_its_round_trip(tmp_path):
    """The video competitor's frames over psao.eval.videolink: every frame asked for arrives with the packets
    the server sent, each no sooner than the link's round trip after its request, and no faster than its rate."""
    from psao.eval.videolink import VideoLinkServer, read_receive_log

    settings = LinkSettings(rtt_ms=120, mbit=2)
    frames = [[bytes([k]) * (20000 + 97 * k), bytes([255 - k]) * 11] for k in range(24)]
    log_path = tmp_path / "video.json"
    with impaired_link(settings) as link, VideoLinkServer(frames, link.host_address) as server:
        proc = subprocess.run(link.command([sys.executable, "-m", "psao.eval.videolink", link.host_address,
                                            server.port, "--fps", "30", "--frames", len(frames), "--out", log_path]),
                              capture_output=True, text=True, timeout=HANG_S)
    assert proc.returncode == 0, proc.stderr
    log = read_receive_log(log_path)
    assert log.arrived == len(frames) and log.packets == frames
    trips = [a - r for r, a in zip(log.requests, log.arrivals)]
    assert min(trips) >= 0.12  # the request up, the frame down: a round trip at least
    payload = sum(len(p) for ps in frames for p in ps)
    # the frames after the first at 2 Mbit/s: longer than the requests take (24 at 30 fps), so the rate shows
    assert log.arrivals[-1] - log.arrivals[0] >= (payload - sum(map(len, frames[0]))) * 8 / 2e6


LEFT = re.compile(r"left \(said Bye\).*link-limited in (?P<windows>\d+) windows, at (?P<link>[-0-9.]+)")


def _client_behind(link, server_log, client_log, frames: int) -> tuple[str, re.Match]:
    """`psao serve` of the animated courtyard (density 64, 20 Hz, --no-cull) on the host's end of `link`, and
    a `psao client` in its namespace for `frames` updates; its stdout, and the server's line on its leaving."""
    with ServerProcess(SCENE, ["--density", "64", "--animate", "--tick-hz", "20", "--no-cull",
                               "--digest-log", server_log],
                       host=link.host_address, start_timeout=HANG_S) as server:
        client = spawn(["client", server.url, SCENE, "--frames", str(frames), "--json", "--no-reconnect",
                        "--reconnect-timeout", "60", "--digest-log", client_log],
                       wrap=link.prefix, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            out, err = client.communicate(timeout=HANG_S)
        finally:
            kill_group(client)
        assert client.returncode == 0, err
        return out, server.wait_for(LEFT, HANG_S, "the client's leaving")


@needs_links
@pytest.mark.slow
def test_client_behind_an_impaired_link_keeps_an_exact_mirror(tmp_path):
    """rtt 100 ms, 1% loss, 5 Mbit/s: the client gets its snapshot and 60 updates, every mirror digest it
    logs equals the server's for the same message, and the link did drop packets. The server logs its state
    only after a message that leaves the client nothing pending (--no-cull: nothing waits for the view),
    which depends on the machine's speed: a few such states at least."""
    server_log, client_log = tmp_path / "server.jsonl", tmp_path / "client.jsonl"
    with impaired_link(LinkSettings(rtt_ms=100, loss=0.01, mbit=5)) as link:
        out, _ = _client_behind(link, server_log, client_log, 60)
    report = json.loads(out.strip().splitlines()[-1])
    assert report["snapshot_bytes"] > 0 and report["updates"] == 60 and report["reconnects"] == 0
    ours = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(server_log)}
    theirs = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(client_log)}
    compared = ours.keys() & theirs.keys()
    differ = [k for k in compared if ours[k] != theirs[k]]
    assert len(compared) >= 5 and not differ, f"{len(differ)} of {len(compared)} mirror states differ"
    dropped = sum(link.counters[d]["dropped_loss"] for d in ("down", "up"))
    forwarded = sum(link.counters[d]["forwarded"] for d in ("down", "up"))
    assert dropped > 0 and forwarded > 100 * dropped / 3  # about 1% of the packets, far from all


@needs_links
def test_a_live_link_changes_its_settings():
    with impaired_link() as link:
        srv = socket.create_server((link.host_address, 0))
        port = srv.getsockname()[1]
        threading.Thread(target=lambda: srv.accept()[0].close(), daemon=True).start()
        before = link.change(LinkSettings(rtt_ms=300))
        assert set(before) == {"down", "up"}
        assert _receive_all(link, port, 1)["connect_s"] >= 0.3
        with pytest.raises(LinkError, match="loss"):
            link.change(LinkSettings(loss=2))
        assert link.settings.rtt_ms == 300
        srv.close()


@needs_links
def test_a_killed_owner_leaves_nothing_for_long():
    """The owner of a link SIGKILLed: its forwarder exits (its stdin ends), taking its devices, and the next
    impaired_link deletes the namespace it left."""
    code = ("import sys, time; from psao.eval.links import impaired_link\n"
            "with impaired_link() as link:\n"
            "    print(link.namespace, link.host_device, flush=True); time.sleep(600)\n")
    owner = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        name, device = owner.stdout.readline().split()
    finally:
        owner.kill()
        owner.wait(60)
    end = time.monotonic() + HANG_S
    while f" {device}:" in link_devices() and time.monotonic() < end:
        time.sleep(0.05)
    assert f" {device}:" not in link_devices()
    with impaired_link():  # (a test running beside this one may have deleted it already)
        assert name not in namespaces()


@needs_links
def test_links_are_unique_and_concurrent():
    with impaired_link() as a, impaired_link() as b:
        assert a.namespace != b.namespace and a.host_address != b.host_address
        assert {a.namespace, b.namespace} <= set(namespaces())
    assert not {a.namespace, b.namespace} & set(namespaces())


@pytest.mark.parametrize("argv", [["--quick", "--mixed"], ["--quick", "--cap"], ["--stall", "--seconds", "0"],
                                  ["--quick", "--deaf"], ["--quick", "--storm"], ["--quick", "--quality"],
                                  ["--no-adapt-rate", "--stall"], ["--no-adapt-rate", "--fig5"]])
def test_bench_links_refuses_bad_options_in_one_line(argv, capsys):
    from benchmarks.bench_links import main

    assert main(argv) == 2  # refused before any link or server is made
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_cpu_seconds_count_a_process_and_its_children():
    """bench_links.cpu_seconds (its CpuMeter's reading): a shell whose child spins is charged the child's CPU."""
    from benchmarks.bench_links import cpu_seconds

    proc = subprocess.Popen(["sh", "-c", f"{sys.executable} -c 'while True: pass' & wait"], start_new_session=True)
    try:
        end = time.monotonic() + HANG_S
        while cpu_seconds(proc.pid) < 0.3 and time.monotonic() < end:
            time.sleep(0.05)
        assert cpu_seconds(proc.pid) >= 0.3  # the shell itself only waits
    finally:
        kill_group(proc)
    assert cpu_seconds(proc.pid) == 0.0  # gone: nothing to read


@pytest.mark.skipif(not os.path.exists("/proc/self/autogroup"), reason="no autogroup scheduling here")
def test_a_spawned_client_session_gets_the_nice_it_is_given():
    from psao.eval.processes import set_session_nice

    proc = subprocess.Popen(["sleep", "30"], start_new_session=True)
    try:
        assert set_session_nice(proc.pid, 7)
        group, _, nice = open(f"/proc/{proc.pid}/autogroup").read().split()
        # The file is empty for a process in the root group (a session never set up since boot, as in some
        # CI containers); the child's group is its own session's either way.
        own_group = (open("/proc/self/autogroup").read().split() or ["root"])[0]
        assert nice == "7" and group != own_group
    finally:
        proc.kill()
        proc.wait()


def test_bench_links_runs_one_scenario_at_a_time():
    from benchmarks.bench_links import main

    with pytest.raises(SystemExit) as exc:
        main(["--mixed", "--stall"])
    assert exc.value.code == 2


@needs_links
@pytest.mark.slow
def test_a_client_behind_a_slow_link_gets_an_estimate_near_its_rate_and_an_exact_mirror(tmp_path):
    """0.5 Mbit/s and rtt 50 ms, under what the animated courtyard's stream takes: without --client-mbit the
    server finds the link queueing and estimates what it carries (the websocket bytes the client was shown
    to read: at most the link's rate, which also carries the headers), and every mirror digest the client
    logs equals the server's. The bounds are the link's, not the machine's: a loaded machine sends no
    faster than the link carries, and the snapshot alone keeps the link full for seconds."""
    mbit = 0.5
    server_log, client_log = tmp_path / "server.jsonl", tmp_path / "client.jsonl"
    with impaired_link(LinkSettings(rtt_ms=50, mbit=mbit)) as link:
        out, left = _client_behind(link, server_log, client_log, 40)
    assert json.loads(out.strip().splitlines()[-1])["updates"] == 40
    assert int(left["windows"]) > 0 and left["link"] != "-", left.group(0)
    assert 0.5 * mbit <= float(left["link"]) <= 1.05 * mbit, left.group(0)
    ours = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(server_log)}
    theirs = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(client_log)}
    compared = ours.keys() & theirs.keys()
    assert len(compared) >= 3 and all(ours[k] == theirs[k] for k in compared)


def test_a_reconnect_storm_leaves_a_client_its_stream_and_an_exact_mirror(tmp_path):
    """bench_links.Storm (connections opened and reset, STORM_PER_S a second) on a real server: once it has
    opened 20, a real client beside it gets its snapshot and 40 Updates, every mirror digest it logs equals
    the server's, and the server serves on."""
    from benchmarks.bench_links import Storm

    server_log, client_log = tmp_path / "server.jsonl", tmp_path / "client.jsonl"
    with ServerProcess(SCENE, ["--density", "16", "--animate", "--no-cull", "--digest-log", server_log],
                       start_timeout=HANG_S) as server:
        storm = Storm(server.url)
        try:
            end = time.monotonic() + HANG_S
            while storm.opened < 20 and time.monotonic() < end:
                time.sleep(0.05)
            assert storm.opened >= 20, f"{storm.opened} opened, {storm.failed} failed"
            client = spawn(["client", server.url, SCENE, "--frames", "40", "--json", "--no-reconnect",
                            "--digest-log", client_log], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            try:
                out, err = client.communicate(timeout=HANG_S)
            finally:
                kill_group(client)
        finally:
            storm.stop()
        assert client.returncode == 0, err
        assert server.alive(), server.log()
    assert json.loads(out.strip().splitlines()[-1])["updates"] == 40
    ours = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(server_log)}
    theirs = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(client_log)}
    compared = ours.keys() & theirs.keys()
    assert compared and all(ours[k] == theirs[k] for k in compared)
