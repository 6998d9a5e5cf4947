"""`psao serve` access control and start-up as commands: tokens from a file or the environment, edits behind
their own token, a warning when listening beyond loopback without a token, the port checked before the bake,
and a client with --frames against a server that sends nothing after the snapshot."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys

import pytest

from serving import HANG_S, server_url
from support.cli import one_line_error, psao
from test_streaming_cli import ROOT

SMALL = ["builtin:cornell", "--density", "8", "--rays", "1"]


def start_serve(tmp_path, *args, env=None, host_pattern=r"127\.0\.0\.1"):
    err = tmp_path / "serve.err"
    proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", *SMALL, "--port", "0", *args], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=open(err, "w"), text=True,
                            env={**os.environ, **(env or {})})
    return server_url(proc, err, 120, host=host_pattern), proc, err


def stop(proc):
    proc.send_signal(signal.SIGTERM)
    proc.wait(30)


def client(url, *args, env=None):
    return subprocess.run([sys.executable, "-m", "psao", "client", url, "builtin:cornell", "--json",
                           "--no-reconnect", *args], cwd=ROOT, capture_output=True, text=True, timeout=HANG_S,
                          env={**os.environ, **(env or {})})


def test_token_from_a_file_and_from_the_environment(tmp_path):
    (tmp_path / "token").write_text("from-file\n")
    url, proc, err = start_serve(tmp_path, "--token-file", str(tmp_path / "token"))
    try:
        assert "from-file" not in " ".join(open(f"/proc/{proc.pid}/cmdline").read().split("\0"))
        ok = client(url, "--frames", "1", env={"PSAO_TOKEN": "from-file"})
        assert ok.returncode == 0, ok.stderr
        one_line_error(client(url, "--frames", "1", env={"PSAO_TOKEN": "guess"}), "wrong token")
        (tmp_path / "client-token").write_text("from-file")
        ok = client(url, "--frames", "1", "--token-file", str(tmp_path / "client-token"))
        assert ok.returncode == 0, ok.stderr
    finally:
        stop(proc)


def test_static_server_client_with_frames_ends(tmp_path):
    url, proc, _ = start_serve(tmp_path)
    try:
        out = client(url, "--frames", "5")
    finally:
        stop(proc)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["updates"] == 0 and report["mirror_cells"] > 0


@pytest.mark.parametrize("args, env, text", [
    (["--allow-edits"], {"PSAO_EDIT_TOKEN": ""}, "edits need an edit token"),
    (["--allow-edits", "--token", "same"], {"PSAO_EDIT_TOKEN": "same"}, "edit token must differ"),
    (["--max-clients", "0"], {}, "max clients must be within 1..100000"),
    (["--allow-edits", "--grid", "g.npz"], {"PSAO_EDIT_TOKEN": "e"}, "--allow-edits bakes the scene itself"),
    (["--token-file", "/nonexistent/token"], {}, "cannot read the token from /nonexistent/token"),
])
def test_bad_access_settings(args, env, text):
    proc = subprocess.run([sys.executable, "-m", "psao", "serve", *SMALL, "--port", "0", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=HANG_S, env={**os.environ, **env})
    one_line_error(proc, text)


def test_warns_when_listening_beyond_loopback_without_a_token(tmp_path):
    _, proc, err = start_serve(tmp_path, "--host", "0.0.0.0", host_pattern=r"0\.0\.0\.0")
    stop(proc)
    assert "listening on 0.0.0.0 without a token" in err.read_text()
    _, proc, err = start_serve(tmp_path, "--host", "0.0.0.0", env={"PSAO_TOKEN": "t"}, host_pattern=r"0\.0\.0\.0")
    stop(proc)
    assert "without a token" not in err.read_text()


def test_busy_port_fails_before_the_bake():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = psao("serve", "builtin:courtyard", "--density", "64", "--port", str(port))
    one_line_error(proc, f"cannot listen on 127.0.0.1:{port}")
    assert "baked" not in proc.stderr
