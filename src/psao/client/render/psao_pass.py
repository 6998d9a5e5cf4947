"""Pass 2: PSAO reconstruction per pixel from the grid tables (src/psao/protocol/shaders/psao_common.glsl, eq. 2-4).

Output: an RG32F texture, r = AO in [0, 1] (1 on background and where no point has weight),
g = the weight sum (0 marks a hole: no point within reach).

A full-screen fragment pass (psao_ao.frag.glsl); the thresholds are compiled in as defines.
"""
from __future__ import annotations

from dataclasses import dataclass

from psao.protocol import gridformat as gf
from psao.client.render.gbuffer import GBuffer
from psao.client.render.gpu_grid import GpuGrid
from psao.client.render.shaderlib import compile_program


@dataclass
class PsaoSettings:
    t_n: float = gf.T_N  # eq. 3 normal threshold (cosine)
    t_d: float = gf.T_D  # eq. 3 distance-direction threshold (squared cosine)


class PsaoPass:
    def __init__(self, ctx, gbuffer: GBuffer, grid: GpuGrid, settings: PsaoSettings | None = None):
        self._ctx = ctx
        self._gbuffer = gbuffer
        self._grid = grid
        s = settings or PsaoSettings()
        defines = {"PSAO_T_N": float(s.t_n), "PSAO_T_D": float(s.t_d)}
        self.output = ctx.texture(gbuffer.size, 2, dtype="f4")
        self.output.filter = (ctx.NEAREST, ctx.NEAREST)
        self.program = compile_program(ctx, defines, vertex_shader="fullscreen.vert.glsl", fragment_shader="psao_ao.frag.glsl")
        self._vao = ctx.vertex_array(self.program, [])
        self._fbo = ctx.framebuffer([self.output])
        for unit, name in enumerate(("u_local", "u_local_normal", "u_instance")):
            self.program[name].value = unit
        grid.prepare(self.program)

    def run(self) -> None:
        ctx, gb = self._ctx, self._gbuffer
        gb["local"].use(0)
        gb["local_normal"].use(1)
        gb["instance"].use(2)
        self._grid.bind()
        self._fbo.use()
        ctx.viewport = (0, 0, *gb.size)
        ctx.disable(ctx.DEPTH_TEST)
        self._vao.render(ctx.TRIANGLES, vertices=3)

    def release(self) -> None:
        for obj in (self._vao, self._fbo, self.program, self.output):
            obj.release()
