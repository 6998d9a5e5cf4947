"""Rigid animations: keyframes, rolling without slipping, walking paths, swings, platforms; TOML syntax
and its load-time validation; the built-in dynamic scenes."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from psao.scene import SceneFormatError, load_scene
from psao.scene.model import animation_hash
from psao.scene.rigid import (KeyframeAnimation, PathAnimation, PlatformAnimation, Polyline, RigidKey, RollAnimation,
                              SwingAnimation, instance_transform, is_dynamic)
from psao.scene.transforms import axis_angle_matrix, matrix_to_quat, trs

RNG = np.random.default_rng(11)


def assert_rigid(m: np.ndarray):
    r = m[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_keyframes_hit_keys_slerp_and_loop():
    base = trs((1.0, 2.0, 3.0), (0, 30, 0))
    axis = np.array([0.0, 0.0, 1.0])
    keys = [RigidKey(0.0, np.zeros(3), matrix_to_quat(np.eye(3)), np.ones(3)),
            RigidKey(2.0, np.array([4.0, 0, 0]), matrix_to_quat(axis_angle_matrix(axis, math.radians(90))),
                     np.array([2.0, 2.0, 2.0])),
            RigidKey(3.0, np.zeros(3), matrix_to_quat(np.eye(3)), np.ones(3))]
    anim = KeyframeAnimation(base=base, keys=keys, loop=True)
    np.testing.assert_allclose(anim.matrix(0.0), base, atol=1e-12)
    m = anim.matrix(2.0)  # translate, then rotate and scale about the object's origin
    origin = base[:3, 3]
    expect = trs(origin + [4, 0, 0], axis_angle_matrix(axis, math.radians(90)) * 2.0) @ trs(-origin) @ base
    np.testing.assert_allclose(m, expect, atol=1e-12)
    # halfway between keys 0 and 1: translation and scale linear, rotation the half angle (slerp)
    half = anim.matrix(1.0) @ np.linalg.inv(base)
    r = half[:3, :3] / 1.5
    np.testing.assert_allclose(r, axis_angle_matrix(axis, math.radians(45)), atol=1e-12)
    for t in RNG.uniform(-10, 10, 10):
        np.testing.assert_allclose(anim.matrix(t), anim.matrix(t + 3.0), atol=1e-9)


def test_slerp_constant_angular_speed():
    q0 = matrix_to_quat(np.eye(3))
    q1 = matrix_to_quat(axis_angle_matrix([1, 1, 0], math.radians(160)))
    anim = KeyframeAnimation(base=np.eye(4), keys=[RigidKey(0.0, np.zeros(3), q0, np.ones(3)),
                                                   RigidKey(1.0, np.zeros(3), q1, np.ones(3))], loop=False)
    angles = [Rotation.from_matrix(anim.matrix(u)[:3, :3]).magnitude() for u in np.linspace(0, 1, 11)]
    np.testing.assert_allclose(np.diff(angles), math.radians(16), atol=1e-9)


def ball_centre(anim, t: float) -> np.ndarray:
    """Where the ball's centre (the base transform's origin, in mesh space (0, 0, 0)) is at time t."""
    return anim.matrix(t)[:3, 3]


def _roll(closed=True):
    r = 0.6
    pts = np.array([[0.0, r, 0.0], [5.0, r, 0.0], [5.0, r, 3.0], [1.0, r, 4.0]])
    return RollAnimation(base=trs(pts[0], (10, 20, 30)), path=Polyline(pts, closed=closed), speed=1.3, radius=r), r


@pytest.mark.parametrize("closed", [True, False])
def test_roll_without_slipping(closed):
    anim, r = _roll(closed)
    h = 1e-5
    for t in RNG.uniform(0, 60, 40):
        m = anim.matrix(t)
        assert_rigid(m)
        centre = ball_centre(anim, t)
        assert centre[1] == pytest.approx(r)
        # the material point touching the floor is at rest (rolling, not sliding)
        contact_local = np.linalg.inv(m) @ [*(centre - [0, r, 0]), 1.0]
        v = ((anim.matrix(t + h) @ contact_local) - (anim.matrix(t - h) @ contact_local))[:3] / (2 * h)
        top_local = np.linalg.inv(m) @ [*(centre + [0, r, 0]), 1.0]
        v_top = ((anim.matrix(t + h) @ top_local) - (anim.matrix(t - h) @ top_local))[:3] / (2 * h)
        if np.linalg.norm(v_top) > 0.1:  # not exactly at a turning point of the ping-pong
            assert np.linalg.norm(v) < 1e-4
            assert np.linalg.norm(v_top) == pytest.approx(2 * anim.speed, rel=1e-4)  # top moves at 2v


def test_roll_segment_quaternion_is_the_axis_angle_rotation():
    """The rolling rotation's quaternion (scalar math) is the Rodrigues matrix's, w >= 0, up to rounding,
    on either side of half a turn."""
    anim, r = _roll(True)
    for i in range(len(anim.path.lengths)):
        for dist in (0.0, 0.3, math.pi * r * 0.999, math.pi * r * 1.001, 5.0, 17.0):
            want = matrix_to_quat(axis_angle_matrix(np.cross([0, 1, 0], anim.path.dirs[i]), dist / r))
            np.testing.assert_allclose(anim._segment_quat(i, dist), want, atol=1e-12)


def test_one_quaternion_to_matrix_is_the_batched_result_bit_for_bit():
    from psao.scene.transforms import quat_to_matrix
    q = RNG.normal(size=(200, 4))
    assert np.array_equal(np.array([quat_to_matrix(x) for x in q]), quat_to_matrix(q))


def test_roll_orientation_matches_integrated_rotation_over_laps():
    """Brute force: compose many small rolling rotations along the path for 2.5 laps."""
    anim, r = _roll(True)
    steps = 4000  # exact on straight runs (rotations about one axis commute); errs only at corners
    t_end = 2.5 * anim.path.length / anim.speed
    rot = np.eye(3)
    dt = t_end / steps
    centre_prev = ball_centre(anim, 0.0)
    for k in range(1, steps + 1):
        centre = ball_centre(anim, k * dt)
        d = centre - centre_prev
        if np.linalg.norm(d) > 0:
            rot = axis_angle_matrix(np.cross([0, 1, 0], d), np.linalg.norm(d) / r) @ rot
        centre_prev = centre
    got = (anim.matrix(t_end) @ np.linalg.inv(anim.base))[:3, :3]
    assert np.abs(got - rot).max() < 1e-3


def test_path_faces_along_motion():
    pts = np.array([[0.0, 0, 0], [4.0, 0, 0], [4.0, 0, 4.0]])
    anim = PathAnimation(base=trs(pts[0]), path=Polyline(pts, closed=False), speed=1.0)
    for t in (0.5, 3.0, 5.0, 9.0, 14.0):
        m = anim.matrix(t)
        assert_rigid(m)
        v = (anim.matrix(t + 1e-4)[:3, 3] - anim.matrix(t - 1e-4)[:3, 3]) / 2e-4
        np.testing.assert_allclose(m[:3, :3] @ [0, 0, 1], v / np.linalg.norm(v), atol=1e-6)
    np.testing.assert_allclose(anim.matrix(0.0), anim.matrix(16.0), atol=1e-12)  # there and back: 2 x 8 m


def test_swing_and_platform():
    base = trs((0.0, 1.0, 0.0))
    s = SwingAnimation(base=base, pivot=np.array([0.0, 3.0, 0.0]), axis=np.array([0.0, 0.0, 1.0]),
                       amplitude=30.0, period=2.0)
    for t in RNG.uniform(0, 10, 10):
        m = s.matrix(t)
        assert_rigid(m)
        np.testing.assert_allclose(m @ np.linalg.inv(base) @ [0, 3, 0, 1], [0, 3, 0, 1], atol=1e-12)  # pivot fixed
    angle = Rotation.from_matrix(s.matrix(0.5)[:3, :3]).magnitude()
    assert angle == pytest.approx(math.radians(30))
    p = PlatformAnimation(base=base, offset=np.array([0.0, 0.0, 5.0]), period=4.0)
    np.testing.assert_allclose(p.matrix(2.0)[:3, 3], [0, 1, 5])
    np.testing.assert_allclose(p.matrix(4.0), base, atol=1e-12)


TOML = """
[[mesh]]
name = "ball"
generator = "sphere"
radius = 0.5

