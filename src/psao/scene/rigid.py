"""Rigid motions of instances (Instance.animation, a RigidAnimation).

`matrix(t)` is the instance's local-to-world 4x4 at time t seconds; Instance.transform holds matrix(0).
Every animation keeps the instance's rest transform `base` (its TOML translate/rotate/scale) and moves it:

    keyframes  world(t) = T(translate(t)) * T(o) R(rotation(t)) S(scale(t)) T(-o) * base, o = base origin:
               keys rotate and scale the object about its own origin; translation linear, rotation slerp
    roll       a ball of `radius` rolling without slipping along a polyline of centre positions on the
               floor (x, z), at `speed`: translation plus rotation s / radius about (up x direction)
    path       walks a polyline at `speed`, turning to face along it (yaw): for characters
    swing      pendulum: rotation about `axis` through `pivot` by amplitude * sin(2 pi t / period + phase)
    platform   back and forth: translation offset * (1 - cos(2 pi t / period + phase)) / 2

Reading them from TOML is toml_animation.py.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from psao.scene.transforms import (axis_angle_matrix, placed_about, quat_mul, quat_pow, quat_to_matrix, slerp,
                         translation_matrix, yaw_matrix)

UP = np.array([0.0, 1.0, 0.0])


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
        origin = self.base[:3, 3]
        return placed_about(translate + origin, quat_to_matrix(slerp(a.rotation, b.rotation, u)) * scale[None, :], origin)


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
        self._starts = self.starts.tolist()  # (bisect on Python floats: a mover locates itself every tick)

    def locate(self, s: float) -> tuple[int, float]:
        """Segment index and distance into it for arc length s in [0, length]."""
        i = min(max(bisect.bisect_right(self._starts, s) - 1, 0), len(self.lengths) - 1)
        return i, s - self._starts[i]

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
        # per segment: the unit axis it rolls about (None: a vertical segment, no rolling)
        self._axes = []
        for d in self.path.dirs:
            axis = np.cross(UP, d)
            norm = float(np.linalg.norm(axis))
            self._axes.append(None if norm < 1e-12 else axis / norm)
        segs = [self._segment_quat(i, self.path.lengths[i]) for i in range(len(self.path.lengths))]
        self._prefix = [np.array([0.0, 0.0, 0.0, 1.0])]  # orientation at the start of each segment
        for q in segs:
            self._prefix.append(quat_mul(q, self._prefix[-1]))

    def _segment_quat(self, i: int, dist: float) -> np.ndarray:
        """Unit quaternion (w >= 0) of the rotation about segment i's axis by dist / radius (scalar math:
        this runs for every moving instance at every tick)."""
        axis = self._axes[i]
        if axis is None:
            return np.array([0.0, 0.0, 0.0, 1.0])
        half = 0.5 * dist / self.radius
        s, c = math.sin(half), math.cos(half)
        if c < 0:
            s, c = -s, -c
        return np.array([axis[0] * s, axis[1] * s, axis[2] * s, c])

    def _orientation(self, s: float, laps: int) -> np.ndarray:
        i, into = self.path.locate(s)
        q = quat_mul(self._segment_quat(i, into), self._prefix[i])
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
        return placed_about(centre, rot, origin)


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
        return placed_about(pos, yaw_matrix(math.atan2(d[0], d[2])), self.base[:3, 3])


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
        return placed_about(self.pivot, axis_angle_matrix(self.axis, angle), self.pivot)


@dataclass
class PlatformAnimation(RigidAnimation):
    offset: np.ndarray = None  # (3,) world displacement at the far end
    period: float = 4.0  # seconds for there and back
    phase: float = 0.0  # degrees

    kind = "platform"

    def motion(self, t: float) -> np.ndarray:
        f = 0.5 * (1 - math.cos(2 * math.pi * t / self.period + math.radians(self.phase)))
        return translation_matrix(self.offset * f)


@dataclass
class PartAnimation:
    """A part of a composed object moved with the whole: world(t) = whole.matrix(t) @ part, `part` the
    part's fixed transform inside the object (a TOML [[instance]] of a mesh file of several parts)."""
    whole: RigidAnimation
    part: np.ndarray  # (4, 4)

    @property
    def kind(self) -> str:
        return self.whole.kind

    def matrix(self, t: float) -> np.ndarray:
        return self.whole.matrix(t) @ self.part


def instance_transform(scene, i: int, t: float) -> np.ndarray:
    """Local-to-world 4x4 of instance i at time t seconds."""
    inst = scene.instances[i]
    return inst.transform if inst.animation is None else inst.animation.matrix(t)


def is_dynamic(scene, i: int) -> bool:
    """Whether instance i moves (rigid animation) or deforms (skinned mesh)."""
    inst = scene.instances[i]
    return inst.animation is not None or scene.meshes[inst.mesh].skin is not None
