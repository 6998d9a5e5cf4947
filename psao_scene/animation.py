"""Animation data: rigid motions of instances and skins of meshes.

Rigid (Instance.animation, a RigidAnimation): `matrix(t)` is the instance's local-to-world 4x4 at time t
seconds; Instance.transform holds matrix(0). Every animation keeps the instance's rest transform `base`
(its TOML translate/rotate/scale) and moves it:

    keyframes  world(t) = T(translate(t)) * T(o) R(rotation(t)) S(scale(t)) T(-o) * base, o = base origin:
               keys rotate and scale the object about its own origin; translation linear, rotation slerp
    roll       a ball of `radius` rolling without slipping along a polyline of centre positions on the
               floor (x, z), at `speed`: translation plus rotation s / radius about (up x direction)
    path       walks a polyline at `speed`, turning to face along it (yaw): for characters
    swing      pendulum: rotation about `axis` through `pivot` by amplitude * sin(2 pi t / period + phase)
    platform   back and forth: translation offset * (1 - cos(2 pi t / period + phase)) / 2

Skinned (Mesh.skin, a Skin): per-vertex joints and weights for Mesh.vertices (same order), inverse bind
matrices, and an animator giving the joint matrices at time t in the mesh's local space; a skinned
vertex is sum_k w_k * (joint_matrices(t)[j_k] @ inverse_bind[j_k]) @ v, then the instance transform
(identity for glTF skins, whose joints are already in the file's world space).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .errors import SceneFormatError
from .meshfile import quat_to_matrix

log = logging.getLogger("psao_scene")

MAX_JOINTS = 256  # joints per skin: the Warp kernel and the wire format index joints with 8 bits
UP = np.array([0.0, 1.0, 0.0])


# ------------------------------------------------------------------------------------ quaternions

def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix."""
    from scipy.spatial.transform import Rotation
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


def axis_angle_matrix(axis, radians: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(radians) * k + (1 - math.cos(radians)) * (k @ k)


def _translation(v) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


def _linear(r: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    return m


def _wrap(t: float, period: float, loop: bool) -> float:
    if period <= 0:
        return 0.0
    return t % period if loop else min(max(t, 0.0), period)


# -------------------------------------------------------------------------------------- rigid motions

@dataclass
class RigidKey:
    time: float  # seconds
    translate: np.ndarray  # (3,) world offset
    rotation: np.ndarray  # (4,) unit quaternion (x, y, z, w) about the object's origin
    scale: np.ndarray  # (3,) non-zero


@dataclass
class RigidAnimation:
    """Base of the rigid motions: `matrix(t)` is the world transform at time t (see module doc)."""
    base: np.ndarray  # (4, 4) rest transform of the instance

    kind = "static"

    def motion(self, t: float) -> np.ndarray:
        raise NotImplementedError

    def matrix(self, t: float) -> np.ndarray:
        return self.motion(float(t)) @ self.base


@dataclass
class KeyframeAnimation(RigidAnimation):
    keys: list[RigidKey] = field(default_factory=list)
    loop: bool = True  # period = last key time - first key time

    kind = "keyframes"

    def motion(self, t: float) -> np.ndarray:
        keys = self.keys
        times = np.array([k.time for k in keys])
        t = times[0] + _wrap(t - times[0], times[-1] - times[0], self.loop)
        i = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, max(len(keys) - 2, 0)))
        if len(keys) == 1:
            a = b = keys[0]
            u = 0.0
        else:
            a, b = keys[i], keys[i + 1]
            u = float(np.clip((t - a.time) / (b.time - a.time), 0.0, 1.0))
        translate = a.translate + (b.translate - a.translate) * u
        scale = a.scale + (b.scale - a.scale) * u
        rs = _linear(quat_to_matrix(slerp(a.rotation, b.rotation, u)) * scale[None, :])
        origin = self.base[:3, 3]
        return _translation(translate + origin) @ rs @ _translation(-origin)


