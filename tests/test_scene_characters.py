"""Composed characters: a skinned glTF of several meshes, primitives and skins as one TOML [[mesh]], placed by
[[instance]]s, its animation chosen by name; the whole-file load poses alike; bad skins, animation names and
scales are one line and exit 2 through `psao bake`; the example lab scene (examples/lab.toml) bakes."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from conftest import REPO, SHARED_SCENES
from psao.client.scene_import import scene_from_file
from psao.protocol.scenefile import SceneFile, skin_pose
from psao.scene import SceneError, SceneNotFound, load_scene
from psao.scene.rigid import instance_transform
from psao.scene.skinning import skin_points_reference
from psao.server.net.scene_export import scene_file
from support.cli import one_line_error, psao

LAB = REPO / "examples" / "lab.toml"
TIMES = (0.0, 0.4, 1.3)


class GltfBuilder:
    """Arrays appended to one binary blob, each an accessor."""

    def __init__(self):
        self.blob, self.views, self.accessors = b"", [], []

    def add(self, array, component: int, kind: str, count: int | None = None) -> int:
        data = np.ascontiguousarray(array).tobytes()
        self.views.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data)))
        self.blob += data + b"\0" * (-len(data) % 4)
        n = len(array) if count is None else count
        self.accessors.append(pygltflib.Accessor(bufferView=len(self.views) - 1, componentType=component, count=n,
                                                 type=kind))
        return len(self.accessors) - 1

    def save(self, path: Path, **doc) -> None:
        g = pygltflib.GLTF2(accessors=self.accessors, bufferViews=self.views,
                            buffers=[pygltflib.Buffer(byteLength=len(self.blob))], **doc)
        g.set_binary_blob(self.blob)
        g.save_binary(str(path))


def quad(x0, x1, y0, y1):
    return np.array([[x0, y0, 0], [x1, y0, 0], [x0, y1, 0], [x1, y1, 0]], np.float32)


QUAD_FACES = np.array([0, 1, 3, 0, 3, 2], np.uint16)


def character_gltf(path: Path, broken: str | None = None) -> None:
    """A small character of four meshes and two skins: 'body' (two primitives, skin 0 over joints j0 and j1),
    'arm' (skin 1, joint j1 alone), 'hat' (no skin, on a node under j1: the animation moves it) and 'plinth'
    (no skin, on a static node at x = 2). Animations 'bend' (j1 about +Z, 90 degrees in 1 s) and 'twist'
    (j0 about +Y, 90 degrees in 2 s). `broken` makes one inconsistency (see BROKEN)."""
    b = GltfBuilder()
    low, high = quad(-0.1, 0.1, 0.0, 1.0), quad(-0.1, 0.1, 1.0, 2.0)
    joints_low = np.array([[0, 0, 0, 0]] * 2 + [[0, 1, 0, 0]] * 2, np.uint16)
    joints_high = np.array([[0, 1, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, np.uint16)
    weights_low = np.array([[1, 0, 0, 0]] * 2 + [[0.5, 0.5, 0, 0]] * 2, np.float32)
    weights_high = np.array([[0.5, 0.5, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, np.float32)
    if broken == "joint_out_of_range":
        joints_high[3] = [5, 0, 0, 0]
    faces = b.add(QUAD_FACES, 5123, "SCALAR")
    body = []
    for k, (pos, jnt, wgt) in enumerate(((low, joints_low, weights_low), (high, joints_high, weights_high))):
        attributes = pygltflib.Attributes(POSITION=b.add(pos, 5126, "VEC3"))
        if not (broken == "primitive_without_joints" and k == 1):
            short = broken == "joints_count" and k == 0
            attributes.JOINTS_0 = b.add(jnt[:3] if short else jnt, 5123, "VEC4")
            attributes.WEIGHTS_0 = b.add(wgt, 5126, "VEC4")
        body.append(pygltflib.Primitive(attributes=attributes, indices=faces))
    arm = pygltflib.Primitive(attributes=pygltflib.Attributes(
        POSITION=b.add(quad(0.3, 0.6, 1.5, 2.0), 5126, "VEC3"),
        JOINTS_0=b.add(np.zeros((4, 4), np.uint16), 5123, "VEC4"),
        WEIGHTS_0=b.add(np.tile(np.float32([1, 0, 0, 0]), (4, 1)), 5126, "VEC4")), indices=faces)
    hat = pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=b.add(quad(-0.3, 0.3, 0.0, 0.4), 5126, "VEC3")),
                              indices=faces)
    plinth = pygltflib.Primitive(attributes=pygltflib.Attributes(
        POSITION=b.add(quad(-0.5, 0.5, 0.0, 0.3), 5126, "VEC3")), indices=faces)
    ibm0 = np.stack([np.eye(4, dtype=np.float32)] * 2)
    ibm0[1, 3, 1] = -1.0  # column-major: j1's inverse bind translates by (0, -1, 0)
    ibm1 = ibm0[1:].copy()
    skin0 = b.add(ibm0[:1] if broken == "inverse_binds" else ibm0, 5126, "MAT4")
    skin1 = b.add(ibm1, 5126, "MAT4")
    animations = []
    for name, node, axis, seconds in (("bend", 2, 2, 1.0), ("twist", 1, 1, 2.0)):
        q = np.zeros((2, 4), np.float32)
        q[:, 3] = 1.0
        q[1, axis], q[1, 3] = math.sin(math.pi / 4), math.cos(math.pi / 4)
        target = 99 if broken == "channel_node" else node
        animations.append(pygltflib.Animation(name=name, channels=[pygltflib.AnimationChannel(
            sampler=0, target=pygltflib.AnimationChannelTarget(node=target, path="rotation"))],
            samplers=[pygltflib.AnimationSampler(input=b.add(np.float32([0.0, seconds]), 5126, "SCALAR"),
                                                 output=b.add(q, 5126, "VEC4"))]))
    nodes = [pygltflib.Node(name="armature", children=[1]),
             pygltflib.Node(name="j0", children=[2]),
             pygltflib.Node(name="j1", translation=[0.0, 1.0, 0.0], children=[3]),
             pygltflib.Node(name="hat", mesh=2, translation=[0.0, 1.0, 0.0]),
             pygltflib.Node(name="body", mesh=0, skin=0),
             pygltflib.Node(name="arm", mesh=1, skin=1),
             pygltflib.Node(name="plinth", mesh=3, translation=[2.0, 0.0, 0.0])]
    joints0 = [1, 1] if broken == "duplicate_joint" else [1, 2]
    b.save(path, scene=0, scenes=[pygltflib.Scene(nodes=[0, 4, 5, 6])], nodes=nodes,
           meshes=[pygltflib.Mesh(name=n, primitives=p) for n, p in
                   (("body", body), ("arm", [arm]), ("hat", [hat]), ("plinth", [plinth]))],
           skins=[pygltflib.Skin(name="main", joints=joints0, inverseBindMatrices=skin0),
                  pygltflib.Skin(name="arm", joints=[2], inverseBindMatrices=skin1)],
           animations=animations)


def posed_world(scene, t: float) -> dict[str, np.ndarray]:
    """Instance name -> its mesh's world vertices at time t (numpy skinning, then the instance transform)."""
    out = {}
    for i, inst in enumerate(scene.instances):
        mesh = scene.meshes[inst.mesh]
        v = mesh.vertices
        if mesh.skin is not None:
            v = skin_points_reference(mesh.skin.skinning_matrices(t), v, mesh.skin.joints, mesh.skin.weights)
        m = instance_transform(scene, i, t)
        out[inst.name] = v @ m[:3, :3].T + m[:3, 3]
    return out


