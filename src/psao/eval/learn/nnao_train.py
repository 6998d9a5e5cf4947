"""Training of NNAO (Holden et al.) on this project's own G-buffers and RTAO at sampled pixels.

Data: for every training scene, frames along its camera path and along the orbit around its bounds are
rendered by the client's renderer (the G-buffer every method shades); `pixels` covered pixels per frame
are picked at random (the paper: 1024 of 1280x720) and only those are ray traced (the RTAO reference's
tracer, `spp` cosine-weighted rays within the AO distance). Inputs are nnao_net.features_gl of the full
31 x 31 grid, normalised by their mean and deviation; the network trains with Adam on mini-batches,
dropout 0.5 on the input and a small L1 term, as the paper does (its L1 weight 0.01 is applied to the
mean absolute parameter).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from psao.client.render.nnao_net import NNAO_ACTIVATIONS, NNAO_CELLS, NNAO_HIDDEN, NNAO_INPUTS, features_gl
from psao.eval.learn.nn import Adam, DenseNet

TRAINING_SCENES = ("builtin:pavilion", "builtin:playground")  # example TOML scenes, kept out of the benchmark


@dataclass
class NnaoDataSettings:
    frames: int = 16  # per scene: half along its camera path, half on the orbit around its bounds
    pixels: int = 768  # sampled pixels per frame
    spp: int = 256  # RTAO rays per sampled pixel
    size: tuple[int, int] = (640, 360)
    seed: int = 1


@dataclass
class NnaoTrainSettings:
    epochs: int = 12
    batch: int = 64
    lr: float = 1e-3
    input_dropout: float = 0.5
    l1: float = 0.01
    seed: int = 1


@dataclass
class NnaoTrainResult:
    arrays: dict[str, np.ndarray]
    losses: list[float] = field(default_factory=list)  # per step
    seconds: float = 0.0


def scene_frames(scene, frames: int, size):
    """(view, proj) pairs: along the scene's first camera path and along the orbit around its bounds."""
    from psao.client.render.views import path_matrices, path_times
    from psao.scene.camera import default_orbit, scene_camera

    paths = [scene_camera(scene, None)]
    if scene.camera_paths:
        paths.append(default_orbit(scene))
    per = [frames - frames // len(paths) * (len(paths) - 1)] + [frames // len(paths)] * (len(paths) - 1)
    return [path_matrices(scene, p, float(t), size) for p, n in zip(paths, per) if n > 0 for t in path_times(p, n)]


def build_dataset(scenes, settings: NnaoDataSettings, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """(inputs (N, 3844) float32, RTAO targets (N,)) over every scene and frame."""
    from psao.client.render.renderer import FrameRenderer
    from psao.eval.quality import rest_transforms
    from psao.eval.reference import ReferenceSettings, trace_pixels

    rng = np.random.default_rng(settings.seed)
    xs, ys = [], []
    for scene in scenes:
        poses = scene_frames(scene, settings.frames, settings.size)
        with FrameRenderer(scene, settings.size, "ssao", timing=False) as r:
            for view, proj in poses:
                gb = r.render(view, proj).gbuffer
                idx = np.flatnonzero(gb.mask.reshape(-1))
                if len(idx) == 0:
                    continue
                pick = np.sort(rng.choice(idx, min(settings.pixels, len(idx)), replace=False))
                world = gb.world.reshape(-1, 3)[pick].astype(np.float64)
                normal = gb.normal.reshape(-1, 3)[pick].astype(np.float64)
                normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
                ao = trace_pixels(scene, world, normal.astype(np.float32), pick, rest_transforms(scene),
                                  ReferenceSettings(spp=settings.spp, cache_dir=None))
                h = gb.depth.shape[0]
                py, px = np.divmod(pick, gb.depth.shape[1])
                n_view = gb.normal @ np.asarray(view, np.float64)[:3, :3].T
                n_view /= np.maximum(np.linalg.norm(n_view, axis=2, keepdims=True), 1e-30)
                f = features_gl(gb.depth[::-1].astype(np.float64), n_view[::-1], px, h - 1 - py,
                                np.arange(NNAO_CELLS), proj, float(scene.ao_distance))
                xs.append(f.reshape(len(pick), NNAO_INPUTS).astype(np.float32))
                ys.append(np.asarray(ao, np.float64))
                if progress is not None:
                    progress(sum(len(y) for y in ys))
    return np.concatenate(xs), np.concatenate(ys)


def train_nnao(x: np.ndarray, y: np.ndarray, settings: NnaoTrainSettings | None = None, steps: int | None = None,
               progress=None) -> NnaoTrainResult:
    """Weights (raw network + mean/std) from a dataset; `steps` overrides the epoch count."""
    settings = settings or NnaoTrainSettings()
    t0 = time.perf_counter()
    mean = x.mean(axis=0, dtype=np.float64)
    std = np.maximum(x.std(axis=0, dtype=np.float64), 1e-6)
    net = DenseNet.create([NNAO_INPUTS, NNAO_HIDDEN, NNAO_HIDDEN, NNAO_HIDDEN, 1], NNAO_ACTIVATIONS, settings.seed)
    net.params["W0"] *= 0.1  # 3844 inputs: start with small first-layer sums
    net.params["b3"][:] = y.mean()
    opt = Adam(net.params, lr=settings.lr)
    rng = np.random.default_rng(settings.seed + 1)
    total = steps if steps is not None else settings.epochs * max(1, len(y) // settings.batch)
    losses = []
    order = rng.permutation(len(y))
    pos = 0
    for step in range(total):
        if pos + settings.batch > len(y):
            order, pos = rng.permutation(len(y)), 0
        b = order[pos:pos + settings.batch]
        pos += settings.batch
        xb = (x[b].astype(np.float64) - mean) / std
        losses.append(net.train_step(xb, y[b], opt, l1=settings.l1, input_dropout=settings.input_dropout, rng=rng))
        if progress is not None:
            progress(step + 1, total, losses[-1])
    arrays = {k: v.copy() for k, v in net.params.items()}
    arrays["mean"], arrays["std"] = mean, std
    return NnaoTrainResult(arrays, losses, time.perf_counter() - t0)


def predict(arrays: dict[str, np.ndarray], x: np.ndarray) -> np.ndarray:
    """AO of raw input rows (N, 3844) with the folded first layer, as the renderer evaluates it."""
    from psao.client.render.nnao_net import fold, head

    f = fold(arrays)
    return head(f, np.asarray(x, np.float64) @ f["W0"] + f["b0"])