@dataclass
class Polyline:
    """Positions along a polyline by arc length: closed (wraps to the start) or ping-pong (there and back)."""
    points: np.ndarray  # (K, 3)
    closed: bool

    def __post_init__(self):
        pts = np.asarray(self.points, dtype=np.float64)
        self.verts = np.vstack([pts, pts[:1]]) if self.closed else pts
        seg = np.diff(self.verts, axis=0)
        self.lengths = np.linalg.norm(seg, axis=1)
        self.dirs = seg / np.maximum(self.lengths, 1e-300)[:, None]
        self.starts = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.length = float(self.starts[-1])

    def locate(self, s: float) -> tuple[int, float]:
        """Segment index and distance into it for arc length s in [0, length]."""
        i = int(np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.lengths) - 1))
        return i, s - self.starts[i]

    def travel(self, distance: float) -> tuple[float, int]:
        """(arc length along the polyline, direction +1 / -1) after travelling `distance` from the start."""
        if self.closed:
            return distance % self.length, 1
        d = distance % (2 * self.length)
        return (d, 1) if d <= self.length else (2 * self.length - d, -1)


@dataclass
class RollAnimation(RigidAnimation):
    """Rolling without slipping: the contact point is at rest, so angular velocity = up x velocity / r.
    On each straight segment the ball turns about (up x direction) by distance / radius; the
    orientation at arc length s is the product of the segment rotations so far (a whole lap is one
    more rotation, applied as a power), so the motion is exact for any number of laps."""
    path: Polyline = None
    speed: float = 1.0  # m/s along the path
    radius: float = 1.0  # rolling radius, m

    kind = "roll"

    def __post_init__(self):
        segs = [matrix_to_quat(self._segment_rotation(i, self.path.lengths[i]))
                for i in range(len(self.path.lengths))]
        self._prefix = [np.array([0.0, 0.0, 0.0, 1.0])]  # orientation at the start of each segment
        for q in segs:
            self._prefix.append(quat_mul(q, self._prefix[-1]))

    def _segment_rotation(self, i: int, dist: float) -> np.ndarray:
        axis = np.cross(UP, self.path.dirs[i])
        if np.linalg.norm(axis) < 1e-12:  # a vertical segment: no rolling
            return np.eye(3)
        return axis_angle_matrix(axis, dist / self.radius)

    def _orientation(self, s: float, laps: int) -> np.ndarray:
        i, into = self.path.locate(s)
        q = quat_mul(matrix_to_quat(self._segment_rotation(i, into)), self._prefix[i])
        if laps:
            q = quat_mul(q, quat_pow(self._prefix[-1], laps))
        return quat_to_matrix(q)

    def motion(self, t: float) -> np.ndarray:
        path = self.path
        distance = self.speed * t
        if path.closed:
            laps = math.floor(distance / path.length)
            s = distance - laps * path.length
            rot = self._orientation(s, laps)
        else:  # ping-pong: rolling back undoes the rotation exactly
            s, _ = path.travel(distance)
            rot = self._orientation(s, 0)
        i, into = path.locate(s)
        centre = path.verts[i] + path.dirs[i] * into
        origin = self.base[:3, 3]
        return _translation(centre) @ _linear(rot) @ _translation(-origin)


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


@dataclass
class PathAnimation(RigidAnimation):
    """Walks a polyline at `speed`, yawed to face along the current segment (the model faces +Z)."""
    path: Polyline = None
    speed: float = 1.0

    kind = "path"

    def motion(self, t: float) -> np.ndarray:
        s, direction = self.path.travel(self.speed * t)
        i, into = self.path.locate(s)
        pos = self.path.verts[i] + self.path.dirs[i] * into
        d = self.path.dirs[i] * direction
        yaw = math.atan2(d[0], d[2])
        origin = self.base[:3, 3]
        return _translation(pos) @ _linear(axis_angle_matrix(UP, yaw)) @ _translation(-origin)


@dataclass
class SwingAnimation(RigidAnimation):
    pivot: np.ndarray = None  # (3,) world
    axis: np.ndarray = None  # (3,) world, non-zero
    amplitude: float = 30.0  # degrees
    period: float = 2.0  # seconds
    phase: float = 0.0  # degrees

    kind = "swing"

    def motion(self, t: float) -> np.ndarray:
        angle = math.radians(self.amplitude) * math.sin(2 * math.pi * t / self.period + math.radians(self.phase))
        return _translation(self.pivot) @ _linear(axis_angle_matrix(self.axis, angle)) @ _translation(-self.pivot)