def character_toml(folder: Path, file: str, mesh_keys: str = "", instance_keys: str = "") -> Path:
    toml = folder / "chars.toml"
    toml.write_text(f'[[mesh]]\nname = "c"\npath = "{file}"\n{mesh_keys}\n'
                    f'[[instance]]\nname = "a"\nmesh = "c"\ntranslate = [3.0, 0.0, 1.0]\nrotate = [0.0, 30.0, 0.0]\n'
                    f'scale = 2.0\n{instance_keys}\n')
    return toml


PLACE = np.array([[2 * math.cos(math.radians(30)), 0, 2 * math.sin(math.radians(30)), 3.0],
                  [0, 2.0, 0, 0.0], [-2 * math.sin(math.radians(30)), 0, 2 * math.cos(math.radians(30)), 1.0],
                  [0, 0, 0, 1.0]])


def assert_composed_like_whole_file(toml_scene, whole, place=PLACE, times=TIMES):
    """Every part of the [[instance]] is the whole-file instance of the same name moved by `place`, posed alike."""
    assert len(toml_scene.meshes) == len(whole.meshes) and len(toml_scene.instances) == len(whole.instances)
    for t in times:
        got, want = posed_world(toml_scene, t), posed_world(whole, t)
        assert sorted(got) == sorted(f"a/{n}" for n in want)
        for name, v in want.items():
            np.testing.assert_allclose(got[f"a/{name}"], v @ place[:3, :3].T + place[:3, 3], atol=1e-9)


