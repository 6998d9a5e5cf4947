"""`psao render` end to end (real EGL, real files) and the streaming render callback over a real Mirror."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_render_gridbuild import server_grid
from serving import HANG_S
from support.cli import psao

from psao.protocol.updates import GridDelta
from psao.client.errors import RenderError
from psao.client.mirror import Mirror
from psao.client.render.stream_render import StreamRenderer

from psao.scene import load_scene
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cornell_grid(tmp_path_factory):
    scene = load_scene("builtin:cornell")
    grid = server_grid(scene, 1024)
    path = tmp_path_factory.mktemp("grid") / "cornell.npz"
    grid.save(path, scene_hash=scene.content_hash())
    return scene, grid, path


def test_render_writes_numbered_pngs_and_json_last_line(cornell_grid, tmp_path):
    _, _, grid_path = cornell_grid
    out = tmp_path / "frames"
    res = psao("render", "builtin:cornell", "--grid", grid_path, "--frames", 2, "--size", "160x120",
               "--ao", "both", "--out", out, "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout.strip().splitlines()[-1])
    assert [f["frame"] for f in report["frames"]] == [0, 1]
    for f in report["frames"]:
        assert set(f["gpu_ms"]) == {"gbuffer", "psao", "ssao", "ssao_blur", "composite"}
        assert all(0 < ms < 60_000 for ms in f["gpu_ms"].values())
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(f"frame_{i:05d}_{kind}_{mode}.png" for i in (0, 1)
                           for kind in ("composite", "ao") for mode in ("psao", "ssao"))
    ao = np.asarray(Image.open(out / "frame_00000_ao_psao.png"))
    rgb = np.asarray(Image.open(out / "frame_00000_composite_psao.png"))
    assert ao.shape == (120, 160) and rgb.shape == (120, 160, 3)
    assert ao.min() < 200 and ao.max() == 255  # shaded somewhere, unoccluded somewhere


@pytest.mark.parametrize("extra,message", [
    (["--size", "0x100"], "frame size 0x100: width and height must be positive"),
    (["--size", "99999x10"], "above this OpenGL's limit"),
    (["--size", "big"], "expected WIDTHxHEIGHT"),
    (["--camera-path", "nope"], "no camera path 'nope'"),
    (["--ao", "psao,hbao"], "unknown AO method 'hbao'"),
    (["--ao", "gtao", "--gtao-preset", "fast"], "GTAO preset 'fast'"),
])
def test_bad_arguments_are_one_line_exit_2(cornell_grid, tmp_path, extra, message):
    _, _, grid_path = cornell_grid
    res = psao("render", "builtin:cornell", "--grid", grid_path, "--out", tmp_path / "o", *extra)
    assert res.returncode == 2
    assert message in res.stderr and len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr


def test_grid_of_another_scene_or_not_a_grid_is_refused(cornell_grid, tmp_path):
    _, _, grid_path = cornell_grid
    res = psao("render", "builtin:courtyard", "--grid", grid_path, "--out", tmp_path / "o")
    assert res.returncode == 2 and "baked from another scene" in res.stderr
    bogus = tmp_path / "bogus.npz"
    bogus.write_bytes(b"not a zip at all")
    res = psao("render", "builtin:cornell", "--grid", bogus, "--out", tmp_path / "o")
    assert res.returncode == 2 and "not a PSAO grid file" in res.stderr
    res = psao("render", "builtin:cornell", "--grid", tmp_path / "missing.npz")
    assert res.returncode == 2 and "grid file not found" in res.stderr
    assert not (tmp_path / "o").exists()


def test_stream_callback_follows_the_mirror(ctx, cornell_grid, tmp_path):
    scene, grid, _ = cornell_grid
    mirror = Mirror(grid.instances, len(grid.buckets), len(grid.cells))
    everything = np.arange(len(grid.cells), dtype=np.uint32)
    all_buckets = np.arange(len(grid.buckets), dtype=np.uint32)
    transforms = np.stack([i.transform for i in scene.instances]).astype(np.float32)
    mirror.apply(GridDelta(len(grid.cells), np.arange(len(transforms)), transforms, all_buckets, grid.buckets,
                           everything, grid.cells))
    with StreamRenderer(scene, tmp_path / "s", size=(96, 72), ctx=ctx) as cb:
        first = cb(mirror, mirror.transforms, tick=0)
        # The server darkens some cells: only those go up, and the frame changes.
        table = grid.point_table()
        grid.set_ao(table.slot, table.index, np.zeros(len(table), np.uint32))
        _, dirty = grid.take_dirty()
        mirror.apply(GridDelta(len(grid.cells), cell_slots=dirty, cells=grid.cells[dirty]))
        before = cb.renderer.grid.bytes_uploaded
        second = cb(mirror, mirror.transforms, tick=0)
        sent = cb.renderer.grid.bytes_uploaded - before
        assert 0 < sent <= grid.cells.nbytes
        np.testing.assert_array_equal(cb.renderer.grid.read_back()[2], mirror.cells)
    a = np.asarray(Image.open(tmp_path / "s" / "frame_00000_ao_psao.png"))
    b = np.asarray(Image.open(tmp_path / "s" / "frame_00001_ao_psao.png"))
    assert first["frame"] == 0 and second["frame"] == 1
    assert b.mean() < a.mean() - 20  # everything occluded now


def test_stream_callback_rejects_unknown_camera_path(ctx, cornell_grid, tmp_path):
    scene, _, _ = cornell_grid
    with pytest.raises(RenderError, match="no camera path"):
        StreamRenderer(scene, tmp_path, camera_path="nope", ctx=ctx)


def test_no_egl_is_one_line_exit_2(cornell_grid, tmp_path):
    """libglvnd with no EGL vendor: the context cannot be created; no traceback, nothing written."""
    import os

    _, _, grid_path = cornell_grid
    env = {**os.environ, "__EGL_VENDOR_LIBRARY_FILENAMES": str(tmp_path / "no-vendor.json")}
    res = subprocess.run([sys.executable, "-m", "psao", "render", "builtin:cornell", "--grid", str(grid_path),
                          "--out", str(tmp_path / "o")], capture_output=True, text=True, cwd=REPO, env=env, timeout=HANG_S)
    assert res.returncode == 2 and "no EGL display available" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "o").exists()


def test_window_without_display_or_glfw_is_one_line_exit_2(cornell_grid, tmp_path):
    """--window on a machine without glfw or without a display: one line naming why, nothing written."""
    import os

    _, _, grid_path = cornell_grid
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    res = subprocess.run([sys.executable, "-m", "psao", "render", "builtin:cornell", "--grid", str(grid_path),
                          "--window", "--out", str(tmp_path / "o")], capture_output=True, text=True, cwd=REPO,
                         env=env, timeout=HANG_S)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and ("glfw" in res.stderr or "window" in res.stderr)
    assert not (tmp_path / "o").exists()