@dataclass
class PlatformAnimation(RigidAnimation):
    offset: np.ndarray = None  # (3,) world displacement at the far end
    period: float = 4.0  # seconds for there and back
    phase: float = 0.0  # degrees

    kind = "platform"

    def motion(self, t: float) -> np.ndarray:
        f = 0.5 * (1 - math.cos(2 * math.pi * t / self.period + math.radians(self.phase)))
        return _translation(self.offset * f)


def instance_transform(scene, i: int, t: float) -> np.ndarray:
    """Local-to-world 4x4 of instance i at time t seconds."""
    inst = scene.instances[i]
    return inst.transform if inst.animation is None else inst.animation.matrix(t)


def animation_hash(scene, times=tuple(np.linspace(0.0, 60.0, 17))) -> str:
    """sha256 of every animated transform and skinning matrix sampled at `times`: equal on two machines
    iff they animate the scene alike (Scene.content_hash covers only the geometry at rest)."""
    import hashlib

    def stable(m) -> bytes:
        # Rounded (and -0.0 folded into 0.0) so last-ulp differences between math libraries do not count.
        return (np.round(np.asarray(m, dtype=np.float64), 6) + 0.0).tobytes()

    h = hashlib.sha256()
    for i, inst in enumerate(scene.instances):
        if inst.animation is not None:
            h.update(inst.name.encode())
            for t in times:
                h.update(stable(inst.animation.matrix(t)))
    for m in scene.meshes:
        if m.skin is not None:
            h.update(m.name.encode())
            h.update(np.ascontiguousarray(m.skin.joints, dtype=np.int64).tobytes())
            h.update(stable(m.skin.weights))
            for t in times:
                h.update(stable(m.skin.skinning_matrices(t)))
    return h.hexdigest()


def is_dynamic(scene, i: int) -> bool:
    """Whether instance i moves (rigid animation) or deforms (skinned mesh)."""
    inst = scene.instances[i]
    return inst.animation is not None or scene.meshes[inst.mesh].skin is not None


# ------------------------------------------------------------------------------------ TOML parsing

def parse_animation(data, where: str, base: np.ndarray) -> RigidAnimation:
    """An `[instance.animation]` table (schema in tomlscene.py); errors name `where`."""
    from .tomlscene import Table  # the TOML field reader; tomlscene imports this module lazily
    kinds = {"keyframes": ({"key", "loop"}, _parse_keyframes), "roll": ({"path", "speed", "radius", "loop"}, _parse_roll),
             "path": ({"path", "speed", "loop"}, _parse_path), "swing": ({"pivot", "axis", "amplitude", "period", "phase"}, _parse_swing),
             "platform": ({"offset", "period", "phase"}, _parse_platform)}
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind not in kinds:
        raise SceneFormatError(f"{where}: 'kind' must be one of {', '.join(kinds)}, got {kind!r}")
    allowed, parse = kinds[kind]
    return parse(Table(data, where, allowed | {"kind"}), np.asarray(base, dtype=np.float64))


def _parse_keyframes(t, base) -> KeyframeAnimation:
    from .tomlscene import Table, rotation_of, scale_of
    keys: list[RigidKey] = []
    for j, raw in enumerate(t.tables("key")):
        kt = Table(raw, f"{t.where}: key {j}", {"time", "translate", "rotate", "scale"})
        key = RigidKey(kt.number("time"), kt.vec("translate", 3, [0, 0, 0]), matrix_to_quat(rotation_of(kt)),
                       scale_of(kt))
        if (key.scale <= 0).any():  # a sign change between keys would pass through a zero scale
            raise kt.fail(f"'scale' of a keyframe must be > 0 (no zero or mirroring), got {key.scale.tolist()}")
        if keys and key.time <= keys[-1].time:
            raise kt.fail(f"time {key.time} is not after the previous key's {keys[-1].time} (keys out of order)")
        keys.append(key)
    if not keys:
        raise t.fail("needs at least one [[...animation.key]]")
    return KeyframeAnimation(base=base, keys=keys, loop=t.flag("loop", True))