def test_character_of_several_meshes_and_skins_is_one_mesh(tmp_path):
    character_gltf(tmp_path / "char.glb")
    whole = load_scene(tmp_path / "char.glb")
    # body and arm by their skins, hat by a one-joint skin on its node (under j1), plinth static; in the
    # order of the node tree (the hat's node is met first, under the armature)
    joints = {m.name: m.skin.joint_count if m.skin else 0 for m in whole.meshes}
    assert joints == {"hat": 1, "body": 2, "arm": 1, "plinth": 0}
    scene = load_scene(character_toml(tmp_path, "char.glb"))
    assert [m.name for m in scene.meshes] == [f"c/{m.name}" for m in whole.meshes]
    assert [i.name for i in scene.instances] == [f"a/{i.name}" for i in whole.instances]
    assert sorted(i.name for i in scene.instances) == ["a/arm", "a/body", "a/hat", "a/plinth"]
    body = next(m for m in scene.meshes if m.name == "c/body")
    assert len(body.faces) == 4  # both primitives
    assert_composed_like_whole_file(scene, whole)
    first, later = posed_world(scene, 0.0), posed_world(scene, 0.7)
    for name in ("a/body", "a/arm", "a/hat"):
        assert np.abs(first[name] - later[name]).max() > 0.1, name
    np.testing.assert_array_equal(first["a/plinth"], later["a/plinth"])
    # the hat rides on j1: halfway through 'bend' (1 s, looping) j1 has turned 45 degrees about +Z, and the
    # hat's rest offset (0, 1, 0) from j1 and its quad's centre (0, 0.2, 0) with it
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    hat = posed_world(whole, 0.5)["hat"]
    np.testing.assert_allclose(hat.mean(axis=0), [-1.2 * s, 1.0 + 1.2 * c, 0.0], atol=1e-6)


def test_animation_by_name_offset_and_rigid_motion(tmp_path):
    character_gltf(tmp_path / "char.glb")
    twist = load_scene(character_toml(tmp_path, "char.glb", 'animation = "twist"'))
    by_index = load_scene(character_toml(tmp_path, "char.glb", "animation = 1"))
    for t in TIMES:  # the animation by name is the animation by index
        got, want = posed_world(twist, t), posed_world(by_index, t)
        assert sorted(got) == sorted(want)
        for name, v in want.items():
            np.testing.assert_allclose(got[name], v, atol=1e-12)
    bend = load_scene(character_toml(tmp_path, "char.glb"))  # the first animation by default
    assert not np.allclose(posed_world(twist, 0.5)["a/body"], posed_world(bend, 0.5)["a/body"])
    late = load_scene(character_toml(tmp_path, "char.glb", "animation_offset = 0.25"))
    for name, v in posed_world(late, 0.3).items():
        np.testing.assert_allclose(v, posed_world(bend, 0.55)[name], atol=1e-9)
    walking = load_scene(character_toml(tmp_path, "char.glb", instance_keys=(
        '[instance.animation]\nkind = "platform"\noffset = [0.0, 0.0, 4.0]\nperiod = 2.0')))
    for t in TIMES:  # every part moves with the whole character, the static plinth too
        shift = np.array([0.0, 0.0, 4.0]) * 0.5 * (1 - math.cos(math.pi * t))
        for name, v in posed_world(walking, t).items():
            np.testing.assert_allclose(v, posed_world(bend, t)[name] + shift, atol=1e-9)


