"""Training of the per-object AO networks of MLP baking (Erra et al.) from a baked PSAO grid.

For every instance: up to `points` AO points of the grid (seeded choice); the input of a point is the
normals of its 16 nearest points (itself first, then by distance; the paper samples 16 normals around the
pixel), the target its traced AO. All instances train at once (one batched network per instance) with
Adam on the mean squared error, as the paper's regression does. An instance without points gets the
constant AO 1 (zero weights, bias 1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from psao.client.render.mlp_pass import MLP_ACTIVATIONS, MLP_HIDDEN, MLP_NORMALS
from psao.eval.learn.grid_points import instance_points
from psao.eval.learn.nn import Adam, DenseNet


@dataclass
class MlpTrainSettings:
    hidden: tuple[int, int] = MLP_HIDDEN  # the paper's NN-32x16
    points: int = 8192  # training points per instance (the paper: 65,536 over four models)
    steps: int = 2000  # Adam steps
    batch: int = 256  # points per instance per step
    lr: float = 3e-3
    seed: int = 1


@dataclass
class MlpTrainResult:
    arrays: dict[str, np.ndarray]
    losses: list[float] = field(default_factory=list)  # mean squared error per step (all instances)
    seconds: float = 0.0
    instances_trained: int = 0


def mlp_dataset(grid, settings: MlpTrainSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inputs (G, points, 48), targets (G, points), has_points (G,)) over the grid's instances."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(settings.seed)
    n_inst = len(grid.instances)
    x = np.zeros((n_inst, settings.points, 3 * MLP_NORMALS))
    y = np.ones((n_inst, settings.points))
    has = np.zeros(n_inst, bool)
    for i in range(n_inst):
        pos, nrm, ao = instance_points(grid.instances, grid.buckets, grid.cells, i)
        if len(pos) == 0:
            continue
        has[i] = True
        pick = rng.choice(len(pos), settings.points, replace=len(pos) < settings.points)
        k = min(MLP_NORMALS, len(pos))
        _, nb = cKDTree(pos).query(pos[pick], k=k)
        nb = np.asarray(nb).reshape(len(pick), k)
        nb = np.concatenate([nb, np.repeat(nb[:, :1], MLP_NORMALS - k, axis=1)], axis=1)  # tiny instances
        x[i] = nrm[nb].reshape(len(pick), -1)
        y[i] = ao[pick]
    return x, y, has


def train_mlp(grid, settings: MlpTrainSettings | None = None, progress=None) -> MlpTrainResult:
    settings = settings or MlpTrainSettings()
    t0 = time.perf_counter()
    x, y, has = mlp_dataset(grid, settings)
    g = len(has)
    net = DenseNet.create([3 * MLP_NORMALS, *settings.hidden, 1], MLP_ACTIVATIONS, settings.seed, groups=g)
    net.params["b2"][:] = y.mean(axis=1, keepdims=True)  # start at each object's mean AO
    opt = Adam(net.params, lr=settings.lr)
    rng = np.random.default_rng(settings.seed + 1)
    losses = []
    rows = np.arange(g)[:, None]
    for step in range(settings.steps):
        idx = rng.integers(0, settings.points, size=(g, settings.batch))
        losses.append(net.train_step(x[rows, idx], y[rows, idx], opt))
        if progress is not None:
            progress(step + 1, settings.steps, losses[-1])
    arrays = {k: v.copy() for k, v in net.params.items()}
    for k in arrays:  # objects without points: AO 1 everywhere
        arrays[k][~has] = 0.0
    arrays["b2"][~has] = 1.0
    return MlpTrainResult(arrays, losses, time.perf_counter() - t0, int(has.sum()))