def _polyline(t, base, loop_default: bool) -> Polyline:
    raw = t.data.get("path")
    if not isinstance(raw, list) or len(raw) < 2:
        raise t.fail("'path' must be a list of at least two [x, z] points")
    pts = []
    for k, p in enumerate(raw):
        if (not isinstance(p, list) or len(p) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in p)):
            raise t.fail(f"'path' point {k} must be [x, z] finite numbers, got {p!r}")
        pts.append([p[0], base[1, 3], p[1]])  # the centre keeps the instance's height
    line = Polyline(np.array(pts), closed=t.flag("loop", loop_default))
    if (line.lengths <= 0).any():
        raise t.fail("'path' has two equal consecutive points")
    return line


def _parse_roll(t, base) -> RollAnimation:
    return RollAnimation(base=base, path=_polyline(t, base, True), speed=t.number("speed", 1.0, positive=True),
                         radius=t.number("radius", positive=True))


def _parse_path(t, base) -> PathAnimation:
    return PathAnimation(base=base, path=_polyline(t, base, True), speed=t.number("speed", 1.0, positive=True))


def _parse_swing(t, base) -> SwingAnimation:
    axis = t.vec("axis", 3, [0, 0, 1])
    if not np.linalg.norm(axis) > 0:
        raise t.fail("'axis' must not be zero")
    return SwingAnimation(base=base, pivot=t.vec("pivot"), axis=axis, amplitude=t.number("amplitude", 30.0),
                          period=t.number("period", 2.0, positive=True), phase=t.number("phase", 0.0))


def _parse_platform(t, base) -> PlatformAnimation:
    return PlatformAnimation(base=base, offset=t.vec("offset"), period=t.number("period", 4.0, positive=True),
                             phase=t.number("phase", 0.0))


# ------------------------------------------------------------------------------------------- skins

class JointAnimator(Protocol):
    def joint_matrices(self, t: float) -> np.ndarray:
        """(J, 4, 4) joint matrices at time t in the skinned mesh's local space."""


@dataclass
class Skin:
    inverse_bind: np.ndarray  # (J, 4, 4) float64
    joints: np.ndarray  # (V, 4) int64, per vertex of Mesh.vertices, index into the J joints
    weights: np.ndarray  # (V, 4) float64, each row sums to 1
    animator: JointAnimator
    joint_names: list[str] = field(default_factory=list)

    @property
    def joint_count(self) -> int:
        return len(self.inverse_bind)

    def joint_matrices(self, t: float) -> np.ndarray:
        return self.animator.joint_matrices(float(t))

    def skinning_matrices(self, t: float) -> np.ndarray:
        """(J, 4, 4) matrices applied to rest-pose vertices: joint_matrices(t) @ inverse_bind."""
        return self.joint_matrices(t) @ self.inverse_bind


def check_skin(joints: np.ndarray, weights: np.ndarray, joint_count: int,
               where: str) -> tuple[np.ndarray, np.ndarray]:
    """Validate per-vertex skin data; returns joints (unused slots set to joint 0, so every index is
    valid) and weights normalised to sum 1 per vertex."""
    if joint_count > MAX_JOINTS:
        raise SceneFormatError(f"{where}: {joint_count} joints, more than the {MAX_JOINTS} supported")
    if joint_count == 0:
        raise SceneFormatError(f"{where}: skin has no joints")
    if joints.shape != weights.shape or joints.shape[1:] != (4,):
        raise SceneFormatError(f"{where}: joints and weights must both be (V, 4)")
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise SceneFormatError(f"{where}: weights must be finite and >= 0")
    used = weights > 0
    if (joints[used] < 0).any() or (joints[used] >= joint_count).any():
        raise SceneFormatError(f"{where}: a vertex refers to a joint outside 0..{joint_count - 1}")
    total = weights.sum(axis=1, keepdims=True)
    if (total <= 0).any():
        raise SceneFormatError(f"{where}: {int((total <= 0).sum())} vertices have all weights zero")
    return np.where(used, joints, 0).astype(np.int64), weights / total


