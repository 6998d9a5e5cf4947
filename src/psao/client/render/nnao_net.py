"""NNAO (Holden et al., "Neural Network Ambient Occlusion"): its input features, its network in numpy,
and the weights file. The shader (src/psao/client/shaders/nnao.frag.glsl) computes the same thing on the GPU; this module
is its oracle and the training's feature extractor.

Features of a pixel: a NNAO_GRID x NNAO_GRID regular grid of view-space offsets in [-r, r]^2 (r = the AO
distance) around its view position, each reprojected to the screen; at the texel found, the difference of
view-space normals and of view depths (divided by r, so one network serves scenes of any scale), scaled
by clamp(1 - |Q - P| / r, 0, 1) so samples beyond the radius contribute nothing. 3844 inputs, then
3844-4-4-4-1 with the paper's PReLU(x; a, b) = b max(x, 0) + a min(x, 0) on every layer. Inputs are
normalised by the training set's mean and deviation, which fold into the first layer (`fold`).

At run time the first layer is four filter textures (the paper's Figure 2), evaluated at NNAO_SAMPLES of
the 961 cells, stratified with a per-pixel jitter and rescaled by 961 / samples, then blurred.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from psao.client.render.weights import load_weights

NNAO_GRID = 31  # the paper's w
NNAO_CELLS = NNAO_GRID * NNAO_GRID
NNAO_FEATURES = 4  # normal difference xyz, depth difference / r
NNAO_INPUTS = NNAO_CELLS * NNAO_FEATURES  # 3844
NNAO_HIDDEN = 4
NNAO_ACTIVATIONS = ["prelu"] * 4
DEFAULT_NNAO_WEIGHTS = Path(__file__).resolve().parent / "nnao_weights.npz"


def nnao_shapes() -> dict[str, tuple]:
    shapes = {"mean": (NNAO_INPUTS,), "std": (NNAO_INPUTS,)}
    sizes = [NNAO_INPUTS, NNAO_HIDDEN, NNAO_HIDDEN, NNAO_HIDDEN, 1]
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        shapes.update({f"W{i}": (n_in, n_out), f"b{i}": (n_out,), f"a{i}": (n_out,), f"s{i}": (n_out,)})
    return shapes


def load_nnao_weights(path=None) -> tuple[dict[str, np.ndarray], dict]:
    return load_weights(path or DEFAULT_NNAO_WEIGHTS, "nnao", nnao_shapes())


def fold(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Normalisation folded into the first layer: W0' = W0 / std, b0' = b0 - (mean / std) . W0."""
    out = {k: np.asarray(v, np.float64) for k, v in arrays.items() if k not in ("mean", "std")}
    std = np.maximum(np.asarray(arrays["std"], np.float64), 1e-6)
    out["W0"] = out["W0"] / std[:, None]
    out["b0"] = out["b0"] - (np.asarray(arrays["mean"], np.float64)) @ out["W0"]
    return out


