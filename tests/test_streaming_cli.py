"""`psao serve` and `psao client` as commands: one-line errors, refusals, clean shutdown on SIGINT."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from serving import HANG_S, server_url
from support.cli import one_line_error, psao

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args, text", [
    (["--tick-hz", "100"], "tick rate must be within 5..60"),
    (["--density", "0"], "density must be a finite number > 0"),
    (["--test-edits", "-1"], "--test-edits must be >= 0"),
    (["--grid", "/nonexistent/grid.npz"], "not a PSAO grid file"),
    (["--tick-hz", "nan"], "tick rate must be within 5..60"),
    (["--animate", "--tick-budget-ms", "nan"], "tick budget must be within (0, 16.6667] ms"),
    (["--animate", "--tick-budget-ms", "0"], "tick budget must be within (0, 16.6667] ms"),
    (["--progressive", "--tick-budget-ms", "30"], "tick budget must be within (0, 16.6667] ms"),
    (["--animate", "--tick-rays", "0"], "round rays must divide the tick's rays (128)"),
    (["--animate", "--rays", "8", "--tick-rays", "16"], "round rays must divide the tick's rays (8)"),
    (["--workers", "-1"], "workers must be >= 0"),
    (["--no-progressive", "--tick-budget-ms", "5"], "need --animate, --progressive or --allow-edits"),
])
def test_serve_bad_settings(args, text):
    one_line_error(psao("serve", "builtin:cornell", "--port", "0", *args), text)


def test_animate_needs_its_own_bake():
    one_line_error(psao("serve", "builtin:cornell", "--port", "0", "--animate", "--grid", "x.npz"),
                   "cannot serve a --grid file")


def serve_with_client(tmp_path, serve_args, client_args) -> tuple[str, list[tuple[str, str]], list[dict], dict]:
    """Run `psao serve ... --port 0 --json` with digest and stats logs, one `psao client` against it, stop
    the server with SIGTERM. Returns the server's log, (server digest, client digest) pairs of the messages
    both logged, the per-tick stats records and the server's final JSON line."""
    err, slog, clog, stats = (tmp_path / n for n in ("serve.err", "server.jsonl", "client.jsonl", "stats.jsonl"))
    proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", *serve_args, "--port", "0", "--digest-log", str(slog),
                             "--stats-json", str(stats), "--json"], cwd=ROOT, stdout=subprocess.PIPE, stderr=open(err, "w"),
                            text=True)
    try:
        url = server_url(proc, err, 120)
        out = psao("client", url, *client_args, "--json", "--digest-log", str(clog))
        assert out.returncode == 0, out.stderr
        proc.send_signal(signal.SIGTERM)
        final, _ = proc.communicate(timeout=HANG_S)
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    server = {(d["conn"], d["seq"]): d["digest"] for d in map(json.loads, slog.read_text().splitlines())}
    client = [json.loads(line) for line in clog.read_text().splitlines()]
    pairs = [(server[(d["conn"], d["seq"])], d["digest"]) for d in client if (d["conn"], d["seq"]) in server]
    return (err.read_text(), pairs, [json.loads(line) for line in stats.read_text().splitlines()],
            json.loads(final.splitlines()[-1]))