@dataclass
class Channel:
    node: int
    path: str  # "translation" | "rotation" | "scale"
    times: np.ndarray  # (K,) strictly increasing
    values: np.ndarray  # (K, C) or (K, 3, C) for CUBICSPLINE (in-tangent, value, out-tangent)
    interpolation: str  # "LINEAR" | "STEP" | "CUBICSPLINE"

    def sample(self, t: float) -> np.ndarray:
        times, k = self.times, len(self.times)
        if k == 1 or t <= times[0]:
            return self._value(0)
        if t >= times[-1]:
            return self._value(k - 1)
        i = int(np.searchsorted(times, t, side="right") - 1)
        if self.interpolation == "STEP":
            return self._value(i)
        dt = times[i + 1] - times[i]
        u = (t - times[i]) / dt
        if self.interpolation == "CUBICSPLINE":
            p0, m0 = self.values[i, 1], self.values[i, 2] * dt
            p1, m1 = self.values[i + 1, 1], self.values[i + 1, 0] * dt
            v = ((2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * m0
                 + (-2 * u**3 + 3 * u**2) * p1 + (u**3 - u**2) * m1)
            return v / np.linalg.norm(v) if self.path == "rotation" else v
        a, b = self.values[i], self.values[i + 1]
        return slerp(a, b, u) if self.path == "rotation" else a + (b - a) * u

    def _value(self, i: int) -> np.ndarray:
        return self.values[i, 1] if self.interpolation == "CUBICSPLINE" else self.values[i]


@dataclass
class NodeAnimator:
    """Joint matrices from a node hierarchy: rest TRS per node, animated by channels, looping.
    Works for glTF skins and for the procedural ones alike (parents as indices, -1 for roots)."""
    parents: np.ndarray  # (N,) int, parents before children
    rest_translation: np.ndarray  # (N, 3)
    rest_rotation: np.ndarray  # (N, 4) (x, y, z, w)
    rest_scale: np.ndarray  # (N, 3)
    rest_matrix: list  # per node: a fixed (4, 4) local matrix (glTF `matrix` nodes) or None
    joint_nodes: np.ndarray  # (J,) node index of each joint
    channels: list[Channel]
    duration: float  # seconds; time loops with this period (0: static)
    root: np.ndarray = field(default_factory=lambda: np.eye(4))  # applied above the root nodes

    def __post_init__(self):
        self.order = topological_order(self.parents)

    def local_matrices(self, t: float) -> np.ndarray:
        t = t % self.duration if self.duration > 0 else 0.0
        tr, rot, sc = self.rest_translation.copy(), self.rest_rotation.copy(), self.rest_scale.copy()
        for c in self.channels:
            v = c.sample(t)
            {"translation": tr, "rotation": rot, "scale": sc}[c.path][c.node] = v
        m = np.zeros((len(tr), 4, 4))
        m[:, :3, :3] = quat_to_matrix(rot) * sc[:, None, :]
        m[:, :3, 3] = tr
        m[:, 3, 3] = 1.0
        for n, fixed in enumerate(self.rest_matrix):
            if fixed is not None and not any(c.node == n for c in self.channels):
                m[n] = fixed
        return m

    def rest_joint_matrices(self) -> np.ndarray:
        """(J, 4, 4) joint matrices of the rest pose (node TRS without any animation)."""
        channels, self.channels = self.channels, []
        try:
            return self.joint_matrices(0.0)
        finally:
            self.channels = channels

    def joint_matrices(self, t: float) -> np.ndarray:
        local = self.local_matrices(t)
        world = np.empty_like(local)
        for n in self.order:
            p = self.parents[n]
            world[n] = (self.root if p < 0 else world[p]) @ local[n]
        return world[self.joint_nodes]


def topological_order(parents: np.ndarray) -> list[int]:
    """Node indices with every parent before its children."""
    children: dict[int, list[int]] = {}
    for n, p in enumerate(parents):
        children.setdefault(int(p), []).append(n)
    order, stack = [], list(reversed(children.get(-1, [])))
    while stack:
        n = stack.pop()
        order.append(n)
        stack.extend(reversed(children.get(n, [])))
    return order


def skin_from_gltf(g, skin_index: int, joints: np.ndarray, weights: np.ndarray, animation: int | str = 0) -> Skin:
    """The Skin of glTF skin `skin_index` for a mesh's (V, 4) joints/weights (already in Mesh.vertices
    order), animated by glTF animation `animation`, an index or a name (static when the file has none)."""
    doc = g.doc
    skin = doc.skins[skin_index]
    name = skin.name or f"skin{skin_index}"
    where = f"{g.path}: skin '{name}'"
    joint_nodes = np.asarray(skin.joints or [], dtype=np.int64)
    if len(joint_nodes) > MAX_JOINTS:
        raise SceneFormatError(f"{where}: {len(joint_nodes)} joints, more than the {MAX_JOINTS} supported")
    if len(joint_nodes) and (joint_nodes.min() < 0 or joint_nodes.max() >= len(doc.nodes)):
        raise SceneFormatError(f"{where}: a joint refers to a missing node")
    joints, weights = check_skin(joints, weights, len(joint_nodes), where)
    if skin.inverseBindMatrices is not None:
        ibm = g.accessor(skin.inverseBindMatrices, f"skin '{name}' inverseBindMatrices").astype(np.float64)
        if len(ibm) != len(joint_nodes) or not np.isfinite(ibm).all():
            raise SceneFormatError(f"{where}: inverseBindMatrices must be {len(joint_nodes)} finite matrices")
        ibm = ibm.reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major in the file
    else:
        ibm = np.tile(np.eye(4), (len(joint_nodes), 1, 1))
    animator = gltf_node_animator(g, joint_nodes, gltf_animation_index(g, animation))
    names = [doc.nodes[j].name or f"node{j}" for j in joint_nodes]
    return Skin(inverse_bind=ibm, joints=joints, weights=weights, animator=animator, joint_names=names)


def gltf_animation_index(g, animation: int | str) -> int:
    """Index of a glTF animation given by index or name; -1 (static) when the file has none."""
    anims = g.doc.animations or []
    names = [a.name or f"animation{k}" for k, a in enumerate(anims)]
    if isinstance(animation, str):
        if animation not in names:
            raise SceneFormatError(f"{g.path}: no animation '{animation}' (has: {', '.join(names) or 'none'})")
        return names.index(animation)
    if not anims and animation == 0:
        return -1
    if not 0 <= animation < len(anims):
        raise SceneFormatError(f"{g.path}: no animation {animation} (has {len(anims)})")
    return int(animation)


def gltf_node_animator(g, joint_nodes: np.ndarray, animation: int) -> NodeAnimator:
    doc = g.doc
    n = len(doc.nodes)
    parents = np.full(n, -1, dtype=np.int64)
    for i, node in enumerate(doc.nodes):
        for c in node.children or []:
            if not 0 <= c < n:
                raise SceneFormatError(f"{g.path}: node {i} has a missing child {c}")
            parents[c] = i
    tr, rot, sc, fixed = np.zeros((n, 3)), np.tile([0.0, 0, 0, 1], (n, 1)), np.ones((n, 3)), [None] * n
    for i, node in enumerate(doc.nodes):
        if node.matrix is not None and len(node.matrix) == 16:
            fixed[i] = np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T
        tr[i] = node.translation if node.translation is not None else 0.0
        rot[i] = node.rotation if node.rotation is not None else [0, 0, 0, 1]
        sc[i] = node.scale if node.scale is not None else 1.0
    channels: list[Channel] = []
    duration = 0.0
    if doc.animations and 0 <= animation < len(doc.animations):
        channels, duration = gltf_channels(g, animation)
    return NodeAnimator(parents=parents, rest_translation=tr, rest_rotation=rot, rest_scale=sc, rest_matrix=fixed,
                        joint_nodes=joint_nodes, channels=channels, duration=duration)


_CHANNEL_WIDTH = {"translation": 3, "rotation": 4, "scale": 3}


def gltf_channels(g, animation: int) -> tuple[list[Channel], float]:
    """Channels of glTF animation `animation` that drive TRS, validated; and its duration."""
    doc = g.doc
    anim = doc.animations[animation]
    aname = anim.name or f"animation{animation}"
    out, duration = [], 0.0
    for ci, ch in enumerate(anim.channels):
        where = f"{g.path}: animation '{aname}' channel {ci}"
        target = ch.target
        if target is None or target.node is None or not 0 <= target.node < len(doc.nodes):
            raise SceneFormatError(f"{where}: targets a missing node {getattr(target, 'node', None)}")
        if target.path not in _CHANNEL_WIDTH:
            continue  # morph target weights: not supported, and they do not move joints
        if ch.sampler is None or not 0 <= ch.sampler < len(anim.samplers):
            raise SceneFormatError(f"{where}: refers to a missing sampler {ch.sampler}")
        sampler = anim.samplers[ch.sampler]
        interp = sampler.interpolation or "LINEAR"
        if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise SceneFormatError(f"{where}: unknown interpolation '{interp}'")
        times = g.accessor(sampler.input, where).reshape(-1).astype(np.float64)
        values = g.accessor(sampler.output, where).astype(np.float64)
        width = _CHANNEL_WIDTH[target.path]
        per_key = 3 if interp == "CUBICSPLINE" else 1
        if values.size != len(times) * per_key * width:
            raise SceneFormatError(f"{where}: {values.size} output values for {len(times)} keyframes")
        values = values.reshape(len(times), per_key, width) if per_key == 3 else values.reshape(len(times), width)
        if len(times) == 0 or not np.isfinite(times).all() or not np.isfinite(values).all():
            raise SceneFormatError(f"{where}: keyframes are empty or not finite")
        if (np.diff(times) <= 0).any():
            raise SceneFormatError(f"{where}: keyframe times are not strictly increasing")
        out.append(Channel(target.node, target.path, times, values, interp))
        duration = max(duration, float(times[-1]))
    return out, duration


@dataclass
class TimeShift:
    """Another animator, `offset` seconds ahead: several characters from one file out of step."""
    inner: JointAnimator
    offset: float  # seconds

    @property
    def duration(self) -> float:
        return getattr(self.inner, "duration", 0.0)

    def joint_matrices(self, t: float) -> np.ndarray:
        return self.inner.joint_matrices(t + self.offset)

    def rest_joint_matrices(self) -> np.ndarray:
        return self.inner.rest_joint_matrices()


# A glTF mesh's vertices are in bind space; when every joint's rest-pose matrix times its inverse bind
# matrix is the same B (the file was bound in its rest pose, the usual case), B @ v is the rest pose in
# the file's world space. Storing that as Mesh.vertices (and inverse_bind @ B^-1) gives static
# consumers (bounds, bakes, the rasteriser) the right geometry and leaves the skinned result unchanged.
REST_POSE_TOLERANCE = 1e-4  # max |B_k - B_0| relative to |B_0|, float32 files reach about 1e-5


def rebase_to_rest_pose(mesh) -> bool:
    """Move a skinned mesh from bind space to its rest pose (see above); False when joints disagree."""
    skin = mesh.skin
    b = skin.animator.rest_joint_matrices() @ skin.inverse_bind
    if np.abs(b - b[0]).max() > REST_POSE_TOLERANCE * max(1.0, np.abs(b[0]).max()):
        log.warning("%s: skin bound away from its rest pose: vertices stay in bind space", mesh.name)
        return False
    b0 = b[0]
    if abs(np.linalg.det(b0[:3, :3])) < 1e-12:
        return False
    mesh.vertices = mesh.vertices @ b0[:3, :3].T + b0[:3, 3]
    if np.linalg.det(b0[:3, :3]) < 0:
        mesh.faces = mesh.faces[:, ::-1].copy()
    skin.inverse_bind = skin.inverse_bind @ np.linalg.inv(b0)
    return True
