"""The --cluster options' failures: one line naming the problem and exit 2, with or without dask installed."""
from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from psao.cli import main
from serving import HANG_S
from support.cli import one_line_error

ROOT = Path(__file__).resolve().parents[1]


def run(code_or_args, timeout=HANG_S) -> subprocess.CompletedProcess:
    argv = ["-c", code_or_args] if isinstance(code_or_args, str) else ["-m", "psao", *code_or_args]
    return subprocess.run([sys.executable, *argv], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_line_within_the_timeout():
    pytest.importorskip("distributed")
    # nothing listens on a port just released; the command gives up after --cluster-timeout
    one_line_error(run(["bake", "builtin:cornell", "--cluster", f"tcp://127.0.0.1:{free_port()}",
                        "--cluster-timeout", "1"]), "cannot reach the dask scheduler at tcp://127.0.0.1:", alone=True)


@pytest.mark.parametrize("command", ["bake", "serve"])
@pytest.mark.parametrize("args, text", [
    (["--tiles"], "--tiles shards the trace over a cluster: it needs --cluster"),
    (["--cluster", "local:0"], "local:N needs a worker count N >= 1"),
    (["--cluster", "local:2", "--cluster-timeout", "0"], "cluster timeout must be > 0"),
    (["--cluster", "local:2", "--tiles", "--tile-points", "0"], "chunk and tile points must be >= 1"),
])
def test_bad_cluster_options(command, args, text, capsys):
    # in-process: these are refused before anything is loaded or started
    extra = ["--port", "0"] if command == "serve" else []
    assert main([command, "builtin:cornell", *extra, *args]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and text in lines[0], lines


@pytest.mark.parametrize("args, text", [
    (["--cluster", "local:1", "--tracer", "warp"], "it cannot use --tracer warp"),
    (["--tracer", "dask"], "--tracer dask needs --cluster"),
])
def test_bake_tracer_conflicts(args, text, capsys):
    assert main(["bake", "builtin:cornell", *args]) == 2
    assert text in capsys.readouterr().err


def test_without_dask_the_cluster_asks_for_the_extra():
    """dask is an optional extra: without it, --cluster says what to install (and nothing else breaks)."""
    code = ("import sys; sys.modules['distributed'] = None; sys.modules['dask'] = None\n"
            "from psao.cli import main\n"
            "sys.exit(main(['bake', 'builtin:cornell', '--cluster', 'local:1', '--probes', '0']))")
    one_line_error(run(code), "pip install 'psao[dask]'", alone=True)
