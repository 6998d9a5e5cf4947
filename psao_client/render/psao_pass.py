"""Pass 2: PSAO reconstruction per pixel from the storage buffers (shaders/psao_common.glsl, eq. 2-4).

Output: an RG32F texture, r = AO in [0, 1] (1 on background and where no point has weight),
g = the weight sum (0 marks a hole: no point within reach).

Two equivalent shaders exist: a full-screen fragment pass (psao_ao.frag.glsl) and a compute pass
(psao_ao.comp.glsl). VARIANT picks the one that measured faster on llvmpipe (benchmarks/bench_render.py
--variants compares them); both use the same include, so they agree bit for bit.
"""
from __future__ import annotations

from dataclasses import dataclass

from psao_client.render.gbuffer import GBuffer
from psao_client.render.gpu_grid import GpuGrid
from psao_client.render.shaderlib import compile_program

VARIANT = "fragment"
_LOCAL_SIZE = 8  # compute work group is 8 x 8, as in psao_ao.comp.glsl


@dataclass
class PsaoSettings:
    t_n: float = 0.1  # eq. 3 normal threshold (paper value)
    t_d: float = 0.7  # eq. 3 distance-direction threshold (paper value)


class PsaoPass:
    def __init__(self, ctx, gbuffer: GBuffer, grid: GpuGrid, settings: PsaoSettings | None = None, variant: str = VARIANT):
        if variant not in ("fragment", "compute"):
            raise ValueError(f"unknown PSAO variant {variant!r}")
        self._ctx = ctx
        self._gbuffer = gbuffer
        self._grid = grid
        self.variant = variant
        s = settings or PsaoSettings()
        defines = {"PSAO_T_N": float(s.t_n), "PSAO_T_D": float(s.t_d)}
        self.output = ctx.texture(gbuffer.size, 2, dtype="f4")
        self.output.filter = (ctx.NEAREST, ctx.NEAREST)
        if variant == "fragment":
            self.program = compile_program(ctx, defines, vertex_shader="fullscreen.vert.glsl", fragment_shader="psao_ao.frag.glsl")
            self._vao = ctx.vertex_array(self.program, [])
            self._fbo = ctx.framebuffer([self.output])
        else:
            self.program = compile_program(ctx, defines, compute="psao_ao.comp.glsl")
            self._vao = self._fbo = None
        self.program["u_local"].value = 0
        self.program["u_local_normal"].value = 1
        self.program["u_instance"].value = 2

    def run(self) -> None:
        ctx, gb = self._ctx, self._gbuffer
        gb["local"].use(0)
        gb["local_normal"].use(1)
        gb["instance"].use(2)
        self._grid.bind()
        if self.variant == "fragment":
            self._fbo.use()
            ctx.viewport = (0, 0, *gb.size)
            ctx.disable(ctx.DEPTH_TEST)
            self._vao.render(ctx.TRIANGLES, vertices=3)
        else:
            self.output.bind_to_image(0, read=False, write=True)
            w, h = gb.size
            self.program.run((w + _LOCAL_SIZE - 1) // _LOCAL_SIZE, (h + _LOCAL_SIZE - 1) // _LOCAL_SIZE, 1)
            ctx.memory_barrier()

    def release(self) -> None:
        for obj in (self._vao, self._fbo, self.program, self.output):
            if obj is not None:
                obj.release()