def cell_offsets() -> np.ndarray:
    """(961, 2) view-space offsets in units of r; cell k = j * 31 + i is (i, j) = (x, y) of the grid."""
    half = (NNAO_GRID - 1) / 2
    k = np.arange(NNAO_CELLS)
    return np.stack([(k % NNAO_GRID - half) / half, (k // NNAO_GRID - half) / half], axis=1)


def _view_position(px, py, depth, size, unproject):
    ndc_x = px / size[0] * 2.0 - 1.0
    ndc_y = py / size[1] * 2.0 - 1.0
    return np.stack([(ndc_x + unproject[2]) * unproject[0] * depth, (ndc_y + unproject[3]) * unproject[1] * depth,
                     -depth], axis=-1)


def features_gl(depth_gl, normal_view_gl, xs, ys, cells, proj, radius: float) -> np.ndarray:
    """(P, C, 4) features of pixels (xs, ys) in GL's bottom-up rows at `cells` ((C,) or (P, C) indices)."""
    h, w = depth_gl.shape
    proj = np.asarray(proj, np.float64)
    un = (1.0 / proj[0, 0], 1.0 / proj[1, 1], proj[0, 2], proj[1, 2])
    d = depth_gl[ys, xs].astype(np.float64)
    P = _view_position(xs + 0.5, ys + 0.5, d, (w, h), un)
    nc = normal_view_gl[ys, xs].astype(np.float64)
    cells = np.broadcast_to(np.asarray(cells), (len(xs), np.shape(cells)[-1]))
    off = cell_offsets()[cells] * radius  # (P, C, 2)
    S = P[:, None, :] + np.concatenate([off, np.zeros(off.shape[:2] + (1,))], axis=2)
    clip = S @ proj[:3, :3].T + proj[:3, 3]
    cw = S @ proj[3, :3] + proj[3, 3]
    ok = cw > 0
    ndc = clip[..., :2] / np.where(ok, cw, 1.0)[..., None]
    tx = np.floor((ndc[..., 0] * 0.5 + 0.5) * w)
    ty = np.floor((ndc[..., 1] * 0.5 + 0.5) * h)
    ok &= (tx >= 0) & (ty >= 0) & (tx < w) & (ty < h)
    tx = np.clip(tx, 0, w - 1).astype(np.int64)
    ty = np.clip(ty, 0, h - 1).astype(np.int64)
    ds = depth_gl[ty, tx].astype(np.float64)
    ok &= ds > 0
    Q = _view_position(tx + 0.5, ty + 0.5, ds, (w, h), un)
    dist = np.linalg.norm(Q - P[:, None, :], axis=2)
    scale = np.where(ok, np.clip(1.0 - dist / radius, 0.0, 1.0), 0.0)
    f = np.concatenate([normal_view_gl[ty, tx] - nc[:, None, :], ((ds - d[:, None]) / radius)[..., None]], axis=2)
    return f * scale[..., None]


def prelu(z, a, s):
    return s * np.maximum(z, 0.0) + a * np.minimum(z, 0.0)


def head(folded: dict[str, np.ndarray], z0: np.ndarray) -> np.ndarray:
    """Layers after the first dot products: z0 (P, 4) = W0' . x + b0' -> AO (P,), clamped to [0, 1]."""
    h = prelu(z0, folded["a0"], folded["s0"])
    for i in (1, 2, 3):
        h = prelu(h @ folded[f"W{i}"] + folded[f"b{i}"], folded[f"a{i}"], folded[f"s{i}"])
    return np.clip(h[:, 0], 0.0, 1.0)


def nnao_noise() -> np.ndarray:
    """4x4 RGBA32F tile: x = the stratification jitter in [0, 1) (a 4x4 Bayer order)."""
    bayer = np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]], dtype=np.float64)
    tile = np.zeros((4, 4, 4), np.float32)
    tile[..., 0] = (bayer + 0.5) / 16.0
    return tile


def stratified_cells(jitter: np.ndarray, samples: int) -> np.ndarray:
    """(P, samples) cell indices floor((m + jitter) * 961 / samples), m = 0..samples-1."""
    m = np.arange(samples)
    k = np.floor((m[None, :] + np.asarray(jitter, np.float64)[:, None]) * (NNAO_CELLS / samples))
    return np.minimum(k, NNAO_CELLS - 1).astype(np.int64)


def nnao_numpy(depth, normal, view, proj, arrays, radius: float, samples: int = NNAO_CELLS) -> np.ndarray:
    """(H, W) AO before the blur from top-down depth and world normals, as the shader computes it
    (samples < 961: the stratified, jittered first layer)."""
    folded = fold(arrays)
    d_gl = np.asarray(depth, np.float64)[::-1]
    n_gl = (np.asarray(normal, np.float64) @ np.asarray(view, np.float64)[:3, :3].T)[::-1]
    n_gl /= np.maximum(np.linalg.norm(n_gl, axis=2, keepdims=True), 1e-30)
    out = np.ones(d_gl.shape)
    ys, xs = np.nonzero(d_gl > 0)
    for lo in range(0, len(xs), 2048):
        x, y = xs[lo:lo + 2048], ys[lo:lo + 2048]
        if samples >= NNAO_CELLS:
            cells, gain = np.arange(NNAO_CELLS), 1.0
        else:
            cells, gain = stratified_cells(nnao_noise()[y & 3, x & 3, 0], samples), NNAO_CELLS / samples
        f = features_gl(d_gl, n_gl, x, y, cells, proj, radius)  # (P, C, 4)
        w0 = folded["W0"].reshape(NNAO_CELLS, NNAO_FEATURES, NNAO_HIDDEN)[cells]  # (C, 4, 4) or (P, C, 4, 4)
        z0 = (np.einsum("pcf,cfh->ph", f, w0) if w0.ndim == 3 else np.einsum("pcf,pcfh->ph", f, w0)) * gain
        out[y, x] = head(folded, z0 + folded["b0"])
    return out[::-1].astype(np.float32)
