"""Deterministic cosine-weighted ray directions per point, and robust ray origins.

A point's K directions are a stratified 2D set (u1 = (j + 0.5) / K, u2 = frac(j * golden ratio)) under a
Cranley-Patterson rotation drawn from a hash of the point's stable id and the seed. So the same point
gets the same rays every tick (unchanged geometry gives unchanged AO, hence no spurious updates), and
neighbouring points get decorrelated rays (their errors average out in the reconstruction).
A slice (`first`, `step`: rays j = first, first + step, ...) of a point's K-ray set is a stratified subset of
it, and the `step` slices of one set are together exactly that set: a trace spread over several rounds,
one slice each, counts the same rays as one full trace.
The Warp back-end implements the same arithmetic in its kernel.
"""
from __future__ import annotations

import numpy as np

GOLDEN = np.float32(0.6180339887498949)
OFFSET_REL = np.float32(2.0 ** -18)  # origin offset per unit of coordinate magnitude (~32 float32 ulps)
OFFSET_AO = np.float32(1e-4)  # origin offset per unit of AO distance


def pcg_hash(v: np.ndarray) -> np.ndarray:
    """PCG-RXS-M-XS 32-bit hash in wrapping uint32 arithmetic (computed in uint64, masked)."""
    m = np.uint64(0xFFFFFFFF)
    state = (np.asarray(v, np.uint64) * np.uint64(747796405) + np.uint64(2891336453)) & m
    word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state) * np.uint64(277803737)) & m
    return ((word >> np.uint64(22)) ^ word).astype(np.uint32)


def rotation_of(point_ids: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-point Cranley-Patterson offsets in [0, 1)."""
    ids = np.asarray(point_ids, np.int64).astype(np.uint64) & np.uint64(0xFFFFFFFF)
    h1 = pcg_hash(ids ^ np.uint64(seed & 0xFFFFFFFF))
    h2 = pcg_hash(h1.astype(np.uint64) ^ np.uint64(0x9E3779B9))
    scale = np.float32(1.0 / 4294967296.0)
    return h1.astype(np.float32) * scale, h2.astype(np.float32) * scale


def tangent_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Branchless orthonormal basis (Duff et al. 2017) for unit normals (P, 3)."""
    sign = np.where(n[:, 2] >= 0, np.float32(1.0), np.float32(-1.0))
    a = np.float32(-1.0) / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] * n[:, 0] * a, sign * b, -sign * n[:, 0]], axis=1).astype(np.float32)
    bt = np.stack([b, sign + n[:, 1] * n[:, 1] * a, -n[:, 1]], axis=1).astype(np.float32)
    return t, bt


def slice_count(first, rays: int, step: int) -> int:
    """Rays per point of the slice j = first, first + step, ... of a `rays`-ray set (`first` one int or
    one per point, all below `step`; per-point slices need `step` to divide `rays`)."""
    first = np.asarray(first)
    if first.ndim and len(first) and rays % step:
        raise ValueError(f"per-point slices need equal sizes: {step} slices do not divide {rays} rays")
    return len(range(int(first.max(initial=0)), rays, step))


def cosine_directions(point_ids: np.ndarray, normals: np.ndarray, rays: int, seed: int = 0, first=0,
                      step: int = 1) -> np.ndarray:
    """(P, K', 3) float32 world directions, cosine-distributed about each normal: rays j = first, first +
    step, ... below `rays` of the K-ray set (all K of them by default). `first` may differ per point
    ((P,) ints, all below `step`, and `step` dividing `rays` so every point gets K' = rays / step)."""
    n = np.asarray(normals, np.float32)
    first = np.asarray(first, np.int64)
    count = slice_count(first, rays, step)
    j = (first[..., None] + step * np.arange(count)).astype(np.float32)
    if j.ndim == 1:
        j = j[None, :]
    u1 = (j + np.float32(0.5)) / np.float32(rays)
    u2 = np.mod(j * GOLDEN, np.float32(1.0))
    a, b = rotation_of(point_ids, seed)
    u1 = np.mod(u1 + a[:, None], np.float32(1.0))
    u2 = np.mod(u2 + b[:, None], np.float32(1.0))
    r = np.sqrt(u1)
    phi = np.float32(2.0 * np.pi) * u2
    lx, ly = r * np.cos(phi), r * np.sin(phi)
    lz = np.sqrt(np.maximum(np.float32(0.0), np.float32(1.0) - u1))
    t, bt = tangent_frame(n)
    d = lx[..., None] * t[:, None, :] + ly[..., None] * bt[:, None, :] + lz[..., None] * n[:, None, :]
    return d.astype(np.float32)


def ray_origins(positions: np.ndarray, normals: np.ndarray, ao_distance: float) -> np.ndarray:
    """Offset along the normal by an epsilon that grows with the coordinates' magnitude (float32 spacing)
    and with the scene's scale (AO distance), so neither far-from-origin nor tiny scenes self-intersect."""
    p = np.asarray(positions, np.float32)
    eps = OFFSET_REL * np.abs(p).max(axis=1) + OFFSET_AO * np.float32(ao_distance)
    return (p + np.asarray(normals, np.float32) * eps[:, None]).astype(np.float32)
