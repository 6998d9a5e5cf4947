"""One skinned mesh placed by two instances: RiggedSimple's bending cylinder standing on a floor, and the same
mesh again beside it, turned a quarter about +Y and sliding on a platform (a skinned instance that also moves
rigidly). Both share the mesh's pose (one skin, posed once a frame) but each is placed by its own transform,
has its own points (seeded by its instance index) and its own grid cells. Every check below works out the
second instance from its own transform and its own points, so a frame, a placement or a tick that took the
first instance's transform or points for the second fails it."""
from __future__ import annotations

import numpy as np
import pytest

from psao.protocol import pointword as pw
from psao.protocol.updates import GridDelta, Reader, decode_delta, encode_delta
from psao.client.mirror import Mirror
from psao.scene import load_scene
from psao.scene.model import Instance, Mesh, Scene
from psao.scene.rigid import PlatformAnimation, instance_transform
from psao.scene.skinning import skinned_vertices
from psao.scene.transforms import axis_angle_matrix, linear_matrix, translation_matrix
from psao.server.tick.animate import PlacedPoints, SceneAnimator, SkinnedPoints, affine
from psao.server.bake import bake_scene
from psao.server.geometry import scene_center, scene_point_ids
from psao.server.tick.budget import BudgetSettings
from psao.server.net.clients import changed_transform_ids, read_delta
from psao.server.settings import BakeSettings, TickSettings, TraceSettings
from psao.server.tick.server_tick import ServerTick
from psao.server.tracer import make_tracer
from test_animate_frame import assert_same, reference_frame

TIMES = (0.0, 0.37, 1.1, 2.5)  # seconds: RiggedSimple's cylinder bends over its clip
TWICE = (0, 1)  # the instances of the skinned mesh


@pytest.fixture
def twice(shared_scene) -> Scene:
    return rigged_twice(shared_scene("riggedsimple/RiggedSimple.glb"))


def rigged_twice(path) -> Scene:
    """RiggedSimple's mesh placed twice over a static floor: instance 0 as the file places it, instance 1
    2.6 m along +X (0.6 m apart at rest: within the AO distance of 1 m, so each occludes the other), turned
    90 degrees about +Y and sliding 0.4 m along +Z and back every 3 s."""
    rigged = load_scene(str(path))
    (mesh,) = rigged.meshes
    assert mesh.skin is not None
    floor = Mesh("floor", np.array([[-3.0, -0.05, -3.0], [6.0, -0.05, -3.0], [6.0, -0.05, 3.0], [-3.0, -0.05, 3.0]]),
                 np.array([[0, 2, 1], [0, 3, 2]]))
    beside = translation_matrix([2.6, 0.0, 0.0]) @ linear_matrix(axis_angle_matrix([0.0, 1.0, 0.0], np.pi / 2))
    instances = [Instance("first", 0, np.eye(4)),
                 Instance("second", 0, beside, PlatformAnimation(beside, offset=np.array([0.0, 0.0, 0.4]), period=3.0)),
                 Instance("floor", 1, np.eye(4))]
    return Scene("rigged-twice", [mesh, floor], instances, rigged.ao_distance)


def world_mesh(scene: Scene, i: int, t: float) -> np.ndarray:
    """Instance i's mesh vertices at time t, worked out for it alone: skinned at t, through its transform at t."""
    return affine(skinned_vertices(scene.meshes[scene.instances[i].mesh], t), instance_transform(scene, i, t))


def on_triangles(vertices: np.ndarray, faces: np.ndarray, ps) -> np.ndarray:
    """The points of PointSet `ps` on `vertices`: each its barycentrics of its own triangle's corners."""
    return np.einsum("pk,pkj->pj", ps.barycentrics, vertices[faces[ps.faces]])


