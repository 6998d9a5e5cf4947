"""Skinned meshes in the client renderer: posed at the server's time, the G-buffer's instance-local
positions lie on the same deformed triangles the server spreads and moves the AO points over."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from psao_client.errors import RenderError
from psao_client.render.renderer import FrameRenderer
from psao_scene import load_scene
from psao_scene.rigid import instance_transform
from psao_scene.camera import look_at, perspective
from psao_scene.skinning import skinned_vertices

SIZE = (160, 120)
T = 0.37  # seconds: mid-stride, limbs far from the rest pose


def robot_view(scene, i: int, t: float):
    """A camera 3 m in front of skinned instance i at time t, looking at its chest."""
    m = instance_transform(scene, i, t)
    chest = m[:3, :3] @ np.array([0.0, 1.1, 0.0]) + m[:3, 3]
    eye = chest + np.array([0.4, 0.5, -2.6])  # from the wall side: the pillar is inside the loop
    return look_at(eye, chest), perspective(50.0, SIZE[0] / SIZE[1], 0.05, 30.0)


def local_distance(mesh_vertices, faces, points) -> np.ndarray:
    """Distance of each point to the nearest triangle, every point against every triangle (trimesh's
    proximity query would need rtree, which is not installed)."""
    tris = np.asarray(mesh_vertices, np.float64)[faces]
    out = np.empty(len(points))
    for k, p in enumerate(points):
        closest = trimesh.triangles.closest_point(tris, np.broadcast_to(p, (len(tris), 3)))
        out[k] = np.linalg.norm(closest - p, axis=1).min()
    return out


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
    local = posed.local[pixels].astype(np.float64)
    rng = np.random.default_rng(0)
    local = local[rng.choice(len(local), size=min(200, len(local)), replace=False)]
    at_t = local_distance(skinned_vertices(mesh, T), mesh.faces, local)
    at_rest = local_distance(mesh.vertices, mesh.faces, local)
    # On the posed surface to float32 precision; many pixels are far off the rest pose (swung limbs).
    assert np.quantile(at_t, 0.99) < 1e-4, f"99% of pixels within {np.quantile(at_t, 0.99):.2e} m"
    assert np.mean(at_rest > 0.01) > 0.05
    # Back to the rest pose: the rest G-buffer lies on the rest mesh.
    back = rest.local[rest.instance == i].astype(np.float64)[:200]
    assert np.quantile(local_distance(mesh.vertices, mesh.faces, back), 0.99) < 1e-4


def test_stream_renderer_poses_skins_at_the_update_time_and_rests_before(ctx, tmp_path):
    """Before any Update (a static server's snapshot: points of the rest pose) skinned meshes are drawn
    at rest; after one, at its server time."""
    from protocol.updates import GridDelta
    from psao_client.mirror import Mirror
    from psao_client.render.stream_render import StreamRenderer
    from psao_server.bake import build_scene_grid
    from psao_server.points import generate_scene_points
    from psao_server.settings import PointSettings

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