def test_composed_character_reaches_the_client_alike(tmp_path):
    """The scene file a server sends for it names the same parts and poses them as the server does; two loads
    hash alike."""
    character_gltf(tmp_path / "char.glb")
    toml = character_toml(tmp_path, "char.glb", 'animation = "bend"')
    scene = load_scene(toml)
    assert load_scene(toml).content_hash() == scene.content_hash()
    got = scene_from_file(SceneFile.parse(scene_file(scene).serialize()))
    assert [m.name for m in got.meshes] == [m.name for m in scene.meshes]
    assert [(i.name, i.mesh) for i in got.instances] == [(i.name, i.mesh) for i in scene.instances]
    wire = SceneFile.parse(scene_file(scene).serialize())
    for t in (0.0, 0.25, 0.5):
        for i, inst in enumerate(scene.instances):
            mesh, theirs = scene.meshes[inst.mesh], wire.meshes[inst.mesh]
            np.testing.assert_allclose(got.instances[i].transform, inst.transform, atol=1e-6)
            if mesh.skin is not None:
                np.testing.assert_allclose(skin_pose(theirs.skin, t), mesh.skin.skinning_matrices(t), atol=5e-3)


def test_robot_expressive_as_one_mesh(tmp_path, shared_scene):
    """RobotExpressive (19 meshes, 4 skins): one [[mesh]] is its 19 parts, 4 of them on 43-joint skins and
    the parts hung on bones following them; the pose at each time is the whole-file load's."""
    robot = shared_scene("robotexpressive/RobotExpressive.glb")
    (tmp_path / "robot.glb").symlink_to(robot)
    for animation in ("Walking", "Wave"):
        scene = load_scene(character_toml(tmp_path, "robot.glb", f'animation = "{animation}"'))
        whole = load_scene(robot) if animation == "Dance" else None
        from psao.scene.meshfile import load_mesh_file

        meshes, instances = load_mesh_file(robot, animation)
        from psao.scene.model import Scene

        whole = Scene("robot", meshes, instances, 1.0)
        assert len(scene.meshes) == 19 and len(scene.instances) == 19
        assert sorted(m.skin.joint_count for m in scene.meshes if m.skin and m.skin.joint_count > 1) == [43] * 4
        assert_composed_like_whole_file(scene, whole, times=(0.1, 0.5))
        first, later = posed_world(scene, 0.1), posed_world(scene, 0.5)
        moved = [n for n in first if np.abs(first[n] - later[n]).max() > 1e-3]
        assert len(moved) >= 10, (animation, moved)


@pytest.mark.parametrize("rel", ["robotexpressive/RobotExpressive.glb",
                                 "cesiumman/CesiumMan.glb", "fox/Fox.glb"])
def test_shared_characters_compose_like_the_whole_file(rel, tmp_path, shared_scene):
    file = shared_scene(rel)
    (tmp_path / file.name).symlink_to(file)
    scene = load_scene(character_toml(tmp_path, file.name))
    whole = load_scene(file)
    if len(whole.instances) == 1:  # a character of one part keeps the [[mesh]] and [[instance]] names
        assert [m.name for m in scene.meshes] == ["c"] and [i.name for i in scene.instances] == ["a"]
        for t in (0.2, 0.9):
            np.testing.assert_allclose(posed_world(scene, t)["a"], (lambda v: v @ PLACE[:3, :3].T + PLACE[:3, 3])(
                posed_world(whole, t)[whole.instances[0].name]), atol=1e-9)
    else:
        assert_composed_like_whole_file(scene, whole, times=(0.2, 0.9))
    v = posed_world(scene, 0.2)
    assert any(np.abs(v[n] - posed_world(scene, 0.9)[n]).max() > 1e-3 for n in v)


BROKEN = [  # (what character_gltf breaks, text of the one error line)
    ("duplicate_joint", "node 1 is listed twice among its joints"),
    ("joint_out_of_range", "a vertex refers to a joint outside 0..1"),
    ("primitive_without_joints", "has JOINTS_0 and WEIGHTS_0 on 1 of its 2 primitives"),
    ("joints_count", "JOINTS_0 has 3 entries for 4 positions"),
    ("inverse_binds", "inverseBindMatrices must be 2 finite matrices"),
    ("channel_node", "targets a missing node 99"),
]


