"""The package as a user installs it: a wheel built from the tree, installed (not editable) in a fresh
venv, runs from another directory with its shaders and example scenes as package data."""
from __future__ import annotations

import json
import os
import site
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

from conftest import REPO

TOP_LEVEL = {"psao"}


def _run(cmd, cwd, timeout=600, env=None):
    return subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    # Without build isolation when this interpreter can build (fast, offline); else pip fetches the
    # build requirements, and a machine without an index skips.
    try:
        import setuptools  # noqa: F401
        import wheel as _wheel  # noqa: F401
        isolation = ["--no-build-isolation"]
    except ImportError:
        isolation = []
    res = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-w", out, REPO], cwd=out)
    wheels = list(out.glob("psao-*.whl"))
    if res.returncode != 0 or not wheels:
        pytest.skip(f"cannot build the wheel here: {(res.stderr or res.stdout).strip().splitlines()[-1:]}")
    return wheels[0]


def test_wheel_holds_the_packages_and_their_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == TOP_LEVEL, top  # benchmarks and tests stay out
    assert "psao/protocol/shaders/psao_common.glsl" in names
    assert {"psao/scene/scenes/pavilion.toml", "psao/scene/scenes/playground.toml"} <= set(names)


def test_installed_wheel_bakes_from_another_directory(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    # The dependencies come from this interpreter's site-packages as plain paths (a .pth line adds the
    # folder, not the .pth files in it, so this interpreter's own install of psao stays out of sight).
    target = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path).stdout.strip())
    deps = [p for p in site.getsitepackages() if Path(p).is_dir()]
    (target / "zz_dependencies.pth").write_text("\n".join(deps) + "\n")
    res = _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", wheel], tmp_path)
    if res.returncode != 0:  # pip older than 22.3 has no --python
        res = _run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--target", target, wheel], tmp_path)
    assert res.returncode == 0, res.stderr
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    where = _run([py, "-c", "import psao.client, psao.scene; print(psao.client.__file__, psao.scene.__file__)"], work, env=env)
    assert where.returncode == 0, where.stderr
    assert all(str(target) in f for f in where.stdout.split()), where.stdout
    bake = _run([env_dir / "bin" / "psao", "bake", "builtin:cornell", "--density", "16", "--rays", "8", "--probes",
                 "500", "--probe-rays", "32", "--workers", "1", "--json"], work, env=env)
    assert bake.returncode == 0, bake.stderr
    stats = json.loads(bake.stdout.strip().splitlines()[-1])
    assert stats["points_kept"] > 0 and (work / stats["out"]).is_file()
    toml = _run([env_dir / "bin" / "psao", "bake", "builtin:pavilion", "--density", "4", "--rays", "4", "--probes", "0",
                 "--workers", "1", "--json"], work, env=env)
    assert toml.returncode == 0, toml.stderr
    shader = _run([py, "-c", "from psao.client.render.shaderlib import load_shader; "
                   "print(len(load_shader('psao_ao.frag.glsl').text))"], work, env=env)
    assert shader.returncode == 0 and int(shader.stdout) > 1000, shader.stderr
