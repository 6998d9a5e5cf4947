"""Transform math shared by the scene modules: quaternions, rotations and 4x4 matrices (numpy, float64).

Quaternions are (x, y, z, w). 4x4 matrices act on column vectors (world = M @ [x, y, z, 1]); `trs` is
T * R * S (scale first, then rotate, then translate). Every module of psao.scene that builds or
interpolates a transform takes it from here; this module imports nothing else of the package.
"""
from __future__ import annotations

import math

import numpy as np


# ------------------------------------------------------------------------------------ quaternions

def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from unit quaternions (..., 4) in (x, y, z, w) order."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    if q.ndim == 1:  # one quaternion (every rigid mover, every tick): the same products on Python floats
        x, y, z, w = q.tolist()
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes a while to import, most scenes never call this

    q = Rotation.from_matrix(np.asarray(r, dtype=np.float64)).as_quat()
    return q if q[3] >= 0 else -q


def slerp(q0: np.ndarray, q1: np.ndarray, u) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions (..., 4); u broadcasts."""
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)[..., None]
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(d < 0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(theta)
    near = s < 1e-9  # nearly equal: linear is exact enough and avoids 0 / 0
    safe = np.where(near, 1.0, s)
    a = np.where(near, 1 - u, np.sin((1 - u) * theta) / safe)
    b = np.where(near, u, np.sin(u * theta) / safe)
    q = a * q0 + b * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b (apply b, then a), (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def quat_pow(q: np.ndarray, n: float) -> np.ndarray:
    """q^n for a unit quaternion: the same axis, n times the angle."""
    w = float(np.clip(q[3], -1.0, 1.0))
    angle = 2 * math.acos(w)
    s = math.sqrt(max(1 - w * w, 0.0))
    if s < 1e-12:
        return np.array([0.0, 0.0, 0.0, 1.0]) if w > 0 or n % 2 == 0 else np.array([0.0, 0.0, 0.0, -1.0])
    axis = q[:3] / s
    half = angle * n / 2
    return np.array([*(axis * math.sin(half)), math.cos(half)])


# ------------------------------------------------------------------------------------ rotations

def axis_angle_matrix(axis, radians: float) -> np.ndarray:
    """3x3 rotation by `radians` about `axis` (right-handed, Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(radians) * k + (1 - math.cos(radians)) * (k @ k)


def rotation_xyz(degrees) -> np.ndarray:
    """3x3 rotation from Euler angles in degrees, applied about X, then Y, then Z (fixed axes)."""
    rx, ry, rz = np.radians(np.asarray(degrees, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


def rotation_axis_angle(axis, degrees: float) -> np.ndarray:
    """3x3 rotation by `degrees` about `axis` (right-handed, Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * (k @ k)


# ------------------------------------------------------------------------------------ 4x4 matrices

def translation_matrix(v) -> np.ndarray:
    """4x4 translation by v (3,)."""
    m = np.eye(4)
    m[:3, 3] = v
    return m


def placed_about(translate, linear, origin) -> np.ndarray:
    """4x4 translation_matrix(translate) @ linear_matrix(linear) @ translation_matrix(-origin): `linear` about
    `origin`, which then lands at `translate`; built directly (rigid motions make one per mover per tick)."""
    m = np.zeros((4, 4))
    m[:3, :3] = linear
    m[:3, 3] = np.asarray(translate, np.float64) - np.dot(linear, np.asarray(origin, np.float64))
    m[3, 3] = 1.0
    return m


def yaw_matrix(radians: float) -> np.ndarray:
    """3x3 rotation by `radians` about +Y (axis_angle_matrix about (0, 1, 0) on Python floats)."""
    s, c = math.sin(radians), math.cos(radians)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def linear_matrix(r: np.ndarray) -> np.ndarray:
    """4x4 with the 3x3 linear part r."""
    m = np.eye(4)
    m[:3, :3] = r
    return m


def trs(translate=(0.0, 0.0, 0.0), rotate=None, scale=1.0) -> np.ndarray:
    """4x4 local-to-world = T * R * S. rotate: Euler degrees (x, y, z) or a 3x3 matrix; scale: float or 3."""
    m = np.eye(4)
    r = np.eye(3) if rotate is None else np.asarray(rotate, dtype=np.float64)
    if r.shape == (3,):
        r = rotation_xyz(r)
    m[:3, :3] = r * np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))[None, :]
    m[:3, 3] = translate
    return m


def trs_matrix(translation=None, rotation=None, scale=None) -> np.ndarray:
    """4x4 from glTF TRS: translation (3), rotation quaternion (x, y, z, w), scale (3)."""
    m = np.eye(4)
    if rotation is not None:
        m[:3, :3] = quat_to_matrix(np.asarray(rotation, dtype=np.float64))
    if scale is not None:
        m[:3, :3] = m[:3, :3] * np.asarray(scale, dtype=np.float64)[None, :]
    if translation is not None:
        m[:3, 3] = translation
    return m
