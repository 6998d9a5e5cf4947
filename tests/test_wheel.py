"""The package as a user installs it: a wheel built from the tree, installed (not editable) in a fresh
venv, runs from another directory with its shaders, example scenes and web client as package data: it
bakes, and its `psao serve` serves a page that chromium loads and draws PSAO frames with."""
from __future__ import annotations

import json
import os
import signal
import site
import subprocess
import sys
import venv
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

from browser import launched, missing_browser, wait_page
from conftest import REPO
from psao.server.net.webpage import ASSETS
from serving import HANG_S, server_url

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
    page = {f"psao/web/{name}" for name, _ in ASSETS.values() if isinstance(name, str)}
    assert page <= set(names), page - set(names)  # every file the page is served from
    assert "psao/web/vendor/LICENSE" in names


@dataclass(frozen=True)
class Installed:
    """The wheel installed in a fresh venv: its interpreter, its bin/ folder, a working folder outside the
    tree and the environment to run it with."""
    python: Path
    bin: Path
    work: Path
    env: dict


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Installed:
    tmp_path = tmp_path_factory.mktemp("installed")
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
    where = _run([py, "-c", "import psao, psao.client, psao.scene, psao.web; "
                  "print(psao.__file__, psao.client.__file__, psao.scene.__file__, psao.web.__file__)"], work, env=env)
    assert where.returncode == 0, where.stderr
    assert len(where.stdout.split()) == 4 and all(f.startswith(str(target)) for f in where.stdout.split()), where.stdout
    return Installed(py, env_dir / "bin", work, env)


def test_installed_wheel_bakes_from_another_directory(installed):
    py, work, env = installed.python, installed.work, installed.env
    bake = _run([installed.bin / "psao", "bake", "builtin:cornell", "--density", "16", "--rays", "8", "--probes",
                 "500", "--probe-rays", "32", "--workers", "1", "--json"], work, env=env)
    assert bake.returncode == 0, bake.stderr
    stats = json.loads(bake.stdout.strip().splitlines()[-1])
    assert stats["points_kept"] > 0 and (work / stats["out"]).is_file()
    toml = _run([installed.bin / "psao", "bake", "builtin:pavilion", "--density", "4", "--rays", "4", "--probes", "0",
                 "--workers", "1", "--json"], work, env=env)
    assert toml.returncode == 0, toml.stderr
    shader = _run([py, "-c", "from psao.client.render.shaderlib import load_shader; "
                   "print(len(load_shader('psao_ao.frag.glsl').text))"], work, env=env)
    assert shader.returncode == 0 and int(shader.stdout) > 1000, shader.stderr


@pytest.mark.skipif(missing_browser() is not None, reason=str(missing_browser()))
def test_installed_wheel_serves_the_web_client(installed, tmp_path):
    """The installed `psao serve`, run from a folder outside the tree, serves the page from its
    site-packages (no npm, no source tree), and chromium on it streams the grid and draws PSAO frames."""
    err = tmp_path / "serve.err"
    with open(err, "w") as log:
        proc = subprocess.Popen([str(installed.bin / "psao"), "serve", "builtin:cornell", "--port", "0", "--density", "16",
                                 "--rays", "8", "--tick-hz", "10"], cwd=installed.work, env=installed.env,
                                stdout=subprocess.DEVNULL, stderr=log)
    try:
        port = int(server_url(proc, err, timeout=HANG_S).rsplit(":", 1)[1])
        with launched() as b:
            page = b.new_page(viewport={"width": 240, "height": 190})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"http://127.0.0.1:{port}/?width=200&height=150", wait_until="commit")
            wait_page(page, "window.psao && window.psao.state === 'streaming' && window.psao.frames >= 1 "
                            "&& window.psao.mode === 'psao'")
            points = page.evaluate("window.psao.mirror.allocatedPoints()")
            page.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    assert not errors
    assert points > 0
