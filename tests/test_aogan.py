"""AOGAN (needs PyTorch, which the test extra installs): the generator trains on a tiny set and its DSSIM
falls, the client's AOGAN pass equals the generator run on the G-buffer read back, bad weights are one line."""
from __future__ import annotations

import numpy as np
import pytest
from test_render_gtao import corner_scene


torch = pytest.importorskip("torch", reason="PyTorch is not installed: the test extra (make test) installs it")

from psao.client.errors import RenderError  # noqa: E402
from psao.client.render.aogan_net import build_generator, gbuffer_inputs, infer, load_generator, state_arrays  # noqa: E402
from psao.client.render.renderer import FrameRenderer, MethodOptions  # noqa: E402
from psao.client.render.views import look_at, perspective  # noqa: E402
from psao.client.render.weights import save_weights  # noqa: E402


def random_generator_file(path, seed=4):
    torch.manual_seed(seed)
    model = build_generator()
    model.eval()
    save_weights(path, "aogan", state_arrays(model), {})
    return model


def test_training_on_a_tiny_set_lowers_dssim():
    from psao.eval.learn.aogan_train import AoganDataSettings, AoganTrainSettings, build_dataset, train_aogan

    x, y = build_dataset([corner_scene()], AoganDataSettings(frames=2, size=(64, 64), spp=16, seed=2))
    assert x.shape == (2, 6, 64, 64) and y.shape == (2, 64, 64)
    result = train_aogan(x, y, AoganTrainSettings(steps=24, critic_steps=1, batch=2, patch=32, lr=3e-3, seed=2))
    assert np.mean(result.losses[-6:]) < 0.8 * np.mean(result.losses[:6]), result.losses


def test_client_pass_equals_generator_on_the_read_back_gbuffer(ctx, tmp_path):
    path = tmp_path / "aogan.npz"
    random_generator_file(path)
    model = load_generator(path)[0]
    scene = corner_scene()
    size = (72, 40)  # not a multiple of 8: padding and cropping are exercised
    view, proj = look_at([0.3, 1.6, 3.0], [0.3, 0.3, 0.0]), perspective(60, size[0] / size[1], 0.05, 50)
    with FrameRenderer(scene, size, "aogan", ctx=ctx, options=MethodOptions(aogan_weights=str(path))) as r:
        frame = r.render(view, proj)
    gb = frame.gbuffer
    expected = infer(model, gbuffer_inputs(gb.depth, gb.normal, view, proj, scene.ao_distance))
    np.testing.assert_allclose(frame.ao["aogan"], expected, atol=1e-5)
    assert frame.gpu_ms["aogan_cpu"] > 0 and np.all(frame.ao["aogan"][~gb.mask] == 1.0)


@pytest.mark.parametrize("damage,message", [
    ("missing", "weights file not found"),
    ("shape", "has shape"),
    ("nan", "NaN"),
])
def test_bad_weights_are_one_line(tmp_path, damage, message):
    torch.manual_seed(1)
    arrays = state_arrays(build_generator())
    path = tmp_path / "w.npz"
    first = next(iter(arrays))
    if damage == "shape":
        arrays[first] = arrays[first][:1]
    if damage == "nan":
        arrays[first].flat[0] = np.nan
    if damage != "missing":
        save_weights(path, "aogan", arrays, {})
    with pytest.raises(RenderError, match=message):
        load_generator(path)