def test_animated_server_keeps_mirror_exact(tmp_path):
    """The real server tick (animation, selection by the client's camera, re-tracing) behind the service;
    every change sent (--no-cull), so that every Update leaves the mirror equal to the whole state."""
    log, pairs, ticks, final = serve_with_client(tmp_path, ["builtin:courtyard", "--animate", "--density", "8", "--rays",
                                                            "4", "--tick-rays", "4", "--tick-hz", "20", "--no-cull"],
                                                 ["--frames", "30"])
    assert len(pairs) >= 25 and all(a == b for a, b in pairs)
    assert "server tick on" in log
    # Per-tick statistics as JSON lines: stage times, and what was sent since the previous tick.
    assert len(ticks) >= 10
    for key in ("considered", "traced", "changed", "cells_dirty", "cells_sent", "bytes_sent", "seconds_animate",
                "seconds_trace", "seconds_grid", "seconds_encode", "queue", "queue_oldest_ms", "budget_ms", "budget_used",
                "service_ms"):
        assert all(key in t and t[key] >= 0 for t in ticks), key
    assert any(t["service_ms"] > 0 for t in ticks)  # the service tells the budget what it spends a tick
    assert sum(t["bytes_sent"] for t in ticks) == ticks[-1]["bytes_out"] > 0
    assert sum(t["cells_sent"] for t in ticks) > 0
    # serve --json: the run's totals and the per-tick records summed up (the same ticks as the jsonl).
    s = final["tick_stats"]
    # two connections: the client fetched the scene (it was given none), then streamed
    assert final["stopped_by"] == "SIGTERM" and final["connections"] == 2 and final["updates_out"] >= 30
    assert s["ticks"] == len(ticks) == final["ticks"] and s["clients_peak"] == 1
    for key in ("bytes_sent", "cells_sent", "cells_dirty", "traced", "changed"):
        assert s[key] == sum(t[key] for t in ticks), key
    ms = sorted(1e3 * t["seconds_tick"] for t in ticks)
    assert s["tick_ms_mean"] == pytest.approx(sum(ms) / len(ms)) and s["tick_ms_max"] == pytest.approx(ms[-1])
    assert ms[0] <= s["tick_ms_p95"] <= ms[-1] and s["tick_ms_p95"] >= ms[len(ms) // 2]
    assert s["ticks_per_s"] == pytest.approx((len(ticks) - 1) / (ticks[-1]["time"] - ticks[0]["time"]))
    assert 0 < s["budget_used_mean"]


def test_progressive_server_streams_a_few_ray_grid_then_refines_it(tmp_path):
    """--progressive: the first grid is traced with --tick-rays, the ticks and the bake's tracer beside them
    refine it towards --rays (writing the improvements into the grid the service streams); the client's mirror is exact and the queue
    only shrinks (nothing moves). How far the refinement got when the client connects depends on the
    machine: the snapshot is what is sure to come."""
    log, pairs, ticks, _ = serve_with_client(tmp_path, ["builtin:cornell", "--progressive", "--density", "32", "--rays", "16",
                                                     "--tick-rays", "2", "--tick-budget-ms", "1", "--tick-hz", "20"],
                                          ["builtin:cornell", "--frames", "0"])
    assert "with 2 rays" in log
    assert len(pairs) >= 1 and all(a == b for a, b in pairs)
    queue = [t["queue"] for t in ticks]
    assert queue[0] > 0 and all(b <= a for a, b in zip(queue, queue[1:]))
    # a tick whose waiting points are all out on the refiner (the bake's tracer, beside the ticks) traces none
    assert sum(t["traced"] for t in ticks) > 0 and sum(t["changed"] for t in ticks) > 0


def test_serve_port_taken():
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        one_line_error(psao("serve", "builtin:cornell", "--density", "8", "--rays", "1", "--port", str(port)),
                       f"cannot listen on 127.0.0.1:{port}")


def test_serve_unknown_scene():
    one_line_error(psao("serve", "builtin:nope", "--port", "0"), "unknown scene")


def test_client_cannot_connect():
    one_line_error(psao("client", "ws://127.0.0.1:9", "builtin:cornell", "--reconnect-timeout", "0.5"),
                   "cannot connect")


def test_client_bad_codecs_and_url():
    one_line_error(psao("client", "ws://127.0.0.1:9", "builtin:cornell", "--codecs", "gzip"), "gzip")
    one_line_error(psao("client", "http:/nothing", "builtin:cornell"), "bad server URL")


@pytest.fixture(scope="module")
def token_server(tmp_path_factory):
    err = tmp_path_factory.mktemp("serve") / "serve.err"
    proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", "builtin:cornell", "--density", "16", "--rays",
                             "2", "--port", "0", "--token", "s3cret", "--tick-hz", "10", "--test-edits", "5"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=open(err, "w"), text=True)
    url = server_url(proc, err, 90)
    yield url, proc, err
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_client_refused_without_token(token_server):
    url, _, err = token_server
    one_line_error(psao("client", url, "builtin:cornell", "--frames", "1"), "server refused: missing token")
    assert "refused: missing token" in err.read_text()


def test_client_refused_for_another_scene(token_server):
    url, _, _ = token_server
    one_line_error(psao("client", url, "builtin:courtyard", "--token", "s3cret", "--frames", "1"),
                   "scene hash mismatch")


