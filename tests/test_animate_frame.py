"""The tick's animate stage made in batches (SceneAnimator.frame: every skinned mesh in one kernel launch, walk
cycles posed together, bounds reduced over merged arrays; ServerTick._deform: every skinned point in one pass)
against the same scene worked out one instance at a time: the same numbers."""
from __future__ import annotations

import numpy as np
import pytest

from psao.scene import load_scene
from psao.scene.rigid import Polyline, instance_transform
from psao.scene.skin import NodeAnimator, compose_hierarchy, hierarchy_order, skinning_matrices_of, topological_order
from psao.scene.skinning import SceneSkinner, skinned_vertices
from psao.scene.skinning_kernels import SurfacePoints
from psao.scene.transforms import axis_angle_matrix, linear_matrix, placed_about, translation_matrix
from psao.server.tick.animate import SceneAnimator, SkinnedPoints, affine, bounds_of, changed_meshes

BUILTIN = ["builtin:robots", "builtin:courtyard", "builtin:tangle", "builtin:space"]
SHARED = ["cesiumman/CesiumMan.glb", "fox/Fox.glb", "riggedsimple/RiggedSimple.glb", "robotexpressive/RobotExpressive.glb"]
TIMES = (0.0, 0.37, 2.5, 33.3)


def reference_frame(scene, animator: SceneAnimator, t: float, bind_pose: bool = False) -> dict:
    """The frame one moving instance at a time: its transform (an edit's, else its animation's), its mesh skinned alone, affine and bounds_of
    on its own vertices, the merged arrays concatenated in instance order."""
    kinds = animator.kinds
    transforms = np.array([inst.transform for inst in scene.instances], np.float64).reshape(-1, 4, 4)
    for i in kinds.moving:
        transforms[i] = animator.placed[i] if i in animator.placed else instance_transform(scene, i, t)
    mesh_vertices = {}
    for i in kinds.skinned:
        mesh = scene.meshes[scene.instances[i].mesh]
        mesh_vertices[scene.instances[i].mesh] = np.array(mesh.vertices if bind_pose else skinned_vertices(mesh, t))
    bounds, spheres, verts, faces, sv, sf, parts, base, sbase = {}, {}, [], [], [], [], [], 0, 0
    for i in kinds.moving:
        m = scene.instances[i].mesh
        w = affine(mesh_vertices.get(m, scene.meshes[m].vertices), transforms[i])
        bounds[i], spheres[i] = bounds_of(w)
        verts.append(w)
        faces.append(scene.meshes[m].faces + base)
        base += len(w)
        if m in mesh_vertices:
            sv.append(w)
            sf.append(scene.meshes[m].faces + sbase)
            parts.append(len(w))
            sbase += len(w)
    return dict(transforms=transforms, mesh_vertices=mesh_vertices, bounds=bounds, spheres=spheres,
                dynamic_vertices=np.concatenate(verts), dynamic_faces=np.concatenate(faces),
                skinned_vertices=np.concatenate(sv) if sv else None,
                skinned_faces=np.concatenate(sf) if sf else np.zeros((0, 3), np.int64), skinned_parts=parts)


def assert_same(got, want, where=""):
    """Equal bit for bit, through dicts, tuples and lists."""
    if isinstance(want, dict):
        assert got.keys() == want.keys(), where
        for k in want:
            assert_same(got[k], want[k], f"{where}[{k}]")
    elif isinstance(want, (tuple, list)):
        assert len(got) == len(want), where
        for k, (g, w) in enumerate(zip(got, want)):
            assert_same(g, w, f"{where}[{k}]")
    elif want is None:
        assert got is None, where
    else:
        assert np.array_equal(np.asarray(got), np.asarray(want)) and np.shape(got) == np.shape(want), where


def scene_named(name, shared_scene):
    return load_scene(name if name.startswith("builtin:") else str(shared_scene(name)))


@pytest.mark.parametrize("name", BUILTIN + SHARED)
def test_frame_equals_the_scene_posed_one_instance_at_a_time(name, shared_scene):
    scene = scene_named(name, shared_scene)
    animator = SceneAnimator(scene)
    assert animator.kinds.moving
    for t in TIMES:
        frame = animator.frame(t)
        want = reference_frame(scene, animator, t)
        assert_same({k: getattr(frame, k) for k in want}, want, f"{name} t={t}")
        # the skinned meshes' merged vertices hold each mesh's vertices (mesh_vertices are its rows)
        for m, v in frame.mesh_vertices.items():
            assert np.shares_memory(v, frame.posed)
    frame = animator.frame(0.5, bind_pose=True)
    want = reference_frame(scene, animator, 0.5, bind_pose=True)
    assert_same({k: getattr(frame, k) for k in want}, want, f"{name} bind pose")


