"""TOML scene files: generators, transforms, mesh paths, and every bad-input case naming file and element."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from psao.scene import SceneFormatError, SceneNotFound, load_scene
from psao.scene.builtin_shapes import GENERATORS, box

REPO = Path(__file__).resolve().parents[1]

BASE = """
[scene]
name = "t"
ao_distance = 0.75

[[mesh]]
name = "b"
generator = "box"
size = [1.0, 2.0, 3.0]
color = [0.1, 0.2, 0.3]

[[instance]]
name = "i"
mesh = "b"
translate = [1.0, 2.0, 3.0]
rotate = [10.0, 20.0, 30.0]
scale = [2.0, 1.0, 0.5]

[[camera_path]]
name = "c"
fov_y = 50.0
[[camera_path.key]]
time = 0.0
eye = [0.0, 0.0, 5.0]
target = [0.0, 0.0, 0.0]
[[camera_path.key]]
time = 2.0
eye = [5.0, 0.0, 0.0]
target = [0.0, 0.0, 0.0]
"""


def write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    f = tmp_path / name
    f.write_text(text)
    return f


def world(scene, k=0) -> np.ndarray:
    inst = scene.instances[k]
    m = scene.meshes[inst.mesh]
    return m.vertices @ inst.transform[:3, :3].T + inst.transform[:3, 3]


def sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


def test_generator_scene_round_trip(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    assert scene.name == "t" and scene.ao_distance == 0.75
    assert scene.meshes[0].color == (0.1, 0.2, 0.3) and not scene.meshes[0].double_sided
    # independent reference: scipy's extrinsic xyz Euler angles, scale first, then rotate, then translate
    r = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    v, _ = box((1.0, 2.0, 3.0))
    expect = (v * [2.0, 1.0, 0.5]) @ r.T + [1, 2, 3]
    np.testing.assert_allclose(sorted_rows(world(scene)), sorted_rows(expect), atol=1e-12)
    path = scene.camera_paths["c"]
    assert path.fov_y == 50.0 and path.loop and [k.time for k in path.keys] == [0.0, 2.0]
    assert load_scene(write(tmp_path, BASE, "again.toml")).content_hash() == scene.content_hash()


def test_axis_angle_rotation_and_uniform_scale(tmp_path):
    text = BASE.replace("rotate = [10.0, 20.0, 30.0]", "rotate = { axis = [1.0, 1.0, 0.0], angle = 40.0 }")
    text = text.replace("scale = [2.0, 1.0, 0.5]", "scale = 3.0")
    scene = load_scene(write(tmp_path, text))
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    r = Rotation.from_rotvec(axis * np.radians(40)).as_matrix()
    np.testing.assert_allclose(scene.instances[0].transform[:3, :3], 3 * r, atol=1e-12)


@pytest.mark.parametrize("gen", sorted(GENERATORS))
def test_every_generator_loads_from_toml(tmp_path, gen):
    text = f'[[mesh]]\nname = "m"\ngenerator = "{gen}"\n[[instance]]\nname = "i"\nmesh = "m"\n'
    scene = load_scene(write(tmp_path, text))
    assert scene.meshes[0].area() > 0
    lo, hi = scene.world_bounds()
    assert scene.ao_distance == pytest.approx(0.1 * np.linalg.norm(hi - lo))  # default when not set


def test_mesh_path_relative_to_file(tmp_path):
    sub = tmp_path / "meshes"
    sub.mkdir()
    (sub / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    text = '[[mesh]]\nname = "m"\npath = "meshes/tri.obj"\ndouble_sided = true\n[[instance]]\nname = "i"\nmesh = "m"\n'
    scene = load_scene(write(tmp_path, text))
    assert scene.meshes[0].double_sided and scene.meshes[0].area() == pytest.approx(0.5)


def test_shipped_scenes_load():
    from psao.scene.loader import example_scenes

    names = sorted(example_scenes())
    assert names == sorted(f.stem for f in (REPO / "src" / "psao" / "scene" / "scenes").glob("*.toml")) and names
    for name in names:
        scene = load_scene(f"builtin:{name}")
        assert scene.instances and scene.camera_paths, name
        assert scene.content_hash() == load_scene(REPO / "src" / "psao" / "scene" / "scenes" / f"{name}.toml").content_hash()


BAD = [  # (replace this, with that, error class, regex the message must match)
    ('generator = "box"', 'generator = "teapot"', SceneFormatError, r"mesh 'b'.*unknown generator 'teapot'"),
    ("size = [1.0, 2.0, 3.0]", "size = [1.0, 2.0, 3.0]\nradius = 2.0", SceneFormatError, r"mesh 'b'.*unknown key 'radius'"),
    ("size = [1.0, 2.0, 3.0]", 'size = "big"', SceneFormatError, r"mesh 'b'.*generator 'box'"),
    ('generator = "box"', 'generator = "box"\npath = "x.obj"', SceneFormatError, r"mesh 'b'.*exactly one"),
    ('generator = "box"\nsize = [1.0, 2.0, 3.0]', 'path = "../outside.obj"', SceneFormatError, r"mesh 'b'.*inside"),
    ('generator = "box"\nsize = [1.0, 2.0, 3.0]', 'path = "missing.obj"', SceneNotFound, r"mesh 'b'.*missing\.obj"),
    ("color = [0.1, 0.2, 0.3]", "color = [2.0, 0.2, 0.3]", SceneFormatError, r"mesh 'b'.*color"),
    ('mesh = "b"', 'mesh = "nope"', SceneFormatError, r"instance 'i'.*unknown mesh 'nope'"),
    ("scale = [2.0, 1.0, 0.5]", "scale = [2.0, 0.0, 0.5]", SceneFormatError, r"instance 'i'.*zero"),
    ("scale = [2.0, 1.0, 0.5]", "scale = 0", SceneFormatError, r"instance 'i'.*zero"),
    ("translate = [1.0, 2.0, 3.0]", "translate = [nan, 2.0, 3.0]", SceneFormatError, r"instance 'i'.*translate"),
    ("translate = [1.0, 2.0, 3.0]", "translate = [1.0, 2.0]", SceneFormatError, r"instance 'i'.*translate"),
    ("rotate = [10.0, 20.0, 30.0]", "rotate = { axis = [0.0, 0.0, 0.0], angle = 3.0 }", SceneFormatError, r"instance 'i'.*axis"),
    ("ao_distance = 0.75", "ao_distance = -1.0", SceneFormatError, r"\[scene\].*ao_distance"),
    ("ao_distance = 0.75", "ao_distance = inf", SceneFormatError, r"\[scene\].*ao_distance"),
    ("time = 2.0", "time = 0.0", SceneFormatError, r"camera_path 'c'.*key 1.*not after"),
    ("fov_y = 50.0", "fov_y = 190.0", SceneFormatError, r"camera_path 'c'.*fov_y"),
    ('[[instance]]\nname = "i"', '[[instance]]\nname = "i"\nwobble = 1', SceneFormatError, r"instance 'i'.*unknown key 'wobble'"),
    ('name = "t"', 'name = "t"\n[extra]\nx = 1', SceneFormatError, r"unknown key 'extra'"),
]


@pytest.mark.parametrize("old,new,err,pattern", BAD, ids=[b[3][:40] for b in BAD])
def test_bad_field_names_file_and_element(tmp_path, old, new, err, pattern):
    assert old in BASE
    f = write(tmp_path, BASE.replace(old, new, 1), "broken_scene.toml")
    with pytest.raises(err) as e:
        load_scene(f)
    msg = str(e.value)
    assert "\n" not in msg and "broken_scene.toml" in msg
    assert re.search(pattern, msg), msg


def test_duplicate_names(tmp_path):
    text = BASE + '\n[[instance]]\nname = "i"\nmesh = "b"\n'
    with pytest.raises(SceneFormatError, match=r"instance 'i'.*duplicate"):
        load_scene(write(tmp_path, text))


def test_empty_scene(tmp_path):
    with pytest.raises(SceneFormatError, match="no \\[\\[instance\\]\\]"):
        load_scene(write(tmp_path, '[scene]\nname = "empty"\n'))
