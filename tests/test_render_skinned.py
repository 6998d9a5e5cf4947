"""Skinned meshes in the client renderer: drawn posed at the server's time (world positions on the deformed
triangles the server traces from), while the G-buffer's instance-local position and normal are the rest
pose's at the same triangle and barycentrics, where the server keeps the AO points."""
from __future__ import annotations

import numpy as np
import pytest

from psao.client.errors import RenderError
from psao.client.render.renderer import FrameRenderer
from psao.scene import load_scene
from psao.scene.rigid import instance_transform
from psao.scene.camera import look_at, perspective
from psao.scene.skinning import skinned_vertices
from skinned import closest_on_mesh, local_distance, rest_place

SIZE = (160, 120)
T = 0.37  # seconds: mid-stride, limbs far from the rest pose


def robot_view(scene, i: int, t: float):
    """A camera 3 m in front of skinned instance i at time t, looking at its chest."""
    m = instance_transform(scene, i, t)
    chest = m[:3, :3] @ np.array([0.0, 1.1, 0.0]) + m[:3, 3]
    eye = chest + np.array([0.4, 0.5, -2.6])  # from the wall side: the pillar is inside the loop
    return look_at(eye, chest), perspective(50.0, SIZE[0] / SIZE[1], 0.05, 30.0)


def test_skinned_mesh_drawn_at_the_server_time(ctx):
    scene = load_scene("builtin:robots")
    i = next(k for k, inst in enumerate(scene.instances) if scene.meshes[inst.mesh].skin is not None)
    mesh = scene.meshes[scene.instances[i].mesh]
    transforms = np.stack([instance_transform(scene, k, T) for k in range(len(scene.instances))])
    view, proj = robot_view(scene, i, T)
    with FrameRenderer(scene, SIZE, "psao", ctx=ctx) as r:
        assert r.geometry.has_skins
        r.set_transforms(transforms)
        r.set_skin_time(T)
        posed = r.render(view, proj).gbuffer
        r.set_skin_time(None)
        rest = r.render(view, proj).gbuffer
        with pytest.raises(RenderError, match="skin time"):
            r.set_skin_time(float("nan"))

    pixels = posed.instance == i
    assert pixels.sum() > 200, "the robot is not in view"
    rng = np.random.default_rng(0)
    pick = rng.choice(int(pixels.sum()), size=min(200, int(pixels.sum())), replace=False)
    m = transforms[i]
    world = posed.world[pixels][pick].astype(np.float64)
    drawn = (world - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T  # instance-local place of the drawn surface
    posed_vertices = skinned_vertices(mesh, T)
    # drawn on the posed surface to float32 precision; many pixels are far off the rest pose (swung limbs)
    assert np.quantile(local_distance(posed_vertices, mesh.faces, drawn), 0.99) < 1e-4
    assert np.mean(local_distance(mesh.vertices, mesh.faces, drawn) > 0.01) > 0.05
    # the local targets: the rest pose of the drawn point (same triangle, same barycentrics) and its normal
    local = posed.local[pixels][pick].astype(np.float64)
    off = np.linalg.norm(local - rest_place(posed_vertices, mesh.vertices, mesh.faces, drawn), axis=1)
    assert np.quantile(off, 0.99) < 1e-3, f"99% of pixels within {np.quantile(off, 0.99):.2e} m of their rest place"
    _, face, _ = closest_on_mesh(mesh.vertices, mesh.faces, local)
    assert np.mean(np.einsum("ij,ij->i", posed.local_normal[pixels][pick], mesh.face_normals()[face]) > 0.999) > 0.95
    # the rest pose drawn: the same local targets as the rest mesh
    back = rest.local[rest.instance == i].astype(np.float64)[:200]
    assert np.quantile(local_distance(mesh.vertices, mesh.faces, back), 0.99) < 1e-4


def test_stream_renderer_poses_skins_at_the_update_time_and_rests_before(ctx, tmp_path):
    """Before any Update (a static server's snapshot: points of the rest pose) skinned meshes are drawn
    at rest; after one, at its server time."""
    from psao.protocol.updates import GridDelta
    from psao.client.mirror import Mirror
    from psao.client.render.stream_render import StreamRenderer
    from psao.server.bake import build_scene_grid
    from psao.server.points.generate import generate_scene_points
    from psao.server.settings import PointSettings

    scene = load_scene("builtin:robots")
    grid = build_scene_grid(scene, generate_scene_points(scene, PointSettings(density=4.0)))
    mirror = Mirror(grid.instances, len(grid.buckets), len(grid.cells))
    mirror.apply(GridDelta(len(grid.cells), cell_slots=grid.allocated_cells(), cells=grid.cells[grid.allocated_cells()]))
    with StreamRenderer(scene, tmp_path, size=(32, 24), ctx=ctx) as cb:
        cb(mirror, mirror.transforms, tick=-1, camera_time=0.0)
        assert cb.renderer.skin_time is None
        mirror.server_time = T
        cb(mirror, mirror.transforms, tick=0, camera_time=0.1)
        assert cb.renderer.skin_time == T
