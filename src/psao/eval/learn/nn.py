"""A small dense network in numpy with hand-written gradients, and Adam: enough for the learned AO
baselines (Erra et al.'s tanh MLP, Holden et al.'s PReLU network) to train on two CPU cores.

    net = DenseNet.create([48, 32, 16, 1], ["tanh", "tanh", "linear"], seed=1)
    opt = Adam(net.params, lr=1e-3)
    loss = net.train_step(x, y, opt)          # mean squared error (+ L1 of the weights when l1 > 0)

`groups=G` trains G independent networks of the same shape at once (one per rigid object): weights get a
leading axis G, inputs are (G, batch, n_in) and targets (G, batch).

Activations: "tanh", "linear", and "prelu" = Holden et al.'s PReLU(x; a, b) = b max(x, 0) + a min(x, 0)
with a learned slope a and scale b per unit. Parameters live in one dict of float64 arrays
(W0, b0, a0, s0, W1, ...): the weights files store exactly these, as float32.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTIVATIONS = ("tanh", "linear", "prelu")


@dataclass
class DenseNet:
    sizes: list[int]
    activations: list[str]
    params: dict[str, np.ndarray]

    @classmethod
    def create(cls, sizes: list[int], activations: list[str], seed: int, groups: int | None = None) -> "DenseNet":
        if len(activations) != len(sizes) - 1 or any(a not in ACTIVATIONS for a in activations):
            raise ValueError(f"activations {activations} do not fit layer sizes {sizes}")
        rng = np.random.default_rng(seed)
        params = {}
        lead = () if groups is None else (int(groups),)
        for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            params[f"W{i}"] = rng.normal(0.0, np.sqrt(1.0 / n_in), size=(*lead, n_in, n_out))
            params[f"b{i}"] = np.zeros((*lead, n_out))
            if activations[i] == "prelu":
                params[f"a{i}"] = np.full((*lead, n_out), 0.1)  # negative slope
                params[f"s{i}"] = np.ones((*lead, n_out))  # positive scale
        return cls(list(sizes), list(activations), params)

    def forward(self, x: np.ndarray, keep: bool = False, dropout_mask: np.ndarray | None = None):
        """(batch, sizes[0]) -> (batch, sizes[-1]); with keep=True also the values backward() needs."""
        h = np.asarray(x, np.float64)
        if dropout_mask is not None:
            h = h * dropout_mask
        cache = [h]
        for i, act in enumerate(self.activations):
            z = h @ self.params[f"W{i}"] + self.params[f"b{i}"][..., None, :]
            if act == "tanh":
                h = np.tanh(z)
            elif act == "prelu":
                h = self.params[f"s{i}"][..., None, :] * np.maximum(z, 0.0) + \
                    self.params[f"a{i}"][..., None, :] * np.minimum(z, 0.0)
            else:
                h = z
            cache.append((z, h))
        return (h, cache) if keep else h

    def backward(self, cache, grad_out: np.ndarray) -> dict[str, np.ndarray]:
        grads = {}
        g = grad_out
        for i in reversed(range(len(self.activations))):
            z, h = cache[i + 1]
            act = self.activations[i]
            if act == "tanh":
                g = g * (1.0 - h * h)
            elif act == "prelu":
                grads[f"s{i}"] = np.sum(g * np.maximum(z, 0.0), axis=-2)
                grads[f"a{i}"] = np.sum(g * np.minimum(z, 0.0), axis=-2)
                g = g * np.where(z > 0, self.params[f"s{i}"][..., None, :], self.params[f"a{i}"][..., None, :])
            h_in = cache[0] if i == 0 else cache[i][1]
            grads[f"W{i}"] = np.swapaxes(h_in, -1, -2) @ g
            grads[f"b{i}"] = g.sum(axis=-2)
            if i > 0:
                g = g @ np.swapaxes(self.params[f"W{i}"], -1, -2)
        return grads

    def loss(self, x: np.ndarray, y: np.ndarray) -> float:
        return float(np.mean((self.forward(x)[..., 0] - y) ** 2))

    def train_step(self, x, y, opt: "Adam", l1: float = 0.0, input_dropout: float = 0.0,
                   rng: np.random.Generator | None = None) -> float:
        """One Adam step on a mini-batch; returns its mean squared error (before the step)."""
        mask = None
        if input_dropout > 0:
            keep = 1.0 - input_dropout
            mask = (rng.random(x.shape) < keep) / keep
        out, cache = self.forward(x, keep=True, dropout_mask=mask)
        err = out[..., 0] - y
        grads = self.backward(cache, (2.0 / y.shape[-1]) * err[..., None])
        if l1 > 0:
            n_weights = sum(v.size for v in self.params.values())
            for k, v in self.params.items():
                grads[k] = grads[k] + l1 * np.sign(v) / n_weights
        opt.step(self.params, grads)
        return float(np.mean(err ** 2))

    def n_weights(self) -> int:
        return int(sum(v.size for v in self.params.values()))


class Adam:
    def __init__(self, params: dict, lr: float = 1e-3, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8):
        self.lr, self.b1, self.b2, self.eps = lr, beta1, beta2, eps
        self.m = {k: np.zeros_like(v) for k, v in params.items()}
        self.v = {k: np.zeros_like(v) for k, v in params.items()}
        self.t = 0

    def step(self, params: dict, grads: dict) -> None:
        self.t += 1
        c1 = 1.0 - self.b1 ** self.t
        c2 = 1.0 - self.b2 ** self.t
        for k, g in grads.items():
            self.m[k] = self.b1 * self.m[k] + (1 - self.b1) * g
            self.v[k] = self.b2 * self.v[k] + (1 - self.b2) * g * g
            params[k] -= self.lr * (self.m[k] / c1) / (np.sqrt(self.v[k] / c2) + self.eps)
