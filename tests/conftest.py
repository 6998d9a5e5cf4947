"""Fixtures shared by the test modules: the headless GL context, the repository root, the shared scenes."""
from __future__ import annotations

from pathlib import Path

import pytest

from psao_client.errors import RenderError

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENES = REPO.parent / "shared" / "scenes"  # test models, read-only; absent on some machines


@pytest.fixture(scope="module")
def ctx():
    """One headless GL context per test module; skips without EGL."""
    from psao_client.render.context import create_context

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
