"""One full-screen fragment pass into a float texture: the building block of the screen-space AO methods.

    p = ScreenPass(ctx, size, "gtao.frag.glsl", defines, components=1)
    p.program["u_radius"].value = 0.6
    p.draw([gbuffer["depth"], gbuffer["normal"]])   # textures bound to units 0, 1, ... in order

The output texture is NEAREST-filtered (passes read it with texelFetch). release() frees every GL object.
"""
from __future__ import annotations

from psao.client.render.shaderlib import compile_program


class GLOwner:
    """Keeps the GL objects (or passes) it creates and releases them, last first."""

    _objects: list

    def _keep(self, obj):
        self._objects.append(obj)
        return obj

    def release(self) -> None:
        for obj in reversed(self._objects):
            obj.release()
        self._objects = []


class ScreenPass(GLOwner):
    def __init__(self, ctx, size: tuple[int, int], fragment_shader: str, defines: dict | None = None,
                 components: int = 1, samplers: tuple[str, ...] = ()):
        self._ctx = ctx
        self.size = (int(size[0]), int(size[1]))
        self.program = compile_program(ctx, defines, vertex_shader="fullscreen.vert.glsl", fragment_shader=fragment_shader)
        self._objects = [self.program]
        try:
            self._vao = self._keep(ctx.vertex_array(self.program, []))
            self.output = self._keep(ctx.texture(self.size, components, dtype="f4"))
            self.output.filter = (ctx.NEAREST, ctx.NEAREST)
            self._fbo = self._keep(ctx.framebuffer([self.output]))
            for unit, name in enumerate(samplers):
                self.program[name].value = unit
        except BaseException:
            self.release()
            raise

    def set(self, **uniforms) -> None:
        """Set uniforms by name; a uniform the compiler optimised away is skipped."""
        for name, value in uniforms.items():
            if name in self.program:
                self.program[name].value = value

    def draw(self, textures) -> None:
        ctx = self._ctx
        for unit, tex in enumerate(textures):
            tex.use(unit)
        self._fbo.use()
        ctx.viewport = (0, 0, *self.size)
        ctx.disable(ctx.DEPTH_TEST)
        self._vao.render(ctx.TRIANGLES, vertices=3)
