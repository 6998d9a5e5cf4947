"""MLP AO baking (Erra et al., "Ambient occlusion baking via a feed-forward neural network"), per fragment.

One network per rigid object (scene instance): 16 object-space normals (48 inputs) -> tanh (MLP_H0 wide)
-> tanh (MLP_H1 wide) -> linear AO, the paper's NN-32x16 by default. It is trained (`psao train mlp`) on
the normals of the 16 nearest AO points around each point of the instance's baked grid; at run time all 16 inputs get the
fragment's own normal, as the paper does, so AO is a function of the object-space normal alone. The
weights file is the whole payload a client needs: bytes = its float32 weights.
"""
from __future__ import annotations

import numpy as np

from psao.client.errors import RenderError
from psao.client.render.gbuffer import GBuffer
from psao.client.render.screenpass import GLOwner, ScreenPass
from psao.client.render.weights import load_weights

MLP_NORMALS = 16  # normals per input vector (the paper's 16 samples)
MLP_HIDDEN = (32, 16)  # the paper's NN-32x16
MLP_ACTIVATIONS = ["tanh", "tanh", "linear"]


def mlp_shapes(n_instances: int | None, hidden=MLP_HIDDEN) -> dict[str, tuple]:
    h0, h1 = hidden
    n = n_instances
    return {"W0": (n, 3 * MLP_NORMALS, h0), "b0": (n, h0), "W1": (n, h0, h1), "b1": (n, h1), "W2": (n, h1, 1), "b2": (n, 1)}


def load_mlp_weights(path, scene) -> tuple[dict[str, np.ndarray], dict]:
    """Weights of every instance of `scene`; the file must come from this very scene."""
    _, header = load_weights(path, "mlp")
    hidden = tuple(header.get("hidden", MLP_HIDDEN))
    arrays, header = load_weights(path, "mlp", mlp_shapes(len(scene.instances), hidden))
    if header.get("scene_hash") != scene.content_hash():
        raise RenderError(f"{path}: MLP weights were trained on another scene ({str(header.get('scene_hash'))[:12]}, "
                          f"{scene.name} has {scene.content_hash()[:12]})")
    return arrays, header


def mlp_numpy(arrays: dict[str, np.ndarray], instance: np.ndarray, local_normal: np.ndarray) -> np.ndarray:
    """AO of fragments (instance index, -1 = background; local normal) with the full 48-input network and
    the normal repeated 16 times: what the shader computes with the folded first layer."""
    inst = np.asarray(instance).reshape(-1)
    n = np.asarray(local_normal, np.float64).reshape(-1, 3)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    out = np.ones(len(inst))
    fg = inst >= 0
    i = inst[fg]
    x = np.tile(n[fg], MLP_NORMALS)
    a = {k: np.asarray(v, np.float64) for k, v in arrays.items()}
    h = np.tanh(np.einsum("pi,pij->pj", x, a["W0"][i]) + a["b0"][i])
    h = np.tanh(np.einsum("pi,pij->pj", h, a["W1"][i]) + a["b1"][i])
    out[fg] = np.clip(np.einsum("pi,pi->p", h, a["W2"][i][..., 0]) + a["b2"][i][:, 0], 0.0, 1.0)
    return out.reshape(np.shape(instance)).astype(np.float32)


def pack_rows(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(n_instances, texels, 4) float32: per instance the folded W0 (3 x MLP_H0), b0, W1, b1, W2, b2."""
    w0 = np.asarray(arrays["W0"], np.float64)
    n, _, h0 = w0.shape
    folded = w0.reshape(n, MLP_NORMALS, 3, h0).sum(axis=1)
    parts = [folded.reshape(n, -1), arrays["b0"], np.asarray(arrays["W1"]).reshape(n, -1), arrays["b1"],
             np.asarray(arrays["W2"]).reshape(n, -1), arrays["b2"]]
    flat = np.concatenate([np.asarray(p, np.float64).reshape(n, -1) for p in parts], axis=1)
    texels = -(-flat.shape[1] // 4)
    rows = np.zeros((n, texels * 4), np.float32)
    rows[:, :flat.shape[1]] = flat
    return rows.reshape(n, texels, 4)


class MlpPass(GLOwner):
    def __init__(self, ctx, gbuffer: GBuffer, arrays: dict[str, np.ndarray]):
        self._gbuffer = gbuffer
        self._objects = []
        try:
            h0, h1 = arrays["W0"].shape[-1], arrays["W1"].shape[-1]
            rows = pack_rows(arrays)
            if rows.shape[1] > 16384 or rows.shape[0] > 16384:
                raise RenderError(f"MLP weights of {rows.shape[0]} instances x {rows.shape[1]} texels exceed a texture")
            self.pass_ = self._keep(ScreenPass(ctx, gbuffer.size, "mlp_ao.frag.glsl", {"MLP_H0": h0, "MLP_H1": h1},
                                               samplers=("u_local_normal", "u_instance", "u_weights")))
            self._weights = self._keep(ctx.texture((rows.shape[1], rows.shape[0]), 4, rows.tobytes(), dtype="f4"))
            self._weights.filter = (ctx.NEAREST, ctx.NEAREST)
        except BaseException:
            self.release()
            raise

    @property
    def output(self):
        return self.pass_.output

    def run(self, view, proj, timer) -> None:
        gb = self._gbuffer
        with timer.measure("mlp"):
            self.pass_.draw([gb["local_normal"], gb["instance"], self._weights])
