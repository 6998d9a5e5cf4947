"""Pass 3: lit colour x AO into an sRGB RGBA8 image (src/psao/client/shaders/composite.frag.glsl)."""
from __future__ import annotations

import numpy as np

from psao.client.render.gbuffer import GBuffer
from psao.client.render.shaderlib import compile_program

BACKGROUND = (0.62, 0.74, 0.88)  # linear sky colour


class CompositePass:
    def __init__(self, ctx, gbuffer: GBuffer, background=BACKGROUND):
        self._ctx = ctx
        self._gbuffer = gbuffer
        self.program = compile_program(ctx, vertex_shader="fullscreen.vert.glsl", fragment_shader="composite.frag.glsl")
        self.program["u_color"].value = 0
        self.program["u_ao"].value = 1
        self.program["u_background"].value = tuple(float(c) for c in background)
        self._vao = ctx.vertex_array(self.program, [])
        self.output = ctx.texture(gbuffer.size, 4, dtype="f1")
        self._fbo = ctx.framebuffer([self.output])

    def run(self, ao_texture) -> None:
        ctx = self._ctx
        self._gbuffer["color"].use(0)
        ao_texture.use(1)
        self._fbo.use()
        ctx.viewport = (0, 0, *self._gbuffer.size)
        ctx.disable(ctx.DEPTH_TEST)
        self._vao.render(ctx.TRIANGLES, vertices=3)

    def read(self) -> np.ndarray:
        """(H, W, 3) uint8, top row first."""
        w, h = self._gbuffer.size
        rgba = np.frombuffer(self.output.read(), dtype=np.uint8).reshape(h, w, 4)[::-1]
        return np.ascontiguousarray(rgba[..., :3])

    @property
    def fbo(self):
        return self._fbo

    def release(self) -> None:
        for obj in (self._vao, self._fbo, self.output, self.program):
            obj.release()


def read_channel(texture, size: tuple[int, int], components: int, channel: int = 0) -> np.ndarray:
    """One float32 channel of a texture as a top-down (H, W) array."""
    w, h = size
    arr = np.frombuffer(texture.read(), dtype=np.float32).reshape(h, w, components)[::-1, :, channel]
    return np.ascontiguousarray(arr)