@pytest.mark.parametrize("broken,text", BROKEN, ids=[b[0] for b in BROKEN])
def test_inconsistent_skins_fail_at_load(tmp_path, broken, text):
    character_gltf(tmp_path / "char.glb", broken)
    with pytest.raises(SceneError, match=text):
        load_scene(tmp_path / "char.glb")
    with pytest.raises(SceneError, match=rf"chars\.toml: mesh 'c'.*char\.glb.*{text}"):
        load_scene(character_toml(tmp_path, "char.glb"))


BAD_TOML = [  # (keys of [[mesh]], keys of [[instance]], text of the one error line)
    ("", "", "node 1 is listed twice among its joints"),  # the duplicate-joint file
    ('animation = "Swim"', "", "no animation 'Swim' (has: bend, twist)"),
    ("animation = 7", "", "no animation 7 (has 2)"),
    ("", "scale = 0.0", "'scale' must not be zero"),
    ("", "scale = 1e30", "over the limit"),
    ("", "scale = 1e-30", "too small for float32 positions to resolve"),
]


@pytest.mark.parametrize("mesh_keys,instance_keys,text", BAD_TOML, ids=[b[2][:30] for b in BAD_TOML])
def test_bad_character_input_is_one_line_exit_2(tmp_path, mesh_keys, instance_keys, text):
    character_gltf(tmp_path / "char.glb", "duplicate_joint" if not (mesh_keys or instance_keys) else None)
    toml = character_toml(tmp_path, "char.glb", mesh_keys, "")
    toml.write_text(toml.read_text().replace("scale = 2.0", instance_keys or "scale = 2.0"))
    one_line_error(psao("bake", toml, "--density", 4, "--rays", 1, "--probes", 0, "--out", tmp_path / "g.npz"), text)


def test_scene_root_outside_the_toml_folder(tmp_path):
    """[scene] root: mesh paths are relative to it and stay inside it; a root that is not there is one line."""
    (tmp_path / "assets").mkdir()
    (tmp_path / "scenes").mkdir()
    character_gltf(tmp_path / "assets" / "char.glb")
    toml = character_toml(tmp_path / "scenes", "char.glb")
    toml.write_text('[scene]\nroot = "../assets"\n' + toml.read_text())
    assert len(load_scene(toml).instances) == 4
    toml.write_text(toml.read_text().replace('path = "char.glb"', 'path = "../scenes/chars.toml"'))
    with pytest.raises(SceneError, match="inside the scene's folder"):
        load_scene(toml)
    toml.write_text(toml.read_text().replace('"../assets"', '"../absent"'))
    with pytest.raises(SceneNotFound, match=r"\[scene\]: scene root '../absent'"):
        load_scene(toml)


def lab_or_skip():
    needed = ["sponza/sponza_s_lod4.glb", "cesiumman/CesiumMan.glb", "fox/Fox.glb",
              "robotexpressive/RobotExpressive.glb", "riggedsimple/RiggedSimple.glb"]
    missing = [n for n in needed if not (SHARED_SCENES / n).is_file()]
    if missing:
        pytest.skip(f"{SHARED_SCENES} lacks {', '.join(missing)}")


def test_lab_scene_composition():
    lab_or_skip()
    scene = load_scene(LAB)
    characters = {i.name.split("/")[0] for i in scene.instances if scene.meshes[i.mesh].skin is not None}
    movers = {i.name for i in scene.instances if i.animation is not None and scene.meshes[i.mesh].skin is None
              and "/" not in i.name}
    assert len(characters) >= 8 and len(movers) >= 3, (characters, movers)
    assert scene.camera_paths["walk"].keys
    lo, hi = scene.world_bounds()
    assert (hi - lo).max() < 50


def test_lab_bake_smoke(tmp_path):
    lab_or_skip()
    proc = psao("bake", LAB, "--density", 4, "--rays", 1, "--probes", 0, "--out", tmp_path / "lab.npz")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "lab.npz").stat().st_size > 0


def test_lab_without_its_files_is_one_line(tmp_path):
    toml = tmp_path / "lab.toml"
    toml.write_text(LAB.read_text())  # its root, ../../shared/scenes from tmp_path, is not there
    assert not (tmp_path / "../../shared/scenes").resolve().is_dir()
    one_line_error(psao("bake", toml, "--density", 4, "--rays", 1, "--probes", 0, "--out", tmp_path / "g.npz"),
                   "scene root '../../shared/scenes'")