def test_frames_do_not_share_what_they_change(shared_scene):
    """A frame's vertices are its own (the next frame does not overwrite them); the faces every frame shares
    cannot be written."""
    animator = SceneAnimator(load_scene("builtin:robots"))
    a = animator.frame(0.2)
    kept = {k: np.array(getattr(a, k)) for k in ("posed", "dynamic_vertices", "skinned_vertices")}
    b = animator.frame(0.7)
    for k, v in kept.items():
        assert np.array_equal(getattr(a, k), v) and not np.array_equal(getattr(b, k), v)
    assert b.dynamic_faces is a.dynamic_faces
    with pytest.raises(ValueError):
        a.dynamic_faces[0, 0] = 1


def test_an_edit_that_makes_a_static_instance_move_lays_the_frame_out_again():
    scene = load_scene("builtin:robots")
    animator = SceneAnimator(scene)
    before = animator.frame(1.0)
    static = animator.kinds.static[3]
    moved = scene.instances[static].transform.copy()
    moved[:3, 3] += [0.5, 0.0, 0.0]
    assert animator.place(static, moved)
    after = animator.frame(1.0)
    assert static in after.bounds and static not in before.bounds
    fields = ("dynamic_vertices", "dynamic_faces", "bounds", "spheres")
    want = reference_frame(scene, animator, 1.0)
    assert_same({k: getattr(after, k) for k in fields}, {k: want[k] for k in fields}, "after the edit")


@pytest.mark.parametrize("name", ["builtin:robots"] + SHARED)
def test_skins_posed_together_equal_each_alone(name, shared_scene):
    scene = scene_named(name, shared_scene)
    meshes = [k for k, m in enumerate(scene.meshes) if m.skin is not None]
    skinner = SceneSkinner(scene)
    for t in TIMES:
        skins = [scene.meshes[m].skin for m in meshes]
        assert np.array_equal(skinning_matrices_of(skins, t), np.concatenate([s.skinning_matrices(t) for s in skins]))
        assert np.array_equal(skinner.posed(meshes, t), np.concatenate([skinner.vertices(m, t) for m in meshes]))
        assert np.array_equal(skinner.posed(meshes[::-1], t), np.concatenate([skinner.vertices(m, t) for m in meshes[::-1]]))


def test_walk_cycles_posed_together_equal_each_alone():
    scene = load_scene("builtin:robots")
    walks = [m.skin.animator for m in scene.meshes if m.skin is not None]
    assert len(walks) > 1 and len({w.phase for w in walks}) == len(walks)
    for t in TIMES:
        together = type(walks[0]).joint_matrices_of(walks, t)
        assert np.array_equal(together, np.stack([w.joint_matrices(t) for w in walks]))
        rot = together[..., :3, :3]  # rigid joints: rotations and translations only
        np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)


def naive_world(local, parents, root):
    """World matrices of every node, one at a time in topological order."""
    world = np.empty_like(local)
    for n in topological_order(parents):
        world[n] = (root if parents[n] < 0 else world[parents[n]]) @ local[n]
    return world


def test_hierarchy_composed_only_where_needed_equals_every_node_composed():
    rng = np.random.default_rng(3)
    parents = np.array([-1, 0, 1, 1, -1, 4, 5, 2, 7, 3])
    local = rng.normal(size=(10, 4, 4))
    root = rng.normal(size=(4, 4))
    full = naive_world(local, parents, root)
    assert np.array_equal(compose_hierarchy(local, hierarchy_order(parents), root), full)
    needed = [8, 6]
    order = hierarchy_order(parents, needed)
    assert {n for n, _ in order} == {0, 1, 2, 7, 8, 4, 5, 6}
    assert np.array_equal(compose_hierarchy(local, order, root)[needed], full[needed])
    batched = rng.normal(size=(3, 10, 4, 4))
    assert np.array_equal(compose_hierarchy(batched, hierarchy_order(parents), root),
                          np.stack([naive_world(b, parents, root) for b in batched]))


@pytest.mark.parametrize("name", SHARED)
def test_gltf_joint_matrices_equal_every_node_composed(name, shared_scene):
    scene = load_scene(str(shared_scene(name)))
    animator = next(m.skin.animator for m in scene.meshes if m.skin is not None)
    assert isinstance(animator, NodeAnimator)
    for t in TIMES:
        want = naive_world(animator.local_matrices(t), animator.parents, animator.root)[animator.joint_nodes]
        assert np.array_equal(animator.joint_matrices(t), want)


