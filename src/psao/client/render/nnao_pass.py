"""NNAO pass (src/psao/client/shaders/nnao.frag.glsl, then the bilateral blur): see src/psao/client/render/nnao_net.py."""
from __future__ import annotations

import numpy as np

from psao.client.errors import RenderError
from psao.client.render.gbuffer import GBuffer, gl_mat4
from psao.client.render.gtao_pass import BilateralBlur, unproject_vector
from psao.client.render.nnao_net import NNAO_CELLS, NNAO_FEATURES, NNAO_GRID, NNAO_HIDDEN, fold, nnao_noise
from psao.client.render.screenpass import GLOwner, ScreenPass

NNAO_SAMPLE_COUNTS = (64, 128, 256, NNAO_CELLS)  # the paper's table rows, and every cell


def filter_texels(folded: dict[str, np.ndarray]) -> np.ndarray:
    """(GRID, 4 * GRID, 4) float32: row j, column 4 i + f holds the 4 filter weights of feature f of cell (i, j)."""
    w0 = np.asarray(folded["W0"], np.float32).reshape(NNAO_GRID, NNAO_GRID, NNAO_FEATURES, NNAO_HIDDEN)
    return np.ascontiguousarray(w0.reshape(NNAO_GRID, NNAO_GRID * NNAO_FEATURES, NNAO_HIDDEN))


class NnaoPass(GLOwner):
    def __init__(self, ctx, gbuffer: GBuffer, arrays: dict[str, np.ndarray], radius: float, samples: int = 64):
        if samples not in NNAO_SAMPLE_COUNTS:
            raise RenderError(f"NNAO samples {samples}: expected one of {', '.join(map(str, NNAO_SAMPLE_COUNTS))}")
        self._gbuffer = gbuffer
        self._objects = []
        try:
            f = fold(arrays)
            self.net = self._keep(ScreenPass(ctx, gbuffer.size, "nnao.frag.glsl", {"NNAO_SAMPLES": int(samples)},
                                             samplers=("u_depth", "u_normal", "u_noise", "u_filters")))
            self.blur = self._keep(BilateralBlur(ctx, gbuffer.size, radius))
            self._noise = self._keep(ctx.texture((4, 4), 4, nnao_noise().tobytes(), dtype="f4"))
            tex = filter_texels(f)
            self._filters = self._keep(ctx.texture((tex.shape[1], tex.shape[0]), 4, tex.tobytes(), dtype="f4"))
            for t in (self._noise, self._filters):
                t.filter = (ctx.NEAREST, ctx.NEAREST)
            p = self.net.program
            vec = {k: tuple(float(x) for x in np.asarray(v).reshape(-1)) for k, v in f.items() if k != "W0"}
            self.net.set(u_radius=float(radius), u_b0=vec["b0"], u_a0=vec["a0"], u_s0=vec["s0"], u_b1=vec["b1"],
                         u_a1=vec["a1"], u_s1=vec["s1"], u_b2=vec["b2"], u_a2=vec["a2"], u_s2=vec["s2"],
                         u_W3=vec["W3"], u_out=(vec["b3"][0], vec["a3"][0], vec["s3"][0]))
            for name in ("W1", "W2"):
                p[f"u_{name}"].write(np.ascontiguousarray(np.asarray(f[name], np.float32)).tobytes())
        except BaseException:
            self.release()
            raise

    @property
    def raw(self):
        return self.net.output

    @property
    def output(self):
        return self.blur.output

    def run(self, view, proj, timer) -> None:
        gb = self._gbuffer
        self.net.program["u_view_rot"].write(np.ascontiguousarray(np.asarray(view, np.float32)[:3, :3].T).tobytes())
        self.net.program["u_proj"].write(gl_mat4(proj))
        self.net.set(u_unproject=unproject_vector(proj))
        with timer.measure("nnao"):
            self.net.draw([gb["depth"], gb["normal"], self._noise, self._filters])
        with timer.measure("nnao_blur"):
            self.blur.run(self.raw, gb)
