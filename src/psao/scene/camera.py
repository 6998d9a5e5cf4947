"""Camera paths and matrices, shared by the client (rendering) and the server (view culling).

Conventions (OpenGL): right-handed, the camera looks down -Z in view space, clip space z in [-1, 1],
matrices are float64 4x4 acting on column vectors (p_clip = P @ V @ p_world).

Path timing: keys are sorted by time. A looping path repeats with period keys[-1].time - keys[0].time;
it is continuous when its last key repeats its first (builtins and the default orbit do), and then
Catmull-Rom takes its end tangents across the seam. A non-looping path holds its end keys.
"""
from __future__ import annotations

import logging

import numpy as np

from psao.scene.model import CameraKey, CameraPath, Scene

log = logging.getLogger("psao.scene")

INTERPOLATIONS = ("catmull_rom", "linear")


def _wrap_time(path: CameraPath, t: float) -> float:
    t0, t1 = path.keys[0].time, path.keys[-1].time
    if t1 <= t0:
        return t0
    if path.loop:
        return t0 + (t - t0) % (t1 - t0)
    return min(max(t, t0), t1)


def _closed(path: CameraPath) -> bool:
    a, b = path.keys[0], path.keys[-1]
    return path.loop and len(path.keys) > 2 and np.allclose(a.eye, b.eye) and np.allclose(a.target, b.target)


def camera_at(path: CameraPath, t: float, interpolation: str = "catmull_rom") -> tuple[np.ndarray, np.ndarray]:
    """(eye, target) at time t seconds, float64 (3,) each."""
    return path_sampler(path, interpolation)(t)


def path_sampler(path: CameraPath, interpolation: str = "catmull_rom"):
    """camera_at(path, t, interpolation) as a function of t, with the keys read once (a client sending its
    camera 30 times a second along a path need not rebuild them each time)."""
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"unknown interpolation '{interpolation}' (known: {', '.join(INTERPOLATIONS)})")
    keys = path.keys
    if not keys:
        raise ValueError(f"camera path '{path.name}' has no keys")
    pts = np.array([[*k.eye, *k.target] for k in keys], dtype=np.float64)  # (K, 6)
    times = np.array([k.time for k in keys], dtype=np.float64)
    closed = len(keys) > 1 and _closed(path)

    def at(t: float) -> tuple[np.ndarray, np.ndarray]:
        if len(keys) == 1:
            return pts[0, :3].copy(), pts[0, 3:].copy()
        t = _wrap_time(path, float(t))
        i = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(keys) - 2))
        span = times[i + 1] - times[i]
        u = 0.0 if span <= 0 else (t - times[i]) / span
        p1, p2 = pts[i], pts[i + 1]
        if interpolation == "linear":
            p = p1 + (p2 - p1) * u
        else:
            m1 = _tangent(times, pts, i, closed) * span
            m2 = _tangent(times, pts, i + 1, closed) * span
            h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
            p = h00 * p1 + h10 * m1 + h01 * p2 + h11 * m2
        return p[:3], p[3:]

    return at


def _tangent(times: np.ndarray, pts: np.ndarray, i: int, closed: bool) -> np.ndarray:
    """Catmull-Rom velocity at key i (per second) from its neighbours' positions and times, so the
    motion is C1 in time even with unevenly spaced keys. A closed loop takes neighbours across the
    seam (its last key equals its first); an open path uses one-sided differences at its ends."""
    n = len(pts)
    period = times[-1] - times[0]

    def key(j: int) -> tuple[float, np.ndarray]:
        if closed and j < 0:
            return times[n - 1 + j] - period, pts[n - 1 + j]
        if closed and j >= n:
            return times[j - n + 1] + period, pts[j - n + 1]
        j = min(max(j, 0), n - 1)
        return times[j], pts[j]

    (ta, pa), (tb, pb) = key(i - 1), key(i + 1)
    return (pb - pa) / (tb - ta)


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-view matrix (gluLookAt)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    f = target - eye
    if np.linalg.norm(f) == 0:
        raise ValueError("look_at: eye and target coincide")
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-12:  # looking along up: pick any perpendicular up
        s = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 0.0, 1.0])
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    """OpenGL projection (gluPerspective): view z in [-near, -far] maps to NDC z in [-1, 1]."""
    if not (0 < fov_y_deg < 180 and aspect > 0 and 0 < near < far):
        raise ValueError(f"perspective: bad parameters fov_y={fov_y_deg} aspect={aspect} near={near} far={far}")
    f = 1.0 / np.tan(np.radians(fov_y_deg) / 2)
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = f / aspect, f
    m[2, 2], m[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


_warned_orbit: set[str] = set()


# The default orbit: field of view, and how far beyond the distance at which the scene's bounding sphere
# just fits the vertical field of view the eye stays (room for the spline between keys to cut inwards).
ORBIT_FOV_Y = 50.0  # degrees
ORBIT_MARGIN = 1.1
ORBIT_ELEVATION = np.arctan2(0.6, 1.6)  # radians above the horizon (about 20.6 degrees)


def default_orbit(scene: Scene, period: float = 20.0, keys: int = 12) -> CameraPath:
    """A closed orbit around the scene bounds, for scenes without a camera path (warns once per scene).

    The eye circles the centre of the bounding box at a distance where the box's bounding sphere fits
    the vertical field of view (and so the horizontal one of any frame at least as wide as it is tall):
    the whole scene stays in view from every angle, however tall or flat it is."""
    if scene.name not in _warned_orbit:
        _warned_orbit.add(scene.name)
        log.warning("scene '%s' has no camera path: using an orbit around its bounds", scene.name)
    lo, hi = scene.world_bounds()
    center = (lo + hi) / 2
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    distance = ORBIT_MARGIN * radius / np.sin(np.radians(ORBIT_FOV_Y) / 2)
    out = []
    for k in range(keys + 1):
        a = 2 * np.pi * (k % keys) / keys
        direction = np.array([np.cos(ORBIT_ELEVATION) * np.sin(a), np.sin(ORBIT_ELEVATION),
                              np.cos(ORBIT_ELEVATION) * np.cos(a)])
        out.append(CameraKey(period * k / keys, tuple(center + distance * direction), tuple(center)))
    return CameraPath(name="orbit", keys=out, fov_y=ORBIT_FOV_Y, loop=True)


def scene_camera(scene: Scene, name: str | None = None) -> CameraPath:
    """The named camera path, the scene's first one, or the default orbit."""
    if name is not None:
        if name not in scene.camera_paths:
            raise KeyError(f"scene '{scene.name}' has no camera path '{name}' "
                           f"(known: {', '.join(scene.camera_paths) or 'none'})")
        return scene.camera_paths[name]
    if scene.camera_paths:
        return next(iter(scene.camera_paths.values()))
    return default_orbit(scene)
