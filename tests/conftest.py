"""Fixtures shared by the test modules: the headless GL context, the repository root, the shared scenes,
the server tick on a fresh bake."""
from __future__ import annotations

from pathlib import Path

import pytest

from psao.client.errors import RenderError

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENES = REPO.parent / "shared" / "scenes"  # test models, read-only; absent on some machines


@pytest.fixture(scope="module")
def ctx():
    """One headless GL context per test module; skips without EGL."""
    from psao.client.render.context import create_context

    try:
        context = create_context()
    except RenderError as exc:
        pytest.skip(str(exc))
    yield context
    context.release()


@pytest.fixture
def shared_scene():
    """shared_scene("sponza/x.glb") -> its path under ../shared/scenes, or a skip when it is absent."""
    def find(rel: str) -> Path:
        path = SHARED_SCENES / rel
        if not path.exists():
            pytest.skip(f"{path} not present")
        return path
    return find


@pytest.fixture
def make_tick():
    """make_tick("NAME", density, rays, bake_rays=rays, budget=None, baked_time=0.0, tick_hz=60, **tick_settings) ->
    (tick, bake): the server tick on a fresh bake of builtin:NAME, one tracer worker each, dirty sets drained.
    The test closes the tick."""
    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings, TickSettings
    from psao.server.tick.server_tick import ServerTick

    def make(name, density=32, rays=8, bake_rays=None, budget=None, baked_time=0.0, tick_hz=60.0, **tick_settings):
        bake = bake_scene(load_scene(f"builtin:{name}"),
                          BakeSettings(density=density, rays=bake_rays or rays, workers=1), show_progress=False)
        tick = ServerTick(bake, TickSettings(rays=rays, workers=1, budget=budget, **tick_settings), baked_time=baked_time,
                          tick_hz=tick_hz)
        tick.grid.take_dirty()
        return tick, bake
    return make


@pytest.fixture(scope="module")
def cornell_double_block():
    """The Cornell box with its tall block made double-sided: one-sided and double-sided point layouts in
    one small scene."""
    import dataclasses

    from psao.scene import load_scene

    base = load_scene("builtin:cornell")
    meshes = list(base.meshes)
    k = base.instances[-1].mesh
    meshes[k] = dataclasses.replace(meshes[k], double_sided=True)
    return dataclasses.replace(base, meshes=meshes)
