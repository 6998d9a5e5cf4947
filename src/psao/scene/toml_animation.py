"""`[instance.animation]` tables of TOML scenes (schema in tomlscene.py) -> rigid animations (rigid.py)."""
from __future__ import annotations

import math

import numpy as np

from psao.scene.errors import SceneFormatError
from psao.scene.rigid import (KeyframeAnimation, PathAnimation, PlatformAnimation, Polyline, RigidAnimation, RigidKey,
                    RollAnimation, SwingAnimation)
from psao.scene.toml_fields import Table, rotation_of, scale_of
from psao.scene.transforms import matrix_to_quat

def parse_animation(data, where: str, base: np.ndarray) -> RigidAnimation:
    """An `[instance.animation]` table (schema in tomlscene.py); errors name `where`."""
    kinds = {"keyframes": ({"key", "loop"}, _parse_keyframes), "roll": ({"path", "speed", "radius", "loop"}, _parse_roll),
             "path": ({"path", "speed", "loop"}, _parse_path), "swing": ({"pivot", "axis", "amplitude", "period", "phase"}, _parse_swing),
             "platform": ({"offset", "period", "phase"}, _parse_platform)}
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind not in kinds:
        raise SceneFormatError(f"{where}: 'kind' must be one of {', '.join(kinds)}, got {kind!r}")
    allowed, parse = kinds[kind]
    return parse(Table(data, where, allowed | {"kind"}), np.asarray(base, dtype=np.float64))


def _parse_keyframes(t, base) -> KeyframeAnimation:
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
