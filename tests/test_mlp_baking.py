"""MLP AO baking: training lowers the loss, the shader equals the numpy network on the same weights and
G-buffer, bad weights files are one line (exit 2 on the command line)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_render_gridbuild import server_grid

from psao.client.errors import RenderError
from psao.client.render.mlp_pass import MLP_HIDDEN, mlp_numpy, mlp_shapes
from psao.client.render.renderer import FrameRenderer, MethodOptions
from psao.client.render.views import path_matrices
from psao.client.render.weights import save_weights
from psao.eval.learn.grid_points import instance_points
from psao.eval.learn.mlp_train import MlpTrainSettings, train_mlp
from serving import HANG_S

import psao.scene
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cornell():
    scene = psao.scene.load_scene("builtin:cornell")
    return scene, server_grid(scene, 256)


def random_weights(n_inst, seed=3):
    rng = np.random.default_rng(seed)
    return {k: rng.normal(0, 0.3, size=s).astype(np.float32) + (0.6 if k == "b2" else 0.0)
            for k, s in mlp_shapes(n_inst).items()}


def test_grid_points_decode_every_allocated_point(cornell):
    scene, grid = cornell
    total = sum(len(instance_points(grid.instances, grid.buckets, grid.cells, i)[0]) for i in range(len(scene.instances)))
    allocated = int(np.count_nonzero(grid.cells[:, :7] >> np.uint32(31)))
    assert total == allocated > 1000


def test_training_lowers_the_loss(cornell):
    _, grid = cornell
    result = train_mlp(grid, MlpTrainSettings(points=512, steps=150, batch=64, seed=2))
    first, last = np.mean(result.losses[:10]), np.mean(result.losses[-10:])
    assert last < 0.8 * first, (first, last)
    again = train_mlp(grid, MlpTrainSettings(points=512, steps=150, batch=64, seed=2))
    np.testing.assert_array_equal(result.arrays["W0"], again.arrays["W0"])  # seeded: reproducible


def test_shader_equals_numpy_network(ctx, cornell, tmp_path):
    scene, _ = cornell
    arrays = random_weights(len(scene.instances))
    path = tmp_path / "w.npz"
    save_weights(path, "mlp", arrays, {"scene_hash": scene.content_hash(), "hidden": list(MLP_HIDDEN)})
    size = (96, 64)
    view, proj = path_matrices(scene, psao.scene.scene_camera(scene, None), 0.0, size)
    with FrameRenderer(scene, size, "mlp", ctx=ctx, options=MethodOptions(mlp_weights=str(path))) as r:
        frame = r.render(view, proj)
    gb = frame.gbuffer
    expected = mlp_numpy(arrays, np.where(gb.mask, gb.instance, -1), gb.local_normal)
    assert gb.mask.mean() > 0.5 and expected[gb.mask].std() > 0.02
    np.testing.assert_allclose(frame.ao["mlp"], expected, atol=2e-4)


@pytest.mark.parametrize("damage,message", [
    ("missing", "weights file not found"),
    ("shape", "array W1 has shape"),
    ("nan", "NaN"),
    ("scene", "trained on another scene"),
    ("garbage", "not a mlp weights file"),
])
def test_bad_weights_are_one_line(ctx, cornell, tmp_path, damage, message):
    scene, _ = cornell
    arrays = random_weights(len(scene.instances))
    header = {"scene_hash": scene.content_hash(), "hidden": list(MLP_HIDDEN)}
    path = tmp_path / "w.npz"
    if damage == "shape":
        arrays["W1"] = arrays["W1"][:, :, :5]
    if damage == "nan":
        arrays["b0"][0, 0] = np.nan
    if damage == "scene":
        header["scene_hash"] = "0" * 64
    if damage == "garbage":
        path.write_bytes(b"not a zip")
    elif damage != "missing":
        save_weights(path, "mlp", arrays, header)
    with pytest.raises(RenderError, match=message):
        FrameRenderer(scene, (32, 32), "mlp", ctx=ctx, options=MethodOptions(mlp_weights=str(path)))


def test_cli_train_and_bad_weights_exit_2(cornell, tmp_path):
    scene, grid = cornell
    grid_path = tmp_path / "g.npz"
    grid.save(grid_path, scene_hash=scene.content_hash())
    out = tmp_path / "mlp.npz"
    r = subprocess.run([sys.executable, "-m", "psao", "train", "mlp", "builtin:cornell", "--grid", str(grid_path),
                        "--out", str(out), "--steps", "20", "--points", "256", "--json"],
                       cwd=REPO, capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-2000:]
    assert out.is_file() and '"weight_bytes"' in r.stdout.splitlines()[-1]
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"xx")
    r = subprocess.run([sys.executable, "-m", "psao", "render", "builtin:cornell", "--grid", str(grid_path),
                        "--ao", "mlp", "--mlp-weights", str(bad), "--out", str(tmp_path / "f"), "--size", "32x32"],
                       cwd=REPO, capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "mlp weights" in r.stderr, r.stderr
