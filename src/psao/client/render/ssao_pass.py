"""SSAO baseline (src/psao/client/shaders/ssao.frag.glsl + ssao_blur.frag.glsl): what a user would pick instead of PSAO.

Normal-oriented hemisphere SSAO as in Crytek / LearnOpenGL: a fixed kernel of SSAO_SAMPLES points in
the unit hemisphere, denser near the centre, rotated per pixel by a 4x4 noise tile; the radius is the
scene's AO distance (world units); a range check fades occluders far behind depth edges; a depth- and
normal-aware 4x4 blur removes the noise-tile pattern. Kernel and noise come from psao.protocol.ssao_kernel,
the page's too.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.client.render.gbuffer import GBuffer, gl_mat4
from psao.protocol import ssao_kernel
from psao.protocol.ssao_kernel import hemisphere_kernel, rotation_noise
from psao.client.render.shaderlib import compile_program


@dataclass
class SsaoSettings:
    samples: int = ssao_kernel.SAMPLES  # kernel size
    radius: float = 0.6  # world units; the renderer sets it to the scene's AO distance
    bias_fraction: float = 0.025  # depth bias as a fraction of the radius (self-occlusion on flat floors)
    seed: int = ssao_kernel.SEED  # kernel and noise (the web page draws the defaults' kernel)


class SsaoPass:
    def __init__(self, ctx, gbuffer: GBuffer, settings: SsaoSettings):
        if settings.samples < 1 or settings.samples > 256:
            from psao.client.errors import RenderError

            raise RenderError(f"SSAO sample count {settings.samples} outside 1..256")
        self._ctx = ctx
        self._gbuffer = gbuffer
        self.settings = settings
        self.program = compile_program(
            ctx, {"SSAO_SAMPLES": int(settings.samples)}, vertex_shader="fullscreen.vert.glsl", fragment_shader="ssao.frag.glsl"
        )
        self.blur_program = compile_program(ctx, vertex_shader="fullscreen.vert.glsl", fragment_shader="ssao_blur.frag.glsl")
        self._vao = ctx.vertex_array(self.program, [])
        self._blur_vao = ctx.vertex_array(self.blur_program, [])
        self.raw = ctx.texture(gbuffer.size, 1, dtype="f4")
        self.output = ctx.texture(gbuffer.size, 1, dtype="f4")
        self._noise = ctx.texture((4, 4), 4, rotation_noise(settings.seed).tobytes(), dtype="f4")
        for tex in (self.raw, self.output, self._noise):
            tex.filter = (ctx.NEAREST, ctx.NEAREST)
        self._raw_fbo = ctx.framebuffer([self.raw])
        self._out_fbo = ctx.framebuffer([self.output])
        p = self.program
        p["u_world"].value, p["u_normal"].value, p["u_depth"].value, p["u_noise"].value = 0, 1, 2, 3
        p["u_kernel"].write(hemisphere_kernel(settings.samples, settings.seed).tobytes())
        p["u_radius"].value = float(settings.radius)
        p["u_bias"].value = float(settings.radius * settings.bias_fraction)
        b = self.blur_program
        b["u_ao"].value, b["u_depth"].value, b["u_normal"].value = 0, 1, 2
        b["u_radius"].value = float(settings.radius)

    def run_occlusion(self, view: np.ndarray, proj: np.ndarray) -> None:
        ctx, gb = self._ctx, self._gbuffer
        gb["world"].use(0)
        gb["normal"].use(1)
        gb["depth"].use(2)
        self._noise.use(3)
        self.program["u_view"].write(gl_mat4(view))
        self.program["u_proj"].write(gl_mat4(proj))
        self.program["u_unproject"].value = (1.0 / proj[0, 0], 1.0 / proj[1, 1], proj[0, 2], proj[1, 2])
        self._raw_fbo.use()
        ctx.viewport = (0, 0, *gb.size)
        ctx.disable(ctx.DEPTH_TEST)
        self._vao.render(ctx.TRIANGLES, vertices=3)

    def run_blur(self) -> None:
        ctx, gb = self._ctx, self._gbuffer
        self.raw.use(0)
        gb["depth"].use(1)
        gb["normal"].use(2)
        self._out_fbo.use()
        ctx.viewport = (0, 0, *gb.size)
        self._blur_vao.render(ctx.TRIANGLES, vertices=3)

    def release(self) -> None:
        for obj in (self._vao, self._blur_vao, self._raw_fbo, self._out_fbo, self.raw, self.output, self._noise,
                    self.program, self.blur_program):
            obj.release()