def test_frame_poses_the_mesh_once_and_places_each_instance_by_its_own_transform(twice):
    animator = SceneAnimator(twice)
    assert animator.kinds.skinned == list(TWICE) and animator.kinds.static == [2]
    v = len(twice.meshes[0].vertices)
    seen = []
    for t in TIMES:
        frame = animator.frame(t)
        # the batched frame equals the scene worked out one instance at a time
        want = reference_frame(twice, animator, t)
        assert_same({k: getattr(frame, k) for k in want}, want, f"t={t}")
        # one posed mesh, two placements of it
        assert list(frame.mesh_vertices) == [0] and frame.skinned_parts == [v, v]
        first, second = frame.skinned_vertices[:v], frame.skinned_vertices[v:]
        np.testing.assert_allclose(first, world_mesh(twice, 0, t), rtol=0, atol=1e-12)
        np.testing.assert_allclose(second, world_mesh(twice, 1, t), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(frame.skinned_faces[len(twice.meshes[0].faces):], twice.meshes[0].faces + v)
        assert np.linalg.norm(first - second, axis=1).min() > 0.1  # apart everywhere
        assert not np.allclose(frame.bounds[0][0], frame.bounds[1][0])
        seen.append((frame.mesh_vertices[0].copy(), frame.transforms[0].copy(), frame.transforms[1].copy()))
    # over the clip the mesh bends, the second instance slides, the first stands where the file put it
    assert all(not np.allclose(seen[0][0], s[0]) for s in seen[1:])
    assert all(np.array_equal(seen[0][1], s[1]) for s in seen[1:])
    assert all(not np.allclose(seen[0][2], s[2]) for s in seen[1:])
    bind = animator.frame(TIMES[1], bind_pose=True)
    assert_same(bind.skinned_vertices, reference_frame(twice, animator, TIMES[1], bind_pose=True)["skinned_vertices"])


@pytest.mark.parametrize("order", [TWICE, TWICE[::-1]], ids=["ids-in-one-run", "ids-out-of-order"])
def test_placed_points_put_each_instance_on_its_own_deformed_triangles(twice, order):
    """PlacedPoints over both instances (their ids one run, written in place, or not) puts each instance's
    points on its own triangles of the posed mesh with its own barycentrics, which differ from the other's."""
    mesh = twice.meshes[0]
    bake = bake_scene(twice, BakeSettings(density=8, rays=4, workers=1), show_progress=False)
    bake.tracer.close()
    sets = bake.pointsets
    assert len(sets[0]) > 100 and len(sets[1]) > 100
    assert len(sets[0]) != len(sets[1]) or not np.array_equal(sets[0].barycentrics, sets[1].barycentrics)
    ids_of = scene_point_ids(sets)
    animator = SceneAnimator(twice)
    n = sum(len(ps) for ps in sets)
    for t in TIMES[1:]:
        frame = animator.frame(t)
        points = {i: SkinnedPoints.from_pointset(mesh, sets[i]) for i in order}
        placed = PlacedPoints(twice, points, ids_of, frame.layout)
        assert isinstance(placed.rows, slice) == (order == TWICE)
        local_pos, local_nrm = np.full((n, 3), np.nan), np.full((n, 3), np.nan, np.float32)
        placed.place(frame.posed, local_pos, local_nrm)
        posed = skinned_vertices(mesh, t)
        for i in TWICE:
            ids, ps = ids_of[i], sets[i]
            np.testing.assert_allclose(local_pos[ids], on_triangles(posed, mesh.faces, ps), rtol=0, atol=1e-12)
            # normals: the posed triangle's, on the side the point was generated on
            a, b, c = (posed[mesh.faces[ps.faces][:, k]] for k in range(3))
            tri = np.cross(b - a, c - a)
            tri /= np.linalg.norm(tri, axis=1, keepdims=True)
            side = np.sign(np.einsum("ij,ij->i", mesh.face_normals()[ps.faces], ps.normals))
            np.testing.assert_allclose(local_nrm[ids], tri * side[:, None], rtol=0, atol=1e-5)
            # through the instance's transform: on that instance's own world triangles of the frame (to the
            # float32 barycentrics' sum, 1 within ~1e-7, times the translation)
            rows = frame.skinned_vertices[i * len(mesh.vertices):(i + 1) * len(mesh.vertices)]
            np.testing.assert_allclose(affine(local_pos[ids], frame.transforms[i]), on_triangles(rows, mesh.faces, ps),
                                       rtol=0, atol=1e-5)
        assert np.isnan(local_pos[ids_of[2]]).all()  # the floor's rows are not written


def snapshot(grid, transforms) -> Mirror:
    """A client's mirror of the whole grid and every transform."""
    mirror = Mirror(grid.instances, len(grid.buckets), len(grid.cells))
    mirror.apply(GridDelta(len(grid.cells), np.arange(len(transforms)), transforms,
                           np.arange(len(grid.buckets), dtype=np.uint32), grid.buckets,
                           np.arange(len(grid.cells), dtype=np.uint32), grid.cells))
    return mirror


def send(tick, mirror: Mirror) -> None:
    """What the tick changed (dirty buckets and cells, changed transforms) to the mirror through the
    wire format, as an Update carries it; the mirror then equals the grid."""
    buckets, cells = tick.grid.take_dirty()
    transforms = tick.transforms()
    delta = read_delta(tick.grid, transforms, changed_transform_ids(mirror.transforms, transforms), buckets, cells)
    mirror.apply(decode_delta(Reader(encode_delta(delta), "update"))[0])
    np.testing.assert_array_equal(mirror.cells, tick.grid.cells)
    np.testing.assert_array_equal(mirror.buckets, tick.grid.buckets)
    np.testing.assert_array_equal(mirror.transforms, transforms)


def reference_codes(scene: Scene, t: float, pos, nrm, ids, settings: TraceSettings) -> np.ndarray:
    """AO codes of world points traced here against the scene at time t built one instance at a time: the
    floor static, each skinned instance's own world triangles (world_mesh) as a deforming part."""
    mesh = scene.meshes[0]
    local = make_tracer("embree", scene_center(scene), workers=1)
    try:
        floor = scene.meshes[scene.instances[2].mesh]
        local.set_static(affine(floor.vertices, scene.instances[2].transform), floor.faces)
        v = len(mesh.vertices)
        local.set_dynamic(np.concatenate([world_mesh(scene, i, t) for i in TWICE]),
                          np.concatenate([mesh.faces + k * v for k in range(len(TWICE))]), None, [v] * len(TWICE))
        return pw.quantise_ao(local.visibility(pos, nrm, ids, settings)).astype(np.int64)
    finally:
        local.close()


def test_budgeted_tick_traces_both_instances_points_where_each_is(twice):
    """A budgeted tick of a few hundred points a tick while both instances bend and the second slides, then
    held still until its queue drains: every point of both instances was traced, each from its own place on
    its own instance (worked out here from its point set, the posed mesh and its transform), and holds the AO
    of a trace of the scene built one instance at a time; a client's mirror fed each tick's changes equals
    the grid after every tick."""
    rays = 8
    bake = bake_scene(twice, BakeSettings(density=8, rays=rays, workers=1), show_progress=False)
    budget = BudgetSettings(budget_ms=1e-3, rays_per_tick=1.0, round_rays=2, min_points=200)
    tick = ServerTick(bake, TickSettings(rays=rays, workers=1, budget=budget))
    try:
        tick.set_cameras([])
        mirror = snapshot(tick.grid, tick.transforms())
        tick.grid.take_dirty()
        ids_of = tick.ids_of
        mine = [ids[tick.tracked[ids]] for ids in (ids_of[0], ids_of[1])]
        assert all(len(m) > 100 for m in mine)
        traced = np.zeros(len(tick.tracked), bool)
        for t in TIMES[1:]:
            plan = tick.prepare(t)
            tick.apply(plan)
            traced[plan.ids] = True
            send(tick, mirror)
            for m in mine:  # the mesh bent: every point of both instances was traced this tick or waits
                assert (np.isin(m, plan.ids) | (tick.queue.done[m] < tick.queue.slices)).all()
        t_end = TIMES[-1]
        for _ in range(4 * len(traced) // budget.min_points + 8):
            plan = tick.prepare(t_end)
            stats = tick.apply(plan)
            traced[plan.ids] = True
            send(tick, mirror)
            if stats.queue == 0:
                break
        assert stats.queue == 0, "the queue does not drain"
        assert all(traced[m].all() for m in mine)

        mesh = twice.meshes[0]
        posed = skinned_vertices(mesh, t_end)
        for i, ids in zip(TWICE, mine):
            assert (tick.grid.cell_instance[tick.slot[ids]] == i).all()  # kept in the instance's own cells
            pos, nrm = tick.world_points(tick.last_frame, ids)
            ps = bake.pointsets[i]
            own = np.searchsorted(ids_of[i], ids)  # each id's row of instance i's point set
            local = np.einsum("pk,pkj->pj", ps.barycentrics[own], posed[mesh.faces[ps.faces[own]]])
            np.testing.assert_allclose(pos, affine(local, instance_transform(twice, i, t_end)), rtol=0, atol=1e-9)
            full = reference_codes(twice, t_end, pos, nrm, ids, tick.trace_settings)
            for cells in (tick.grid.cells, mirror.cells):
                stored = (cells[tick.slot[ids], tick.index[ids]] & 0xFF).astype(np.int64)
                assert np.abs(stored - full).max() <= tick.settings.threshold, f"instance {i}"
    finally:
        tick.close()