def test_client_renders_frames_while_streaming(token_server, tmp_path):
    url, proc, _ = token_server
    if proc.poll() is not None:
        pytest.skip("server already stopped by an earlier test")
    out = psao("client", url, "builtin:cornell", "--token", "s3cret", "--frames", "3", "--json",
               "--render", str(tmp_path / "frames"), "--size", "64x48")
    if out.returncode != 0 and "EGL" in out.stderr:
        pytest.skip(f"no EGL here: {out.stderr.strip()}")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["frames_rendered"] == 3
    assert len(list((tmp_path / "frames").glob("*.png"))) >= 3
    # per-frame GPU times of each pass (timer queries), and the frame log the eval reads
    assert [f["frame"] for f in report["frames"]] == [0, 1, 2]
    for f in report["frames"]:
        assert {"gbuffer", "psao", "composite"} <= set(f["gpu_ms"]) and all(v >= 0 for v in f["gpu_ms"].values())
    assert len((tmp_path / "frames" / "frames.jsonl").read_text().splitlines()) == 3


def test_client_unknown_camera_path(token_server):
    url, _, _ = token_server
    one_line_error(psao("client", url, "builtin:cornell", "--camera-path", "nope", "--frames", "1"),
                   "no camera path 'nope'")


def test_client_ends_on_sigint_also_where_it_came_in_ignored(token_server, tmp_path):
    """A `psao client` started as a script's background job (SIGINT ignored from its parent) still ends on
    SIGINT with its report, as a benchmark stopping it expects."""
    url, proc, _ = token_server
    if proc.poll() is not None:
        pytest.skip("server already stopped by an earlier test")
    digest = tmp_path / "client.jsonl"
    client = subprocess.Popen([sys.executable, "-m", "psao", "client", url, "builtin:cornell", "--token", "s3cret",
                               "--json", "--digest-log", str(digest)], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True,
                              preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        deadline = time.monotonic() + HANG_S  # a hang limit, not a speed expectation
        while not (digest.exists() and digest.read_text().strip()):
            assert client.poll() is None and time.monotonic() < deadline, "client ended or never got its snapshot"
            time.sleep(0.05)
        client.send_signal(signal.SIGINT)
        out, err = client.communicate(timeout=HANG_S)
    finally:
        if client.poll() is None:
            client.kill()
            client.wait()
    assert client.returncode == 0, err
    assert json.loads(out.strip().splitlines()[-1])["mirror_cells"] > 0


def test_client_with_token_then_server_stops_on_sigint(token_server):
    url, proc, err = token_server
    out = psao("client", url, "builtin:cornell", "--token", "s3cret", "--frames", "5", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["updates"] == 5 and report["mirror_cells"] > 0 and report["codec"] == "zstd-stream"
    assert set(report) >= {"bytes_received", "messages", "snapshot_bytes", "mirror_cells", "mirror_buckets", "seconds",
                           "stream_seconds", "updates_per_s"}
    # the Updates' own window: from the first Update to the fifth, inside the run (connecting, snapshot)
    assert 0 < report["stream_seconds"] < report["seconds"]
    assert report["updates_per_s"] == pytest.approx(4 / report["stream_seconds"])
    proc.send_signal(signal.SIGINT)
    assert proc.wait(20) == 0
    assert "stopped on SIGINT" in err.read_text()


def test_client_renders_at_its_own_rate_from_a_static_server(tmp_path):
    """A static server sends nothing after the snapshot: the client still renders, at its own --fps,
    and stops after --frames rendered frames."""
    err = tmp_path / "serve.err"
    proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", "builtin:cornell", "--density", "16", "--rays", "8",
                             "--port", "0"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=open(err, "w"), text=True)
    try:
        url = server_url(proc, err, 120)
        out = psao("client", url, "builtin:cornell", "--frames", "4", "--fps", "10", "--json",
                   "--render", str(tmp_path / "frames"), "--size", "64x48")
        if out.returncode != 0 and "EGL" in out.stderr:
            pytest.skip(f"no EGL here: {out.stderr.strip()}")
        assert out.returncode == 0, out.stderr
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["updates"] == 0 and report["frames_rendered"] == 4
    times = [f["time"] for f in report["frames"]]
    assert all(b > a for a, b in zip(times, times[1:])), times  # (their spacing depends on the machine's load)
    assert len(list((tmp_path / "frames").glob("frame_*_ao_psao.png"))) == 4