[[instance]]
name = "a"
mesh = "ball"
translate = [0.0, 0.5, 0.0]
[instance.animation]
kind = "keyframes"
loop = false
[[instance.animation.key]]
time = 0.0
[[instance.animation.key]]
time = 1.0
translate = [2.0, 0.0, 0.0]
rotate = [0.0, 90.0, 0.0]
scale = 2.0

[[instance]]
name = "b"
mesh = "ball"
translate = [0.0, 0.5, 3.0]
[instance.animation]
kind = "roll"
path = [[0.0, 3.0], [4.0, 3.0]]
radius = 0.5
speed = 2.0
loop = false

[[instance]]
name = "c"
mesh = "ball"
translate = [0.0, 1.0, 0.0]
[instance.animation]
kind = "swing"
pivot = [0.0, 3.0, 0.0]
axis = [1.0, 0.0, 0.0]
amplitude = 20.0
period = 3.0

[[instance]]
name = "d"
mesh = "ball"
[instance.animation]
kind = "platform"
offset = [0.0, 2.0, 0.0]
period = 5.0

[[instance]]
name = "e"
mesh = "ball"
[instance.animation]
kind = "path"
path = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]
speed = 0.5

[[instance]]
name = "static"
mesh = "ball"
"""


def test_toml_animations(tmp_path):
    f = tmp_path / "anim.toml"
    f.write_text(TOML)
    scene = load_scene(f)
    kinds = {i.name: (i.animation.kind if i.animation else None) for i in scene.instances}
    assert kinds == {"a": "keyframes", "b": "roll", "c": "swing", "d": "platform", "e": "path", "static": None}
    for k, inst in enumerate(scene.instances):
        np.testing.assert_allclose(instance_transform(scene, k, 0.0), inst.transform, atol=1e-12)
        assert is_dynamic(scene, k) == (inst.animation is not None)
    a = instance_transform(scene, 0, 1.0)
    np.testing.assert_allclose(a[:3, 3], [2.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(a[:3, :3], 2 * axis_angle_matrix([0, 1, 0], math.radians(90)), atol=1e-12)
    np.testing.assert_allclose(instance_transform(scene, 1, 1.0)[:3, 3], [2.0, 0.5, 3.0], atol=1e-12)


BAD = [
    ("time = 1.0", "time = 0.0", r"instance 'a': animation: key 1.*out of order"),
    ('translate = [2.0, 0.0, 0.0]', 'translate = [nan, 0.0, 0.0]', r"instance 'a': animation: key 1.*translate"),
    ("scale = 2.0", "scale = 0.0", r"instance 'a': animation: key 1.*zero"),
    ("scale = 2.0", "scale = [1.0, -1.0, 1.0]", r"instance 'a': animation: key 1.*scale.*> 0"),
    ('kind = "keyframes"', 'kind = "teleport"', r"instance 'a': animation.*kind"),
    ("radius = 0.5\nspeed", "speed", r"instance 'b': animation.*radius"),
    ("path = [[0.0, 3.0], [4.0, 3.0]]", "path = [[0.0, 3.0], [0.0, 3.0]]", r"instance 'b': animation.*equal"),
    ("path = [[0.0, 3.0], [4.0, 3.0]]", "path = [[0.0, 3.0]]", r"instance 'b': animation.*path"),
    ("period = 3.0", "period = 0.0", r"instance 'c': animation.*period"),
    ("axis = [1.0, 0.0, 0.0]", "axis = [0.0, 0.0, 0.0]", r"instance 'c': animation.*axis"),
    ("offset = [0.0, 2.0, 0.0]", "offset = [0.0, inf, 0.0]", r"instance 'd': animation.*offset"),
    ("speed = 0.5", "speed = 0.5\nwobble = 1", r"instance 'e': animation.*unknown key 'wobble'"),
]


@pytest.mark.parametrize("old,new,pattern", BAD, ids=[b[2][:40] for b in BAD])
def test_toml_animation_errors_at_load_time(tmp_path, old, new, pattern):
    assert old in TOML
    f = tmp_path / "bad_anim.toml"
    f.write_text(TOML.replace(old, new, 1))
    with pytest.raises(SceneFormatError, match=pattern) as e:
        load_scene(f)
    assert "bad_anim.toml" in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------------------------- built-in dynamic scenes

def world_vertices(scene, k, t):
    m = scene.meshes[scene.instances[k].mesh]
    T = instance_transform(scene, k, t)
    return m.vertices @ T[:3, :3].T + T[:3, 3]


def test_courtyard_boulders_roll_on_the_floor_without_hitting_anything():
    scene = load_scene("builtin:courtyard")
    rolling = [k for k, i in enumerate(scene.instances) if i.animation is not None]
    assert len(rolling) >= 2 and all(scene.instances[k].animation.kind == "roll" for k in rolling)
    obstacles = [k for k, i in enumerate(scene.instances)
                 if i.name.startswith(("boulder", "column_ground"))]
    boxes = [(world_vertices(scene, k, 0).min(0), world_vertices(scene, k, 0).max(0)) for k in obstacles]
    for t in np.linspace(0, 60, 61):
        spheres = []
        for k in rolling:
            v = world_vertices(scene, k, t)
            r = scene.instances[k].animation.radius
            assert abs(v[:, 1].min()) < 0.08 * r  # resting on the floor
            c = v.mean(0)
            spheres.append((c, r))
            for lo, hi in boxes:  # never inside an obstacle's box (closest point of the box is farther than r)
                assert np.linalg.norm(np.clip(c, lo, hi) - c) > 0.9 * r, (scene.instances[k].name, t)
        for a in range(len(spheres)):
            for b in range(a + 1, len(spheres)):
                assert np.linalg.norm(spheres[a][0] - spheres[b][0]) > spheres[a][1] + spheres[b][1]


def test_space_is_mostly_static_with_far_moving_asteroids():
    scene = load_scene("builtin:space")
    moving = [k for k, i in enumerate(scene.instances) if i.animation is not None]
    assert 2 <= len(moving) <= 6
    tris = lambda ks: sum(len(scene.meshes[scene.instances[k].mesh].faces) for k in ks)  # noqa: E731
    assert tris(moving) < 0.25 * tris(range(len(scene.instances)))
    static_hi = np.max([np.abs(world_vertices(scene, k, 0)).max() for k in range(len(scene.instances))
                        if k not in moving])
    for k in moving:
        for t in np.linspace(0, 40, 9):
            v = world_vertices(scene, k, t)
            assert np.linalg.norm(v, axis=1).min() > static_hi + 10 * scene.ao_distance
    lo, hi = scene.world_bounds()
    assert (hi - lo).max() > 150


def test_robots_walk_in_the_room():
    from psao.scene.skinning import skinned_vertices
    scene = load_scene("builtin:robots")
    robots = [k for k, i in enumerate(scene.instances) if scene.meshes[i.mesh].skin is not None]
    assert len(robots) >= 3
    assert all(scene.instances[k].animation is not None for k in robots)
    furniture = [k for k, i in enumerate(scene.instances) if i.name.startswith(("workbench", "crate", "shelf", "pillar"))]
    boxes = [(world_vertices(scene, k, 0).min(0), world_vertices(scene, k, 0).max(0)) for k in furniture]
    for t in np.linspace(0, 30, 31):
        heads = []
        for k in robots:
            mesh = scene.meshes[scene.instances[k].mesh]
            T = instance_transform(scene, k, t)
            v = skinned_vertices(mesh, t) @ T[:3, :3].T + T[:3, 3]
            assert -0.05 < v[:, 1].min() < 0.1 and 1.6 < v[:, 1].max() < 1.85  # feet on the floor, upright
            assert (np.abs(v[:, [0, 2]]) < [8.0, 5.0]).all()  # inside the room
            for lo, hi in boxes:
                inside = np.all((v > lo + 0.01) & (v < hi - 0.01), axis=1)
                assert not inside.any(), (scene.instances[k].name, t)
            heads.append(v.mean(0))
        heads = np.array(heads)
        d = np.linalg.norm(heads[:, None, [0, 2]] - heads[None, :, [0, 2]], axis=2) + np.eye(len(heads)) * 9
        assert d.min() > 0.6, t  # robots do not walk through each other


def test_shipped_playground_uses_every_kind():
    scene = load_scene("builtin:playground")
    kinds = {i.animation.kind for i in scene.instances if i.animation is not None}
    assert kinds == {"keyframes", "roll", "path", "swing", "platform"}


def test_animation_hash_stable_and_sensitive():
    a, b = load_scene("builtin:courtyard"), load_scene("builtin:courtyard")
    assert animation_hash(a) == animation_hash(b)
    b.instances[[i.animation is not None for i in b.instances].index(True)].animation.speed *= 1.01
    assert animation_hash(a) != animation_hash(b)
    r = load_scene("builtin:robots")
    h = animation_hash(r)
    next(m for m in r.meshes if m.skin is not None).skin.animator.phase += 0.1
    assert animation_hash(r) != h
