"""Per-pass GPU times from OpenGL timer queries (GL_TIME_ELAPSED through moderngl's Query).

One query object per pass name, created on first use and reused every frame. Reading `elapsed` waits
for the GPU, so results are collected once per frame after all passes were submitted.
"""
from __future__ import annotations

from contextlib import contextmanager


class PassTimer:
    def __init__(self, ctx, enabled: bool = True):
        self._ctx = ctx
        self._queries: dict[str, object] = {}
        self._used: list[str] = []
        self.enabled = enabled
        if enabled:
            self._spend_first_query(ctx)

    @staticmethod
    def _spend_first_query(ctx) -> None:
        """llvmpipe (Mesa 22.3) answers the first time query that contains GL work with 0xFFFFFFFF ns:
        spend it on clearing a 1x1 framebuffer. (Every pass binds its own framebuffer, so the binding
        this leaves behind does not matter.)"""
        target = ctx.simple_framebuffer((1, 1))
        query = ctx.query(time=True)
        target.use()
        with query:
            target.clear(0.0, 0.0, 0.0, 0.0)
        _ = query.elapsed
        target.release()

    @contextmanager
    def measure(self, name: str):
        """Time the GL commands issued inside the block under `name`."""
        if not self.enabled:
            yield
            return
        query = self._queries.get(name)
        if query is None:
            query = self._queries[name] = self._ctx.query(time=True)
        with query:
            yield
        self._used.append(name)

    def collect(self) -> dict[str, float]:
        """Milliseconds per pass measured since the last collect (waits for the GPU)."""
        result = {name: self._queries[name].elapsed / 1e6 for name in self._used}
        self._used = []
        return result

    def release(self) -> None:
        # moderngl 5 Query objects have no release(); their GL names go with the context.
        self._queries.clear()
