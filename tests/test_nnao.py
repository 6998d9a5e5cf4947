"""NNAO: the shader equals the numpy network on the same weights and G-buffer (every cell and the
stratified 64), training lowers the loss, bad weights files are one line."""
from __future__ import annotations

import numpy as np
import pytest
from test_render_gtao import corner_scene

from psao.client.errors import RenderError
from psao.client.render.composite import read_channel
from psao.client.render.nnao_net import nnao_numpy, nnao_shapes
from psao.client.render.renderer import FrameRenderer, MethodOptions
from psao.client.render.views import look_at, perspective
from psao.client.render.weights import save_weights


def random_nnao(seed=5):
    rng = np.random.default_rng(seed)
    arrays = {}
    for k, s in nnao_shapes().items():
        if k == "std":
            arrays[k] = rng.uniform(0.05, 0.3, size=s)
        elif k == "mean":
            arrays[k] = rng.normal(0, 0.02, size=s)
        elif k[0] == "W":
            arrays[k] = rng.normal(0, 0.05 if k == "W0" else 0.6, size=s)
        elif k[0] == "a":
            arrays[k] = rng.uniform(0.05, 0.3, size=s)
        elif k[0] == "s":
            arrays[k] = rng.uniform(0.7, 1.3, size=s)
        else:
            arrays[k] = rng.normal(0, 0.2, size=s)
    arrays["b3"] = arrays["b3"] + 0.5
    return {k: v.astype(np.float32) for k, v in arrays.items()}


@pytest.mark.parametrize("samples", [64, 961])
def test_shader_equals_numpy_network(ctx, tmp_path, samples):
    arrays = random_nnao()
    path = tmp_path / "nnao.npz"
    save_weights(path, "nnao", arrays, {})
    scene = corner_scene()
    size = (64, 40)
    view, proj = look_at([0.3, 1.6, 3.0], [0.3, 0.3, 0.0]), perspective(60, size[0] / size[1], 0.05, 50)
    with FrameRenderer(scene, size, "nnao", ctx=ctx, options=MethodOptions(nnao_weights=str(path), nnao_samples=samples)) as r:
        frame = r.render(view, proj)
        raw = read_channel(r.passes["nnao"].raw, r.size, 1, 0)
    gb = frame.gbuffer
    expected = nnao_numpy(gb.depth, gb.normal, view, proj, arrays, scene.ao_distance, samples)
    assert gb.mask.mean() > 0.9 and expected[gb.mask].std() > 0.01
    diff = np.abs(raw - expected)[gb.mask]
    # float32 reprojection may pick the neighbouring texel for a few taps on a texel border
    assert np.mean(diff < 1e-3) > 0.97 and np.median(diff) < 1e-4, (np.mean(diff < 1e-3), np.median(diff))
    assert np.all(raw[~gb.mask] == 1.0)


@pytest.mark.parametrize("damage,message", [
    ("missing", "weights file not found"),
    ("shape", "array W0 has shape 3844x3, expected 3844x4"),
    ("nan", "NaN"),
    ("method", "holds 'mlp' weights"),
])
def test_bad_weights_are_one_line(ctx, tmp_path, damage, message):
    arrays = random_nnao()
    path = tmp_path / "w.npz"
    method = "nnao"
    if damage == "shape":
        arrays["W0"] = arrays["W0"][:, :3]
    if damage == "nan":
        arrays["s2"][1] = np.nan
    if damage == "method":
        method = "mlp"
    if damage != "missing":
        save_weights(path, method, arrays, {})
    with pytest.raises(RenderError, match=message):
        FrameRenderer(corner_scene(), (32, 32), "nnao", ctx=ctx, options=MethodOptions(nnao_weights=str(path)))
    with pytest.raises(RenderError, match="NNAO samples 100"):
        save_weights(path, "nnao", random_nnao(), {})
        FrameRenderer(corner_scene(), (32, 32), "nnao", ctx=ctx, options=MethodOptions(nnao_weights=str(path), nnao_samples=100))


def test_training_on_a_tiny_set_lowers_the_loss():
    from psao.eval.learn.nnao_train import NnaoDataSettings, NnaoTrainSettings, build_dataset, predict, train_nnao

    x, y = build_dataset([corner_scene()], NnaoDataSettings(frames=2, pixels=96, spp=32, size=(96, 64), seed=3))
    assert x.shape == (len(y), 3844) and 100 < len(y) <= 192 and y.std() > 0.05
    settings = NnaoTrainSettings(batch=16, lr=3e-3, input_dropout=0.0, seed=3)
    before = train_nnao(x, y, settings, steps=1)
    after = train_nnao(x, y, settings, steps=300)
    mse_before = np.mean((predict(before.arrays, x) - y) ** 2)
    mse_after = np.mean((predict(after.arrays, x) - y) ** 2)
    assert mse_after < 0.7 * mse_before, (mse_before, mse_after)
    again = train_nnao(x, y, settings, steps=300)
    np.testing.assert_array_equal(after.arrays["W0"], again.arrays["W0"])  # seeded: reproducible
