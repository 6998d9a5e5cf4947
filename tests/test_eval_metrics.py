"""Metrics: PSNR against its formula, identical images, FLIP input validation (never reaches native code)."""
from __future__ import annotations

import numpy as np
import pytest

from psao.eval.errors import EvalError
from psao.eval.metrics import PSNR_CAP, composite_ao, flip, magma, psnr, score, ssim


@pytest.fixture
def ao_pair():
    rng = np.random.default_rng(3)
    ref = rng.random((40, 64)).astype(np.float32)
    return ref, np.clip(ref + rng.normal(0, 0.05, ref.shape), 0, 1).astype(np.float32)


def test_identical_images(ao_pair):
    ref, _ = ao_pair
    s, fmap = score(ref, ref.copy())
    assert s.psnr == PSNR_CAP
    assert s.ssim == pytest.approx(1.0)
    assert s.flip == 0.0
    assert s.bias == 0.0
    assert fmap.shape == ref.shape and np.all(fmap == 0)


def test_psnr_matches_its_formula(ao_pair):
    ref, img = ao_pair
    mse = float(np.mean((ref.astype(np.float64) - img) ** 2))
    assert psnr(ref, img) == pytest.approx(10 * np.log10(1.0 / mse), rel=1e-5)


def test_worse_images_score_worse(ao_pair):
    ref, img = ao_pair
    rng = np.random.default_rng(4)
    worse = np.clip(ref + rng.normal(0, 0.2, ref.shape), 0, 1).astype(np.float32)
    assert psnr(ref, worse) < psnr(ref, img)
    assert ssim(ref, worse) < ssim(ref, img)
    f_img, map_img = flip(ref, img)
    f_worse, _ = flip(ref, worse)
    assert 0 < f_img < f_worse < 1
    assert map_img.min() >= 0 and map_img.max() <= 1
    assert f_img == pytest.approx(float(map_img.mean()), rel=1e-4)  # the mean is the map's mean


def test_bias_is_the_mean_signed_difference():
    ref = np.full((16, 16), 0.5, np.float32)
    brighter = np.full((16, 16), 0.7, np.float32)
    assert score(ref, brighter)[0].bias == pytest.approx(0.2, abs=1e-6)
    assert score(brighter, ref)[0].bias == pytest.approx(-0.2, abs=1e-6)


def test_flip_is_symmetric_enough_and_grey_in_grey_out():
    ref = np.full((16, 16), 0.5, np.float32)
    dark = np.full((16, 16), 0.2, np.float32)
    f, fmap = flip(ref, dark)
    assert f > 0.05
    assert np.allclose(fmap, fmap[0, 0], atol=1e-3)  # uniform difference, uniform error


@pytest.mark.parametrize("bad,msg", [
    (np.full((16, 16), np.nan, np.float32), "NaN"),
    (np.full((16, 16), 1.5, np.float32), "outside"),
    (np.full((16, 16), -0.1, np.float32), "outside"),
    (np.zeros((16, 16, 3), np.float32), "shape"),
    (np.zeros((16, 17), np.float32), "differ in shape"),
    (np.zeros((4, 4), np.float32), "smaller than 8x8"),
    (np.array([["a"] * 16] * 16), "dtype"),
])
def test_bad_inputs_raise_instead_of_exiting(bad, msg):
    ref = np.full((16, 16), 0.5, np.float32)
    with pytest.raises(EvalError, match=msg):
        flip(ref, bad)
    with pytest.raises(EvalError, match=msg):
        psnr(ref, bad)


def test_composite_sets_background_to_one_and_clips():
    ao = np.array([[0.2, -0.1], [1.3, np.nan]], np.float32)
    mask = np.array([[True, True], [True, False]])
    out = composite_ao(ao, mask)
    np.testing.assert_array_equal(out, np.array([[0.2, 0.0], [1.0, 1.0]], np.float32))  # NaN on background is fine
    with pytest.raises(EvalError, match="NaN"):
        composite_ao(ao, np.ones((2, 2), bool))
    with pytest.raises(EvalError, match="shapes"):
        composite_ao(ao, np.ones((3, 2), bool))


def test_magma_map_is_rgb_uint8():
    m = magma(np.linspace(0, 1, 20, dtype=np.float32).reshape(4, 5))
    assert m.shape == (4, 5, 3) and m.dtype == np.uint8
    assert m[0, 0].sum() < m[-1, -1].sum()  # black to bright
