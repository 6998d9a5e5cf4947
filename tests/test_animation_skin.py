"""Skins from glTF (joints, weights, inverse binds, animation channels), their validation, procedural
skins, and the Warp skinning kernels against the numpy reference."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from psao.scene import SceneFormatError, load_scene
from psao.scene.skin import MAX_JOINTS
from psao.scene.transforms import axis_angle_matrix
from psao.scene.skinning import skin_normals, skin_normals_reference, skin_points, skin_points_reference, skinned_vertices
from psao.scene.skinning_kernels import SkinDeformer

RNG = np.random.default_rng(5)


def skinned_gltf(path: Path, joints: int = 2, channel_node: int = 2, times=(0.0, 1.0),
                 interpolation: str = "LINEAR") -> None:
    """A vertical strip of 3 vertex rows (y = 0, 1, 2) skinned to a chain of `joints` joints one unit
    apart (nodes 1..joints); node 0 holds the mesh. One rotation channel turns `channel_node` from 0 to
    90 degrees about +Z over `times`."""
    pos = np.array([[-0.1, 0, 0], [0.1, 0, 0], [-0.1, 1, 0], [0.1, 1, 0], [-0.1, 2, 0], [0.1, 2, 0]], np.float32)
    jnt = np.array([[0, 0, 0, 0]] * 2 + [[0, 1, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, np.uint16)
    wgt = np.array([[1, 0, 0, 0]] * 2 + [[0.5, 0.5, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, np.float32)
    idx = np.array([0, 1, 3, 0, 3, 2, 2, 3, 5, 2, 5, 4], np.uint16)
    ibm = np.stack([np.eye(4, dtype=np.float32) for _ in range(joints)])
    ibm[:, 3, 1] = -np.arange(joints)  # column-major: translation (0, -k, 0) in the last column
    t = np.asarray(times, np.float32)
    q = np.array([[0, 0, math.sin(a / 2), math.cos(a / 2)] for a in np.linspace(0, math.pi / 2, len(t))], np.float32)
    chunks = [pos, jnt, wgt, idx, ibm, t, q]
    blob, views, off = b"", [], 0
    for c in chunks:
        data = c.tobytes()
        data += b"\0" * (-len(data) % 4)
        views.append(pygltflib.BufferView(buffer=0, byteOffset=off, byteLength=len(c.tobytes())))
        blob += data
        off += len(data)
    acc = lambda v, ct, n, typ: pygltflib.Accessor(bufferView=v, componentType=ct, count=n, type=typ)  # noqa: E731
    nodes = [pygltflib.Node(name="strip", mesh=0, skin=0)]
    for k in range(joints):
        nodes.append(pygltflib.Node(name=f"j{k}", translation=[0, 1.0 if k else 0.0, 0],
                                    children=[k + 2] if k + 1 < joints else []))
    g = pygltflib.GLTF2(
        scene=0, scenes=[pygltflib.Scene(nodes=[0, 1])], nodes=nodes,
        meshes=[pygltflib.Mesh(primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=0, JOINTS_0=1, WEIGHTS_0=2), indices=3)])],
        skins=[pygltflib.Skin(joints=list(range(1, joints + 1)), inverseBindMatrices=4)],
        animations=[pygltflib.Animation(name="bend", channels=[pygltflib.AnimationChannel(
            sampler=0, target=pygltflib.AnimationChannelTarget(node=channel_node, path="rotation"))],
            samplers=[pygltflib.AnimationSampler(input=5, output=6, interpolation=interpolation)])],
        accessors=[acc(0, 5126, 6, "VEC3"), acc(1, 5123, 6, "VEC4"), acc(2, 5126, 6, "VEC4"), acc(3, 5123, 12, "SCALAR"),
                   acc(4, 5126, joints, "MAT4"), acc(5, 5126, len(t), "SCALAR"), acc(6, 5126, len(t), "VEC4")],
        bufferViews=views, buffers=[pygltflib.Buffer(byteLength=len(blob))])
    g.accessors[3].min = None
    g.set_binary_blob(blob)
    g.save_binary(str(path))


def posed(scene, t):
    mesh = scene.meshes[0]
    return skinned_vertices(mesh, t)


def find(v, p):
    return np.argmin(np.linalg.norm(v - p, axis=1))


def test_synthetic_skin_by_hand(tmp_path):
    skinned_gltf(tmp_path / "s.glb")
    scene = load_scene(tmp_path / "s.glb")
    mesh = scene.meshes[0]
    assert mesh.skin.joint_count == 2 and np.allclose(scene.instances[0].transform, np.eye(4))
    np.testing.assert_allclose(mesh.skin.weights.sum(1), 1.0)
    rest = mesh.vertices.copy()
    np.testing.assert_allclose(posed(scene, 0.0), rest, atol=1e-6)
    top, mid = find(rest, [0.1, 2, 0]), find(rest, [0.1, 1, 0])
    for t, deg in ((0.5, 45.0), (0.25, 22.5)):
        r = axis_angle_matrix([0, 0, 1], math.radians(deg))
        v = posed(scene, t)
        # the top row follows joint 1 (at y = 1) fully; the middle row is half joint 0, half joint 1
        np.testing.assert_allclose(v[top], [0, 1, 0] + r @ [0.1, 1, 0], atol=1e-6)
        np.testing.assert_allclose(v[mid], 0.5 * np.array([0.1, 1, 0]) + 0.5 * ([0, 1, 0] + r @ [0.1, 0, 0]), atol=1e-6)
    np.testing.assert_allclose(posed(scene, 0.5), posed(scene, 1.5), atol=1e-9)  # loops with the duration


def test_step_interpolation(tmp_path):
    skinned_gltf(tmp_path / "step.glb", times=(0.0, 1.0, 2.0), interpolation="STEP")
    scene = load_scene(tmp_path / "step.glb")
    top = find(scene.meshes[0].vertices, [0.1, 2, 0])
    np.testing.assert_allclose(posed(scene, 0.9)[top], posed(scene, 0.0)[top], atol=1e-9)
    r = axis_angle_matrix([0, 0, 1], math.radians(45))
    np.testing.assert_allclose(posed(scene, 1.5)[top], [0, 1, 0] + r @ [0.1, 1, 0], atol=1e-6)


@pytest.mark.parametrize("kwargs,pattern", [
    (dict(joints=MAX_JOINTS + 1), r"skin.*257 joints.*256"),
    (dict(channel_node=99), r"animation 'bend' channel 0.*missing node 99"),
    (dict(times=(0.0, 1.0, 1.0)), r"animation 'bend' channel 0.*not strictly increasing"),
])
def test_bad_skins_fail_at_load(tmp_path, kwargs, pattern):
    skinned_gltf(tmp_path / "bad_skin.glb", **kwargs)
    with pytest.raises(SceneFormatError, match=pattern) as e:
        load_scene(tmp_path / "bad_skin.glb")
    assert "bad_skin.glb" in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("rel,height", [("cesiumman/CesiumMan.glb", 1.5), ("riggedsimple/RiggedSimple.glb", None),
                                        ("fox/Fox.glb", None)])
def test_real_skins(rel, height, shared_scene):
    scene = load_scene(shared_scene(rel))
    mesh = scene.meshes[0]
    skin = mesh.skin
    assert skin is not None and 0 < skin.joint_count <= MAX_JOINTS
    np.testing.assert_allclose(skin.weights.sum(1), 1.0, atol=1e-9)
    # the rest pose skins to the stored vertices (rebased from bind space)
    rest = skin.animator.rest_joint_matrices() @ skin.inverse_bind
    np.testing.assert_allclose(skin_points_reference(rest, mesh.vertices, skin.joints, skin.weights), mesh.vertices,
                               atol=1e-4 * np.abs(mesh.vertices).max())
    duration = skin.animator.duration
    assert duration > 0
    size = np.ptp(mesh.vertices, axis=0).max()
    for t in np.linspace(0, duration, 25, endpoint=False):
        v = skin_points(skin, t, mesh.vertices, skin.joints, skin.weights)
        ref = skin_points_reference(skin.skinning_matrices(t), mesh.vertices, skin.joints, skin.weights)
        np.testing.assert_allclose(v, ref, atol=1e-9 * size)
        assert np.isfinite(v).all() and np.ptp(v, axis=0).max() < 1.6 * size
        if height is not None:  # an upright walker: feet on the ground, head at its height
            assert abs(v[:, 1].min()) < 0.05 * height and abs(v[:, 1].max() - height) < 0.1 * height
        # continuous in time: a step of duration / 400 moves no vertex by more than a few % of the size
        nxt = skinned_vertices(mesh, t + duration / 400)
        assert np.linalg.norm(nxt - v, axis=1).max() < 0.05 * size
    np.testing.assert_allclose(skinned_vertices(mesh, 0.3), skinned_vertices(mesh, 0.3 + duration),
                               atol=1e-6 * size)


def test_procedural_robot_skins_deform():
    scene = load_scene("builtin:robots")
    mesh = next(m for m in scene.meshes if m.skin is not None)
    skin = mesh.skin
    blended = ((skin.weights > 0).sum(1) > 1).sum()
    assert blended > 50  # smooth weights across joints, not rigid parts
    a, b = skinned_vertices(mesh, 0.0), skinned_vertices(mesh, 0.4)
    moved = np.linalg.norm(a - b, axis=1)
    assert moved.max() > 0.1 and np.median(moved) < moved.max()


def random_setup(p=500, j=7):
    mats = np.tile(np.eye(4), (j, 1, 1))
    mats[:, :3, :3] = RNG.normal(size=(j, 3, 3)) * 0.3 + np.eye(3)  # scale and shear, not only rotation
    mats[:, :3, 3] = RNG.normal(size=(j, 3))
    joints = RNG.integers(0, j, size=(p, 4))
    weights = RNG.uniform(0, 1, size=(p, 4)) * (RNG.uniform(size=(p, 4)) < 0.7)
    weights[:, 0] += 1e-3
    weights /= weights.sum(1, keepdims=True)
    pos = RNG.normal(size=(p, 3)) * 3
    nrm = RNG.normal(size=(p, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return mats, joints, weights, pos, nrm


def test_warp_kernels_match_numpy_reference():
    mats, joints, weights, pos, nrm = random_setup()
    d = SkinDeformer(pos, joints, weights, rest_nrm=nrm)
    for _ in range(3):  # buffers reused across updates
        mats[:, :3, 3] += 0.1
        p, n = d.deform(mats)
        np.testing.assert_allclose(p, skin_points_reference(mats, pos, joints, weights), atol=1e-12)
        np.testing.assert_allclose(n, skin_normals_reference(mats, nrm, joints, weights), atol=1e-10)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)


def test_normals_stay_perpendicular_to_skinned_surface():
    """A normal skinned like its triangle stays perpendicular to the skinned triangle (same blend)."""
    mats, _, _, _, _ = random_setup(j=3)
    tri = RNG.normal(size=(3, 3))
    joints = np.tile([0, 1, 2, 0], (3, 1))
    weights = np.tile([0.5, 0.3, 0.2, 0.0], (3, 1))  # one blend for the whole triangle: an affine map
    n0 = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    n0 /= np.linalg.norm(n0)

    class S:
        @staticmethod
        def skinning_matrices(t):
            return mats

    v = skin_points(S, 0.0, tri, joints, weights)
    n = skin_normals(S, 0.0, n0[None], joints[:1], weights[:1])[0]
    e1, e2 = v[1] - v[0], v[2] - v[0]
    assert abs(n @ e1) < 1e-9 and abs(n @ e2) < 1e-9
    assert n @ np.cross(e1, e2) > 0  # same side as the skinned triangle's winding


def test_corrupted_skinned_gltf_never_crashes(tmp_path):
    """Mutate one field of a valid skinned glTF at a time: loading either works or raises a SceneError,
    never another exception (no traceback reaches the user)."""
    from psao.scene import SceneError
    skinned_gltf(tmp_path / "ok.glb")
    rng = np.random.default_rng(0)
    bad_values = [None, -1, 0, 1, 7, 99, 5124, 1e9, "VEC2", "MAT4", [], [1, 2]]
    fields = [("accessors", ["bufferView", "componentType", "count", "type", "byteOffset"]),
              ("bufferViews", ["buffer", "byteOffset", "byteLength", "byteStride"]),
              ("skins", ["inverseBindMatrices", "joints"]), ("nodes", ["mesh", "skin", "children"]),
              ("animations", ["channels", "samplers"])]
    for trial in range(150):
        g = pygltflib.GLTF2().load(str(tmp_path / "ok.glb"))
        table, names = fields[trial % len(fields)]
        items = getattr(g, table)
        obj = items[rng.integers(len(items))]
        setattr(obj, names[rng.integers(len(names))], bad_values[rng.integers(len(bad_values))])
        try:
            g.save_binary(str(tmp_path / "mutant.glb"))
        except Exception:  # pygltflib itself cannot write this mutation: nothing to load
            continue
        try:
            load_scene(tmp_path / "mutant.glb")
        except SceneError as e:
            assert "mutant.glb" in str(e) and "\n" not in str(e)


def test_toml_skinned_file_meshes(tmp_path):
    skinned_gltf(tmp_path / "strip.glb", times=(0.0, 1.0, 2.0))
    toml = tmp_path / "chars.toml"
    toml.write_text(
        '[[mesh]]\nname = "a"\npath = "strip.glb"\nanimation = "bend"\n'
        '[[mesh]]\nname = "b"\npath = "strip.glb"\nanimation = 0\nanimation_offset = 0.5\n'
        '[[instance]]\nname = "a"\nmesh = "a"\ntranslate = [3.0, 0.0, 0.0]\n'
        '[[instance]]\nname = "b"\nmesh = "b"\n')
    scene = load_scene(toml)
    a, b = scene.meshes
    assert a.skin is not None and b.skin is not None
    np.testing.assert_allclose(skinned_vertices(b, 0.2), skinned_vertices(a, 0.7), atol=1e-12)  # 0.5 s ahead
    assert not np.allclose(skinned_vertices(a, 0.2), skinned_vertices(a, 0.7))
    good = toml.read_text()
    for value, pattern in (('"dance"', r"chars\.toml: mesh 'a'.*strip\.glb: no animation 'dance' \(has: bend\)"),
                           ("1.5", r"chars\.toml: mesh 'a'.*'animation' must be a name or an index")):
        toml.write_text(good.replace('animation = "bend"', f"animation = {value}"))
        with pytest.raises(SceneFormatError, match=pattern):
            load_scene(toml)
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    toml.write_text('[[mesh]]\nname = "s"\npath = "tri.obj"\nanimation = 0\n[[instance]]\nname = "s"\nmesh = "s"\n')
    with pytest.raises(SceneFormatError, match=r"mesh 's'.*no skin"):
        load_scene(toml)


def test_fox_animation_by_name(tmp_path, shared_scene):
    fox = shared_scene("fox/Fox.glb")
    from psao.scene.meshfile import load_mesh_file
    survey = load_mesh_file(fox)[0][0].skin.animator.duration
    walk = load_mesh_file(fox, "Walk")[0][0].skin.animator.duration
    run = load_mesh_file(fox, 2)[0][0].skin.animator.duration
    assert len({survey, walk, run}) == 3
    with pytest.raises(SceneFormatError, match="Survey, Walk, Run"):
        load_mesh_file(fox, "Swim")


def test_surface_points_kernel_follows_like_numpy():
    """SkinnedPoints.follow (Warp's SurfacePoints) against its numpy reference on a moving mesh: the same
    positions and normals up to rounding, sides kept, rest normals where a triangle is skinned flat."""
    from psao.server.tick.animate import SkinnedPoints

    rng = np.random.default_rng(4)
    faces = rng.integers(0, 200, size=(150, 3))
    faces[7] = [5, 5, 9]  # degenerate in every pose
    face_index = rng.integers(0, 150, size=3000)
    face_index[:5] = 7
    rest = rng.normal(size=(3000, 3))
    rest /= np.linalg.norm(rest, axis=1, keepdims=True)
    sp = SkinnedPoints(face_index, rng.dirichlet(np.ones(3), size=3000), np.where(rng.random(3000) < 0.5, 1.0, -1.0), rest)
    for step in range(3):
        vertices = rng.normal(size=(200, 3)) * (1 + step)
        pos, nrm = sp.follow(faces, vertices)
        want_pos, want_nrm = sp.follow_numpy(faces, vertices)
        np.testing.assert_allclose(pos, want_pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(nrm, want_nrm, rtol=0, atol=2e-7)
        assert pos.dtype == np.float64 and nrm.dtype == np.float32
        np.testing.assert_array_equal(nrm[:5], rest[:5].astype(np.float32))


def test_merged_channels_sample_as_one_by_one(shared_scene):
    """NodeAnimator samples a glTF skin's channels merged (merge_channels): the very numbers each channel
    gives on its own, at and between keys, before the first and after the last."""
    from psao.scene.skin import merge_channels

    mesh = next(m for m in load_scene(shared_scene("cesiumman/CesiumMan.glb")).meshes if m.skin is not None)
    channels = mesh.skin.animator.channels
    merged = merge_channels(channels)
    assert len(merged) < len(channels) and sum(np.size(m.node) for m in merged) == len(channels)
    own = {(int(c.node), c.path): c for c in channels}
    for t in np.concatenate([np.linspace(-0.1, 1.1 * mesh.skin.animator.duration, 41), channels[0].times[:3]]):
        for m in merged:
            got = np.asarray(m.sample(t)).reshape(np.size(m.node), -1)
            for k, node in enumerate(np.atleast_1d(m.node)):
                np.testing.assert_array_equal(got[k], own[(int(node), m.path)].sample(t))


def test_moving_bounds_equal_the_plain_reductions():
    # animate.bounds_of (rows of coordinates) against min / max along the vertices (bit for bit) and the
    # largest distance from the box centre (to rounding: the sums of squares may round differently)
    from psao.server.tick.animate import bounds_of

    rng = np.random.default_rng(11)
    for n in (1, 3, 820, 5000):
        v = rng.normal(size=(n, 3)) * rng.uniform(0.01, 100.0, 3) + rng.uniform(-50, 50, 3)
        (lo, hi), (centre, radius) = bounds_of(v)
        np.testing.assert_array_equal(lo, v.min(axis=0))
        np.testing.assert_array_equal(hi, v.max(axis=0))
        np.testing.assert_array_equal(centre, 0.5 * (v.min(axis=0) + v.max(axis=0)))
        d = v - centre
        assert radius == pytest.approx(float(np.sqrt(np.einsum("pi,pi->p", d, d).max())), rel=1e-14, abs=0.0)
