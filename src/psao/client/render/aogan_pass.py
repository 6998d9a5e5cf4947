"""AOGAN in the client process: read the G-buffer back, run the generator on the CPU (PyTorch), upload the
AO so the composite pass shades with it. Its cost is CPU milliseconds (`cpu_ms`, read-back included),
reported beside the GPU timer queries as "aogan_cpu"."""
from __future__ import annotations

import time

import numpy as np

from psao.client.render.aogan_net import gbuffer_inputs, infer
from psao.client.render.composite import read_channel
from psao.client.render.gbuffer import GBuffer
from psao.client.render.screenpass import GLOwner


class AoganPass(GLOwner):
    def __init__(self, ctx, gbuffer: GBuffer, model, radius: float):
        self._gbuffer = gbuffer
        self._model = model
        self._radius = float(radius)
        self._objects = []
        self.output = self._keep(ctx.texture(gbuffer.size, 1, dtype="f4"))
        self.output.filter = (ctx.NEAREST, ctx.NEAREST)
        self.cpu_ms = 0.0

    def run(self, view, proj, timer) -> None:
        start = time.perf_counter()
        w, h = self._gbuffer.size
        depth = read_channel(self._gbuffer["depth"], (w, h), 1, 0)
        normal = np.frombuffer(self._gbuffer["normal"].read(), np.float32).reshape(h, w, 4)[::-1, :, :3]
        ao = infer(self._model, gbuffer_inputs(depth, normal, view, proj, self._radius))
        self.output.write(np.ascontiguousarray(ao[::-1]).tobytes())
        self.cpu_ms = (time.perf_counter() - start) * 1e3