def test_rigid_placement_and_path_lookup_equal_their_definitions():
    rng = np.random.default_rng(8)
    for _ in range(20):
        translate, origin, linear = rng.normal(size=3), rng.normal(size=3), rng.normal(size=(3, 3))
        want = translation_matrix(translate) @ linear_matrix(linear) @ translation_matrix(-origin)
        np.testing.assert_allclose(placed_about(translate, linear, origin), want, rtol=0, atol=1e-13)
    path = Polyline(rng.normal(size=(6, 3)), closed=True)
    for s in np.concatenate([rng.uniform(0, path.length, 200), path.starts, [0.0, path.length]]):
        i = int(np.clip(np.searchsorted(path.starts, s, side="right") - 1, 0, len(path.lengths) - 1))
        assert path.locate(float(s)) == (i, float(s - path.starts[i]))
    scene = load_scene("builtin:robots")
    for i, inst in enumerate(scene.instances):  # walkers: yawed along their paths about +Y
        if inst.animation is None:
            continue
        a = inst.animation
        for t in TIMES:
            s, direction = a.path.travel(a.speed * t)
            k, into = a.path.locate(s)
            d = a.path.dirs[k] * direction
            want = (translation_matrix(a.path.verts[k] + a.path.dirs[k] * into)
                    @ linear_matrix(axis_angle_matrix([0, 1, 0], np.arctan2(d[0], d[2])))
                    @ translation_matrix(-a.base[:3, 3]) @ a.base)
            np.testing.assert_allclose(a.matrix(t), want, rtol=0, atol=1e-12)


def test_surface_points_write_in_place_what_they_return():
    rng = np.random.default_rng(2)
    faces = rng.integers(0, 50, size=(40, 3))
    index = rng.integers(0, 40, size=500)
    rest = rng.normal(size=(500, 3))
    sp = SurfacePoints(faces, index, rng.dirichlet(np.ones(3), size=500), np.where(rng.random(500) < 0.5, 1.0, -1.0), rest)
    vertices = rng.normal(size=(50, 3))
    want = [a.copy() for a in sp.follow(vertices)]
    pos, nrm = np.zeros((600, 3)), np.zeros((600, 3), np.float32)
    own = [a.copy() for a in sp.follow(vertices * 3)]  # what the object's own buffers hold now
    got = sp.follow(vertices, out=(pos[100:], nrm[100:]))
    assert got[0].base is pos and np.array_equal(pos[100:], want[0]) and np.array_equal(nrm[100:], want[1])
    # written straight into `out`: the object's own buffers still hold the previous call's answer
    assert all(np.array_equal(a.numpy().reshape(-1, 3)[:500], b) for a, b in zip(sp._own, own))
    assert not pos[:100].any() and not nrm[:100].any()
    strided = np.zeros((500, 6))[:, ::2]  # not one block: written through the object's own buffers
    sp.follow(vertices * 2, out=(strided, nrm[100:]))
    assert np.array_equal(strided, sp.follow(vertices * 2)[0])


def test_deform_places_every_skinned_point_on_its_triangle_once_per_change(make_tick):
    tick, _ = make_tick("robots", density=8, rays=4)
    try:
        frame = tick.animator.frame(1.3)
        assert tick._deform(frame) == sum(len(tick.ids_of[i]) for i in tick.kinds.skinned)
        for i in tick.kinds.skinned:
            mesh = tick.scene.meshes[tick.scene.instances[i].mesh]
            sp: SkinnedPoints = tick.skinned[i]
            want_pos, want_nrm = sp.follow_numpy(mesh.faces, frame.mesh_vertices[tick.scene.instances[i].mesh])
            ids = tick.ids_of[i]
            np.testing.assert_allclose(tick.local_pos[ids], want_pos, rtol=0, atol=1e-12)
            np.testing.assert_allclose(tick.local_nrm[ids], want_nrm, rtol=0, atol=1e-6)
        assert tick._deform(frame) == 0  # placed on these meshes already
        assert tick._deform(tick.animator.frame(1.3)) == 0  # another frame of the same pose
        assert tick._deform(tick.animator.frame(1.4)) > 0
    finally:
        tick.close()


def test_changed_meshes_are_those_whose_vertices_differ():
    scene = load_scene("builtin:robots")
    animator = SceneAnimator(scene)
    a, b = animator.frame(0.5), animator.frame(0.5)
    assert changed_meshes(b, a) == set()
    later = animator.frame(0.6)
    assert changed_meshes(later, a) == {scene.instances[i].mesh for i in animator.kinds.skinned}
    assert changed_meshes(a, None) == set(a.mesh_vertices)


def test_scene_without_skins_is_animated_without_warp():
    """Warp (half a second or more to import) stays out of a process whose scene has no skin: loading and
    animating the rigid courtyard imports none of it (`psao serve --progressive` then listens before any
    Warp import); a skinned scene's first frame does."""
    import subprocess
    import sys

    code = ("import sys\n"
            "from psao.scene import load_scene\n"
            "from psao.server.tick.animate import SceneAnimator\n"
            "SceneAnimator(load_scene(sys.argv[1])).frame(0.5)\n"
            "print('warp' in sys.modules)\n")
    for scene, warp in (("builtin:courtyard", False), ("builtin:robots", True)):
        out = subprocess.run([sys.executable, "-c", code, scene], capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip().splitlines()[-1] == str(warp), (scene, out.stdout)
