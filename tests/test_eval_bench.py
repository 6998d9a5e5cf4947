"""`psao bench` end to end on real processes, its failures, and that no server outlives it."""
from __future__ import annotations

import argparse

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from psao.eval.errors import EvalError
from psao.eval.processes import ServerProcess, run_client
from serving import HANG_S

ROOT = Path(__file__).resolve().parents[1]


def processes_mentioning(text: str) -> list[int]:
    """Pids whose command line contains `text` (each test's own tmp path identifies its children)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmd:
            found.append(int(entry.name))
    return found


def wait_gone(text: str, timeout: float = 10.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        left = processes_mentioning(text)
        if not left:
            return []
        time.sleep(0.1)
    return processes_mentioning(text)


def bench(tmp_path: Path, *extra: str, out: Path | None = None) -> list[str]:
    return [sys.executable, "-m", "psao.cli", "bench", "--cache", str(tmp_path / "cache"),
            "--out", str(out or tmp_path / "out"), "--size", "160x96", "--spp", "8", "--frames", "2", *extra]


def test_tiny_bench_end_to_end(tmp_path):
    out = tmp_path / "out"
    r = subprocess.run(bench(tmp_path, "builtin:cornell", "--densities", "128", "--tick-hz", "30",
                             "--stream-seconds", "1"), cwd=ROOT, capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("table.md", "table.csv", "results.json", "runtime_error.png", "bandwidth_quality.png",
                 "frame_cornell.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    rows = json.loads((out / "results.json").read_text())
    by_method = {r["method"]: r for r in rows}
    assert set(by_method) == {"SSAO", "GTAO", "PSAO-128"}  # the default --methods ssao,gtao,psao
    for row in rows:
        assert 10 < row["psnr"] < 60, row
        assert 0 < row["flip"] < 1, row
        assert 0 < row["ssim"] <= 1, row
        assert math.isfinite(row["client_ms_frame"]) and row["client_ms_frame"] > 0
    psao = by_method["PSAO-128"]
    assert psao["tick_hz"] == 30 and psao["snapshot_mb"] > 0
    assert 0 <= psao["stream_mbit_s"] < 0.1  # a static scene sends (almost) nothing after its snapshot
    assert psao["points"] > 0
    with open(out / "table.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 3
    md = (out / "table.md").read_text()
    assert "| cornell | PSAO-128 |" in md and "Mbit/s, --tick-hz 30" in md
    assert "LPIPS not computed" in r.stdout
    assert not wait_gone(str(tmp_path))


def run_in_process(args: list[str], capsys) -> tuple[int, str]:
    """`psao bench` through the CLI dispatcher in this process (argument errors need no subprocess)."""
    from psao.cli import main

    assert args[:3] == [sys.executable, "-m", "psao.cli"]
    rc = main(args[3:])
    return rc, capsys.readouterr().err


def test_unwritable_out_dir_is_one_line_and_leaves_nothing(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    rc, err = run_in_process(bench(tmp_path, "builtin:cornell", "--densities", "64", out=blocker / "sub"), capsys)
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "output folder" in lines[0] and "cannot be written" in lines[0], err
    assert not wait_gone(str(tmp_path))


@pytest.mark.parametrize("args,msg", [
    (["--densities", "12,x"], "--densities"),
    (["--tick-hz", "90"], "outside 5..60"),
    (["--size", "12by4"], "frame size"),
    (["--frames", "0"], "--frames"),
    (["--methods", "ssao,hbao,psao"], "unknown AO method 'hbao'"),
    (["--ao", "ssao,hbao"], "unknown AO method 'hbao'"),
    (["--gtao-preset", "fast"], "--gtao-preset"),
])
def test_bad_arguments_are_one_line(tmp_path, capsys, args, msg):
    rc, err = run_in_process(bench(tmp_path, "builtin:cornell", *args), capsys)
    assert rc == 2 and msg in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("flag", ["--methods", "--ao"])
@pytest.mark.parametrize("text,methods,video", [
    ("ssao,gtao", ("psao", "ssao", "gtao"), False),  # psao is always scored
    ("video", ("psao", "video"), True),
    ("gtao,video,psao", ("psao", "gtao", "video"), True),
    ("both", ("psao", "ssao"), False),
])
def test_methods_and_ao_are_one_vocabulary(flag, text, methods, video):
    from psao.eval.bench_cli import add_arguments, config_from_args

    p = argparse.ArgumentParser()
    add_arguments(p)
    cfg = config_from_args(p.parse_args(["builtin:cornell", flag, text]))
    assert cfg.methods == methods and (cfg.video is not None) == video
    assert "video" not in cfg.render_methods and "psao" not in cfg.baselines


@pytest.mark.parametrize("victim", ["server", "bench"])
def test_killed_mid_run_leaves_nothing(tmp_path, victim):
    """SIGKILL the server while the bench streams from it (one-line error, exit 2), or SIGTERM the bench
    itself (exit 130): either way no process of the run is left."""
    proc = subprocess.Popen(bench(tmp_path, "builtin:cornell", "--densities", "64", "--tick-hz", "30",
                                  "--stream-seconds", "60"), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        server = None
        deadline = time.monotonic() + HANG_S
        while server is None and time.monotonic() < deadline and proc.poll() is None:
            servers = [p for p in processes_mentioning(str(tmp_path)) if _is_serving(p)]
            server = servers[0] if servers else None
            time.sleep(0.1)
        assert server is not None, "the bench never started a server"
        time.sleep(2.0)  # let the client connect and take its snapshot
        if victim == "server":
            os.kill(server, signal.SIGKILL)
        else:
            proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=HANG_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    if victim == "server":
        assert proc.returncode == 2, err[-2000:]
        assert "psao bench: error:" in err and "Traceback" not in err
    else:
        assert proc.returncode == 130, err[-2000:]
    assert not wait_gone(str(tmp_path))


def _is_serving(pid: int) -> bool:
    try:
        return b" serve " in Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
    except OSError:
        return False


def test_server_process_group_dies_with_an_exception(tmp_path):
    grid_missing = tmp_path / "missing.npz"
    with pytest.raises(EvalError, match="exited"):
        with ServerProcess("builtin:cornell", ["--grid", str(grid_missing)]):
            pass
    assert not wait_gone(str(tmp_path))


def test_unreachable_server_is_an_error(tmp_path):
    with pytest.raises(EvalError):
        run_client("ws://127.0.0.1:9", "builtin:cornell", 0.5, extra=["--digest-log", str(tmp_path / "d.jsonl")],
                   connect_timeout=HANG_S)
    assert not wait_gone(str(tmp_path))


def test_scene_without_camera_path_uses_an_orbit(tmp_path):
    obj = tmp_path / "two_boxes.obj"
    obj.write_text(_boxes_obj())
    out = tmp_path / "out"
    r = subprocess.run(bench(tmp_path, str(obj), "--densities", "64", "--no-stream", "--frames", "1"), cwd=ROOT,
                       capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "no camera path" in r.stderr
    rows = json.loads((out / "results.json").read_text())
    assert all(np.isfinite(row["psnr"]) for row in rows)


def _boxes_obj() -> str:
    """A floor and a box on it (OBJ, no camera path)."""
    v = [(-2, 0, -2), (2, 0, -2), (2, 0, 2), (-2, 0, 2)]
    f = [(1, 3, 2), (1, 4, 3)]
    cube = [(x, y, z) for x in (-0.5, 0.5) for y in (0, 1) for z in (-0.5, 0.5)]
    base = len(v)
    v += cube
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    for a, b, c, d in quads:
        f += [(base + a + 1, base + b + 1, base + c + 1), (base + a + 1, base + c + 1, base + d + 1)]
    return "".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a} {b} {c}\n" for a, b, c in f)


def test_sigterm_while_a_child_starts_leaves_no_child(tmp_path, monkeypatch):
    """SIGTERM that reaches the bench while it is inside Popen (the child forked, not yet exec'd: here
    the child itself sends it from its pre-exec hook, so it always lands there) still interrupts the
    bench, and the child it started is killed rather than left running unowned."""
    from psao.eval import processes

    marker = str(tmp_path / "child-marker")
    monkeypatch.setattr(processes, "psao_command",
                        lambda *args: [sys.executable, "-c", "import time; time.sleep(120)", marker])
    setup = processes._child_setup

    def setup_then_signal_parent():
        setup()
        os.kill(os.getppid(), signal.SIGTERM)

    monkeypatch.setattr(processes, "_child_setup", setup_then_signal_parent)
    got = None
    try:
        with processes.interrupt_on_sigterm():
            got = processes.spawn(["serve"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(30)  # not reached when the signal interrupts the bench
    except KeyboardInterrupt:
        interrupted = True
    else:
        interrupted = False
    left = wait_gone(marker)
    for pid in left:  # clean up after a failure
        os.kill(pid, signal.SIGKILL)
    assert interrupted and got is None
    assert not left, "the child started during SIGTERM was left running"
    assert signal.getsignal(signal.SIGTERM) is not None
