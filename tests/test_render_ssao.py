"""SSAO baseline: unoccluded on an open plane, darker in a corner, blur keeps depth edges, seeded."""
from __future__ import annotations

import numpy as np
import pytest
from test_render_gridbuild import box_mesh, plane_mesh

from psao.client.errors import RenderError
from psao.client.render.renderer import FrameRenderer
from psao.protocol.ssao_kernel import hemisphere_kernel
from psao.client.render.views import look_at, perspective
from psao.scene.model import Instance, Scene

SIZE = (320, 180)


def render_ssao(ctx, scene, eye, target, samples=16):
    view, proj = look_at(eye, target), perspective(60, SIZE[0] / SIZE[1], 0.05, 50)
    with FrameRenderer(scene, SIZE, "ssao", ssao_samples=samples, ctx=ctx) as r:
        return r.render(view, proj)


def test_kernel_is_in_the_unit_hemisphere_and_denser_near_the_centre():
    k = hemisphere_kernel(64, 7)
    assert np.all(k[:, 2] >= 0) and np.all(np.linalg.norm(k, axis=1) <= 1.0 + 1e-6)
    assert np.linalg.norm(k[:16], axis=1).mean() < np.linalg.norm(k[-16:], axis=1).mean()


def test_open_plane_is_unoccluded(ctx):
    scene = Scene("plane", [plane_mesh("floor", size=40.0)], [Instance("floor", 0, np.eye(4))], ao_distance=0.6)
    frame = render_ssao(ctx, scene, eye=[0.0, 3.0, 4.0], target=[0.0, 0.0, 0.0])
    m = frame.gbuffer.mask
    assert m.mean() > 0.5
    ao = frame.ao["ssao"][m]
    assert np.percentile(ao, 1) > 0.97 and ao.mean() > 0.99


def test_corner_is_darker_than_open_floor(ctx):
    # Floor y = 0 and a wall (thick box) whose face is the plane z = 0, seen from the open side.
    meshes = [plane_mesh("floor", size=20.0), box_mesh("wall", (-10, 0, -1), (10, 4, 0))]
    scene = Scene("corner", meshes, [Instance("floor", 0, np.eye(4)), Instance("wall", 1, np.eye(4))], ao_distance=0.6)
    frame = render_ssao(ctx, scene, eye=[0.0, 2.0, 4.0], target=[0.0, 0.3, 0.0])
    gb = frame.gbuffer
    floor = gb.mask & (gb.instance == 0)
    near_corner = floor & (gb.world[..., 2] < 0.1)
    far_floor = floor & (gb.world[..., 2] > 1.5)
    ao = frame.ao["ssao"]
    assert near_corner.sum() > 100 and far_floor.sum() > 100
    assert ao[near_corner].mean() < 0.92
    assert ao[far_floor].mean() > 0.97
    # The wall right above the floor is darkened too (both sides of the crease).
    wall_low = gb.mask & (gb.instance == 1) & (gb.world[..., 1] < 0.1)
    assert ao[wall_low].mean() < 0.92


def test_more_samples_converge_and_frames_repeat(ctx):
    meshes = [plane_mesh("floor", size=20.0), box_mesh("wall", (-10, 0, -1), (10, 4, 0))]
    scene = Scene("corner", meshes, [Instance("floor", 0, np.eye(4)), Instance("wall", 1, np.eye(4))], ao_distance=0.6)
    a = render_ssao(ctx, scene, [0.0, 2.0, 4.0], [0.0, 0.3, 0.0], samples=8).ao["ssao"]
    b = render_ssao(ctx, scene, [0.0, 2.0, 4.0], [0.0, 0.3, 0.0], samples=8).ao["ssao"]
    c = render_ssao(ctx, scene, [0.0, 2.0, 4.0], [0.0, 0.3, 0.0], samples=64).ao["ssao"]
    np.testing.assert_array_equal(a, b)
    assert 0.0 < np.abs(a - c).mean() < 0.05


def test_bad_sample_count_is_rejected(ctx):
    scene = Scene("plane", [plane_mesh("floor")], [Instance("floor", 0, np.eye(4))], ao_distance=0.6)
    with pytest.raises(RenderError, match="sample count"):
        FrameRenderer(scene, SIZE, "ssao", ssao_samples=0, ctx=ctx)


def test_the_page_draws_the_desktop_ssao_kernel_and_noise():
    """The web page's SSAO kernel, noise and sample count are the desktop SsaoPass defaults', served in
    /psao_constants.js; the page's shader writes no sample count of its own."""
    import json
    import re

    from psao.client.render.ssao_pass import SsaoSettings
    from psao.protocol.ssao_kernel import rotation_noise
    from psao.server.net.webpage import WEB_DIR, constants_module

    served = {m.group(1): json.loads(m.group(2))
              for m in re.finditer(r"^export const (SSAO_\w+) = (.*);$", constants_module(), flags=re.M)}
    desktop = SsaoSettings()
    assert served["SSAO_SAMPLES"] == desktop.samples
    assert np.array_equal(np.float32(served["SSAO_KERNEL"]), hemisphere_kernel(desktop.samples, desktop.seed).ravel())
    assert np.array_equal(np.float32(served["SSAO_NOISE"]), rotation_noise(desktop.seed).ravel())
    assert not re.search(r"#\s*define\s+SSAO_SAMPLES", (WEB_DIR / "shaders" / "ssao.frag").read_text())
