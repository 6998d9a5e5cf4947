"""Spatial tiles for a sharded trace: the points split into boxes, each box with only the triangles its rays
can reach.

An AO ray leaves its point's origin (offset along the normal, directions.ray_origins) and stops at the AO
distance, so every triangle it can hit overlaps the box of the tile's points grown by the AO distance plus
the largest origin offset. A tile traced against just those triangles answers exactly as against the
whole scene: the triangles it keeps are a superset of those its rays can hit, and their vertices are the
same float32 values, copied, not recomputed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.server.tracer.directions import OFFSET_AO, OFFSET_REL

# Relative slack on the reach: covers float32 rounding of hit distances near the AO distance.
REACH_SLACK = 1e-3


@dataclass
class Tile:
    points: np.ndarray  # (P,) int64 indices into the traced points
    lo: np.ndarray  # (3,) float64 box of the triangles it needs: its points' box grown by the reach
    hi: np.ndarray


def split_points(positions: np.ndarray, max_points: int) -> list[np.ndarray]:
    """Index sets of at most `max_points` points each: halve along the longest axis of a set's box at the
    median until each part is small enough (a k-d split, so tiles stay compact on any layout)."""
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    p = np.asarray(positions)
    todo = [np.arange(len(p), dtype=np.int64)]
    out = []
    while todo:
        idx = todo.pop()
        if len(idx) <= max_points:
            if len(idx):
                out.append(idx)
            continue
        sub = p[idx]
        axis = int(np.argmax(sub.max(axis=0) - sub.min(axis=0)))
        half = len(idx) // 2
        order = np.argpartition(sub[:, axis], half)
        todo += [idx[order[half:]], idx[order[:half]]]
    return out


def ray_reach(positions: np.ndarray, ao_distance: float) -> float:
    """How far from its point a ray can hit: the AO distance plus the largest origin offset, with slack."""
    p = np.asarray(positions, np.float32)
    mag = float(np.abs(p).max()) if len(p) else 0.0
    offset = float(OFFSET_REL) * mag + float(OFFSET_AO) * ao_distance
    return (ao_distance + offset) * (1.0 + REACH_SLACK) + 1e-6


def make_tiles(positions: np.ndarray, ao_distance: float, max_points: int) -> list[Tile]:
    reach = ray_reach(positions, ao_distance)
    p = np.asarray(positions, np.float64)
    return [Tile(points=idx, lo=p[idx].min(axis=0) - reach, hi=p[idx].max(axis=0) + reach)
            for idx in split_points(positions, max_points)]


def triangle_boxes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) lower and upper corners of each triangle's box."""
    tri = np.asarray(vertices)[np.asarray(faces)]
    return tri.min(axis=1), tri.max(axis=1)


def cut_triangles(vertices: np.ndarray, faces: np.ndarray, boxes: tuple[np.ndarray, np.ndarray],
                  lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangles whose box overlaps [lo, hi], with only the vertices they use (values copied)."""
    tri_lo, tri_hi = boxes
    keep = np.all(tri_lo <= hi, axis=1) & np.all(tri_hi >= lo, axis=1)
    sub = np.asarray(faces)[keep]
    used, remap = np.unique(sub, return_inverse=True)
    return np.asarray(vertices)[used], remap.reshape(sub.shape).astype(np.int32)
