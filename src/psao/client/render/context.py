"""OpenGL context for the renderer: a headless EGL context by default, a window when asked.

The shaders are `#version 410` (integer textures, explicit locations; no storage buffers, see
gpu_grid.py), so any OpenGL 4.1 driver will do, macOS's included; Mesa's llvmpipe offers 4.5 through
EGL, so the renderer runs on a machine without a GPU. Failures become RenderError with one line naming the cause.
"""
from __future__ import annotations

from psao.client.errors import RenderError

REQUIRED_GL = 410  # the shaders' #version


def create_context(window: bool = False, size: tuple[int, int] = (640, 360)):
    """A moderngl context with GL >= 4.1: standalone EGL (headless), or an on-screen window (glfw)."""
    import moderngl

    if window:
        ctx = _window_context(size)
    else:
        try:
            ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # glcontext raises plain Exception/ValueError types for EGL failures
            raise RenderError(f"no EGL display available: {_one_line(exc)}") from None
    check_version(ctx)
    return ctx


def check_version(ctx) -> None:
    if ctx.version_code < REQUIRED_GL:
        renderer = ctx.info.get("GL_RENDERER", "?")
        ctx.release()
        raise RenderError(f"OpenGL 4.1 or newer is needed; {renderer} offers {ctx.version_code}")


def max_frame_size(ctx) -> tuple[int, int]:
    """Largest (width, height) both a texture and the viewport accept."""
    tex = int(ctx.info["GL_MAX_TEXTURE_SIZE"])
    vw, vh = (int(v) for v in ctx.info["GL_MAX_VIEWPORT_DIMS"])
    return min(tex, vw), min(tex, vh)


def check_frame_size(ctx, size: tuple[int, int]) -> tuple[int, int]:
    w, h = (int(v) for v in size)
    mw, mh = max_frame_size(ctx)
    if w <= 0 or h <= 0:
        raise RenderError(f"frame size {w}x{h}: width and height must be positive")
    if w > mw or h > mh:
        raise RenderError(f"frame size {w}x{h} is above this OpenGL's limit of {mw}x{mh}")
    return w, h


def _window_context(size: tuple[int, int]):
    """A visible window through glfw; the renderer still draws offscreen and blits the composite."""
    try:
        import glfw  # optional: not a dependency of the headless client
    except ImportError:
        raise RenderError("a window needs the 'glfw' package, which is not installed (pip install glfw); render headless instead") from None
    import moderngl

    if not glfw.init():
        raise RenderError("glfw could not initialise (no display?)")
    glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 4)
    glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 1)
    glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
    glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
    handle = glfw.create_window(int(size[0]), int(size[1]), "psao", None, None)
    if not handle:
        glfw.terminate()
        raise RenderError("glfw could not open an OpenGL 4.1 window")
    glfw.make_context_current(handle)
    ctx = moderngl.create_context(require=REQUIRED_GL)
    ctx.extra = {"glfw_window": handle}
    return ctx


def present(ctx, fbo) -> bool:
    """Blit an offscreen framebuffer to the window and swap; False once the user closed the window."""
    handle = (getattr(ctx, "extra", None) or {}).get("glfw_window")
    if handle is None:
        return True
    import glfw

    ctx.copy_framebuffer(ctx.screen, fbo)
    glfw.swap_buffers(handle)
    glfw.poll_events()
    return not glfw.window_should_close(handle)


def release_context(ctx) -> None:
    handle = (getattr(ctx, "extra", None) or {}).get("glfw_window")
    ctx.release()
    if handle is not None:
        import glfw

        glfw.destroy_window(handle)
        glfw.terminate()


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
