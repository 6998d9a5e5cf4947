"""Camera paths (looping, interpolation) and the OpenGL view/projection matrices."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from psao.scene import CameraKey, CameraPath, camera_at, default_orbit, load_scene, look_at, perspective
from psao.scene.builtin import BUILTINS

RNG = np.random.default_rng(3)


def random_path(n=5, loop=True, closed=False) -> CameraPath:
    times = np.cumsum(RNG.uniform(0.5, 2.0, n)) - 0.7
    eyes = RNG.normal(size=(n, 3)) * 5
    targets = RNG.normal(size=(n, 3))
    if closed:
        eyes[-1], targets[-1] = eyes[0], targets[0]
    keys = [CameraKey(float(t), tuple(e), tuple(g)) for t, e, g in zip(times, eyes, targets)]
    return CameraPath("p", keys, loop=loop)


@pytest.mark.parametrize("interp", ["linear", "catmull_rom"])
def test_passes_through_keys(interp):
    path = random_path(closed=True)
    for k in path.keys:
        eye, target = camera_at(path, k.time, interp)
        np.testing.assert_allclose(eye, k.eye, atol=1e-12)
        np.testing.assert_allclose(target, k.target, atol=1e-12)


def test_linear_midpoints():
    path = random_path(loop=False)
    for a, b in zip(path.keys, path.keys[1:]):
        eye, target = camera_at(path, (a.time + b.time) / 2, "linear")
        np.testing.assert_allclose(eye, (np.array(a.eye) + b.eye) / 2, atol=1e-12)
        np.testing.assert_allclose(target, (np.array(a.target) + b.target) / 2, atol=1e-12)


def test_catmull_rom_reproduces_uniform_straight_motion():
    keys = [CameraKey(float(t), (2.0 * t, 1.0, -t), (0.0, 0.0, 0.0)) for t in range(6)]
    path = CameraPath("line", keys, loop=False)
    for t in np.linspace(0, 5, 41):
        np.testing.assert_allclose(camera_at(path, t)[0], [2 * t, 1, -t], atol=1e-12)


@pytest.mark.parametrize("interp", ["linear", "catmull_rom"])
def test_looping_is_periodic(interp):
    path = random_path(closed=True)
    period = path.keys[-1].time - path.keys[0].time
    for t in RNG.uniform(-20, 20, 25):
        for k in (-3, 1, 7):
            a, b = camera_at(path, t, interp), camera_at(path, t + k * period, interp)
            np.testing.assert_allclose(a[0], b[0], atol=1e-9)
            np.testing.assert_allclose(a[1], b[1], atol=1e-9)


def test_closed_catmull_rom_is_smooth_across_the_seam():
    path = random_path(n=6, closed=True)
    t0, h = path.keys[0].time, 1e-5
    # velocity just before and just after the seam (and at an interior key, for scale)
    before = (camera_at(path, t0 - h)[0] - camera_at(path, t0 - 2 * h)[0]) / h
    after = (camera_at(path, t0 + 2 * h)[0] - camera_at(path, t0 + h)[0]) / h
    assert np.linalg.norm(before - after) < 1e-2 * max(1.0, np.linalg.norm(before))


def test_non_looping_path_holds_its_ends():
    path = random_path(loop=False)
    np.testing.assert_allclose(camera_at(path, -100)[0], path.keys[0].eye)
    np.testing.assert_allclose(camera_at(path, 1e6)[0], path.keys[-1].eye)


def test_look_at_maps_eye_and_target():
    for _ in range(20):
        eye, target = RNG.normal(size=3) * 10, RNG.normal(size=3)
        v = look_at(eye, target)
        np.testing.assert_allclose(v[:3, :3] @ v[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(v[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_allclose(v @ [*eye, 1], [0, 0, 0, 1], atol=1e-9)
        t = v @ [*target, 1]
        np.testing.assert_allclose(t[:2], 0, atol=1e-9)
        assert t[2] == pytest.approx(-np.linalg.norm(target - eye))  # looks down -z
        up = v[:3, :3] @ [0, 1, 0]
        assert up[1] >= 0  # world up stays up on screen
    v = look_at([0, 5, 0], [0, 0, 0])  # looking straight down: still a rotation
    np.testing.assert_allclose(v[:3, :3] @ v[:3, :3].T, np.eye(3), atol=1e-12)


def test_perspective_planes_and_fov():
    fov, aspect, near, far = 60.0, 1.5, 0.1, 50.0
    p = perspective(fov, aspect, near, far)

    def ndc(x):
        c = p @ [*x, 1.0]
        return c[:3] / c[3]

    assert ndc([0, 0, -near])[2] == pytest.approx(-1.0)
    assert ndc([0, 0, -far])[2] == pytest.approx(1.0)
    d = 7.0
    half_h = d * np.tan(np.radians(fov / 2))
    np.testing.assert_allclose(ndc([aspect * half_h, half_h, -d])[:2], [1, 1])
    with pytest.raises(ValueError):
        perspective(60, 1, 1.0, 0.5)


def test_builtin_camera_paths_look_into_the_scene():
    for name in BUILTINS:
        scene = load_scene(f"builtin:{name}")
        lo, hi = scene.world_bounds()
        for path in scene.camera_paths.values():
            for t in np.linspace(0, path.keys[-1].time, 17):
                eye, target = camera_at(path, t)
                assert np.all(target > lo) and np.all(target < hi), (name, t)
                assert np.linalg.norm(target - eye) > 0.1


def test_default_orbit_warns_once(caplog):
    scene = load_scene("builtin:cornell")
    scene.name = "orbit-test"
    scene.camera_paths.clear()
    with caplog.at_level(logging.WARNING, logger="psao.scene"):
        a, b = default_orbit(scene), default_orbit(scene)
    assert sum("orbit-test" in r.getMessage() for r in caplog.records) == 1
    lo, hi = scene.world_bounds()
    for t in np.linspace(0, 40, 33):
        eye, target = camera_at(a, t)
        np.testing.assert_allclose(target, (lo + hi) / 2)
        assert not np.all((eye > lo) & (eye < hi))  # outside the bounds
    np.testing.assert_allclose(camera_at(a, 3.3)[0], camera_at(b, 3.3)[0])


@pytest.mark.parametrize("extent", [(0.2, 3.0, 0.2), (40.0, 0.5, 25.0), (1.0, 1.0, 1.0)])
@pytest.mark.parametrize("size", [(640, 360), (400, 400)])
def test_default_orbit_keeps_every_corner_in_view(tmp_path, extent, size):
    """Tall, flat and cubic models: every bounding-box corner projects inside the frustum at every
    frame along the default orbit (frames at least as wide as tall)."""
    from psao.client.render.views import path_matrices, path_times

    ex = np.asarray(extent)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * ex
    obj = tmp_path / f"box{ex[0]:g}x{ex[1]:g}.obj"
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7), (1, 3, 7),
             (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    obj.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in corners) + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    scene = load_scene(obj)
    path = default_orbit(scene)
    for t in path_times(path, 60):
        view, proj = path_matrices(scene, path, float(t), size)
        clip = (proj @ view @ np.c_[corners, np.ones(8)].T).T
        assert (clip[:, 3] > 0).all()
        ndc = clip[:, :3] / clip[:, 3:]
        assert np.abs(ndc).max() <= 1.0, (t, ndc)
