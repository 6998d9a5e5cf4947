"""Typed reading of TOML tables: every getter raises SceneFormatError naming the element."""
from __future__ import annotations

import math

import numpy as np

from psao.scene.errors import SceneFormatError
from psao.scene.transforms import rotation_axis_angle, rotation_xyz

class Table:
    """One TOML table being read: typed getters that raise SceneFormatError naming `where`."""

    def __init__(self, data, where: str, allowed: set[str]):
        if not isinstance(data, dict):
            raise SceneFormatError(f"{where}: expected a table")
        unknown = sorted(set(data) - allowed)
        if unknown:
            raise SceneFormatError(f"{where}: unknown key '{unknown[0]}' (allowed: {', '.join(sorted(allowed))})")
        self.data, self.where = data, where

    def fail(self, msg: str) -> SceneFormatError:
        return SceneFormatError(f"{self.where}: {msg}")

    def has(self, key: str) -> bool:
        return key in self.data

    def text(self, key: str, default: str | None = None) -> str:
        v = self.data.get(key, default)
        if not isinstance(v, str) or not v:
            raise self.fail(f"'{key}' must be a non-empty string")
        return v

    def flag(self, key: str, default: bool) -> bool:
        v = self.data.get(key, default)
        if not isinstance(v, bool):
            raise self.fail(f"'{key}' must be true or false")
        return v

    def number(self, key: str, default: float | None = None, positive: bool = False) -> float:
        v = self.data.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(f"'{key}' must be a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.fail(f"'{key}' must be > 0, got {v!r}")
        return float(v)

    def vec(self, key: str, n: int = 3, default=None) -> np.ndarray:
        v = self.data.get(key, default)
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise self.fail(f"'{key}' must be a list of {n} finite numbers, got {v!r}")
        return np.asarray(v, dtype=np.float64)

    def tables(self, key: str) -> list:
        v = self.data.get(key, [])
        if not isinstance(v, list):
            raise self.fail(f"'{key}' must be an array of tables ([[{key}]])")
        return v


def rotation_of(t: Table) -> np.ndarray:
    r = t.data.get("rotate", [0, 0, 0])
    if isinstance(r, dict):
        rt = Table(r, f"{t.where}: rotate", {"axis", "angle"})
        axis = rt.vec("axis")
        if np.linalg.norm(axis) == 0:
            raise rt.fail("'axis' must not be zero")
        return rotation_axis_angle(axis, rt.number("angle"))
    return rotation_xyz(t.vec("rotate", 3, [0, 0, 0]))


def scale_of(t: Table) -> np.ndarray:
    s = t.data.get("scale", 1.0)
    v = np.full(3, t.number("scale", 1.0)) if not isinstance(s, list) else t.vec("scale")
    if np.any(v == 0):
        raise t.fail(f"'scale' must not be zero, got {s!r}")
    return v
