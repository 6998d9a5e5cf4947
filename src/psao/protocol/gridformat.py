"""Grid layout shared by server, wire, client mirror, Warp kernels and GLSL (DESIGN.md, "Formats").

Memory (all uint32 unless said otherwise):

    cells    (n_slots, 8)       words 0-6 point words (allocated first), word 7 the cell key
    buckets  (n_buckets, 8, 2)  entries (key, slot); empty entry = (EMPTY, EMPTY); used entries first,
                                a key's entries next to each other
    instances INSTANCE_DTYPE    one record per mesh instance, 48 bytes, std430-compatible (3 x 16 bytes)

A free cell slot holds FREE_CELL (all points zero, key EMPTY). The key of a cell is its linear index
`x + Dx * (y + Dy * z)` in the instance's dense virtual grid; the bucket of a cell is
`hash(x, y, z) & (B - 1)` offset by the instance's first bucket. Double-sided instances keep the points of
the back side in cells of their own, whose key has BACK_BIT set (same bucket as the front cell): both
sides of a thin surface share space, and sharing cells would halve what a cell holds per side. The
lookup at a fragment reads one key per cell: the back-side key where the G-buffer flags the fragment as
the back side of a double-sided instance, else the front key. Where more than 7 points fall in one cell
(surfaces crossing, thin parts with two faces close together) the key takes further cells, up to KEY_CELLS:
further entries of its bucket with the same key, next to each other (the server keeps every bucket's
entries sorted by key), and the lookup reads them from the key's first entry on, where the paper drops
what does not fit. Points are stored in instance-local space:
a point word's 5-bit codes q give the local position `origin + (cell + (q + 0.5) / 32) * cell_size`.

The lookup thresholds T_N and T_D (paper eq. 3) live here too: the oracle (reconstruct.py), the gap fill
and the shader (through shader_constants.py) read them from this module.
"""
from __future__ import annotations

import math

import numpy as np

from psao.protocol import pointword as pw

CELL_WORDS = 8
POINTS_PER_CELL = 7
KEY_WORD = 7
BUCKET_ENTRIES = 8
# A cell key whose points do not fit one cell takes up to this many cells (consecutive entries of its
# bucket with the same key); the lookup reads them all. Beyond it points are dropped.
KEY_CELLS = 3
EMPTY = np.uint32(0xFFFFFFFF)
MAX_DIM = 1 << 10  # per axis; Dx * Dy * Dz <= 2^30 keeps keys below BACK_BIT
BACK_BIT = np.uint32(1 << 30)  # key flag: the cell holds back-side points of a double-sided instance
KEY_MASK = np.uint32((1 << 30) - 1)
HASH_Y = 17  # paper eq. 1: hash = x + y * Dx * HASH_Y + z * Dx * Dy * HASH_Z
HASH_Z = 31

# Paper eq. 3: a point counts at a fragment only if n_p . n_x > T_N and (n_p . (p - x) / |p - x|)^2 < T_D.
T_N = 0.1  # normal threshold (cosine; paper value)
T_D = 0.7  # distance-direction threshold (squared cosine; paper value)
# The first step (radius r) takes only the fragment's own face: n_p . n_x > FIRST_T_N (within about 18
# degrees, just wider than the octahedral normals' worst quantisation error of 17.1) and a point close to
# the fragment's tangent plane, (n_p . (p - x))^2 < FIRST_T_D |p - x|^2 (more than about 67 degrees from
# the normal). Near a crease, a step or a moulding the points of the other surface differ in AO more than
# anything within r on the same one, and eq. 3's T_N = 0.1 and T_D = 0.7 let them in.
FIRST_T_N = 0.95
FIRST_T_D = 0.15
# Where the first step finds no weight (a small face, a moulding narrower than r), the second step takes
# the block's points at radius FALLBACK_SCALE * r whose normal is within about 26 degrees (SECOND_T_N) of
# the fragment's, and only where that has none either the third step takes eq. 3 alone at that radius, so
# no fragment loses the points it found before. On Sponza's probes (8192-ray truth) the three steps take
# the MAE from 0.0276 to 0.0259 at the default points.
SECOND_T_N = 0.9
# Weights are max(0, 1 - d / rho) to this power (paper eq. 2: 1). Squared weights helped only on densified
# grids (Sponza with --densify 5: 0.0199 -> 0.0190) and hurt at the default points (0.0259 -> 0.0264) and
# with few rays per point, where averaging more neighbours cancels more noise (bunny at 16 rays per point:
# 0.026 -> 0.029), so the paper's power stays.
WEIGHT_POWER = 1
# The radius of the second and third steps is r times this; where those have no weight either, the 3x3x3
# block around the fragment's cell takes that radius (every point within one cell, s >= 2 r, lies in it).
FALLBACK_SCALE = 2.0
# The 3x3x3 ring answers only where nothing else did, mostly on small faces at sharp edges whose points all
# went to their neighbours: it keeps eq. 3's tangent-plane test but takes points whose normal is up to
# 120 degrees from the fragment's (cosine > RING_T_N), the faces across such an edge, rather than AO = 1.
# The back of a thin wall (cosine near -1) still does not count.
RING_T_N = -0.5
# The ring's radius is r times this (1.5 cells, as cell_size = 2 r): it takes the ring's points farther than
# the 2r steps reach, so a fragment beside a patch its own surface has no points on (a contact line where
# the points under another object were left out, a thin Poisson gap) still finds the surface around it.
# The 3x3x3 block reaches at least one cell (2 r) from the fragment on every side, so the ring holds every
# point within 2 r and only some of those between 2 r and 3 r. On Sponza's 15,662 visible probes, with the
# detail levels of src/psao/server/points/sampling.py, 6 holes are left where a ring of 2 r left 26 (AO 1 where the
# truth was about 0.3).
RING_SCALE = 3.0

FREE_CELL = np.array([0] * POINTS_PER_CELL + [0xFFFFFFFF], dtype=np.uint32)
EMPTY_BUCKET = np.full((BUCKET_ENTRIES, 2), 0xFFFFFFFF, dtype=np.uint32)

# Instance flags.
FLAG_DOUBLE_SIDED = 1 << 0

INSTANCE_DTYPE = np.dtype(
    [
        ("origin", "<f4", (3,)),  # local-space corner of cell (0, 0, 0)
        ("cell_size", "<f4"),  # local units
        ("dims", "<u4", (3,)),  # Dx, Dy, Dz
        ("bucket_offset", "<u4"),  # first bucket of this instance in the global bucket array
        ("bucket_count", "<u4"),  # B, a power of two
        ("radius", "<f4"),  # interpolation radius r, local units; cell_size >= 2 r
        ("flags", "<u4"),
        ("pad", "<u4"),
    ]
)
assert INSTANCE_DTYPE.itemsize == 48


def _xyz_dims(x, y, z, dims):
    """Cell coordinates and Dx, Dy as uint64; dims is (3,) or (..., 3), broadcast against x, y, z."""
    dims = np.asarray(dims, dtype=np.uint64)
    x, y, z = (np.asarray(v, dtype=np.uint64) for v in (x, y, z))
    return x, y, z, dims[..., 0], dims[..., 1]


def cell_hash(x: np.ndarray, y: np.ndarray, z: np.ndarray, dims) -> np.ndarray:
    """Paper eq. 1 in wrapping uint32 arithmetic, as GLSL's uint does: x + y*Dx*17 + z*Dx*Dy*31."""
    x, y, z, dx, dy = _xyz_dims(x, y, z, dims)
    m = np.uint64(0xFFFFFFFF)
    h = (x + ((y * ((dx * np.uint64(HASH_Y)) & m)) & m) + ((z * ((dx * dy * np.uint64(HASH_Z)) & m)) & m)) & m
    return h.astype(np.uint32)


def bucket_index(x, y, z, dims, bucket_offset, bucket_count) -> np.ndarray:
    """Global bucket index of cells (x, y, z) of an instance; dims (3,) or (..., 3), bucket_offset and
    bucket_count (B, a power of two) scalars or arrays broadcast like x."""
    mask = np.asarray(bucket_count, dtype=np.uint32) - np.uint32(1)
    return ((cell_hash(x, y, z, dims) & mask) + np.asarray(bucket_offset, dtype=np.uint32)).astype(np.uint32)


def cell_key(x, y, z, dims) -> np.ndarray:
    """Front key of cells (x, y, z): x + Dx * (y + Dy * z); dims (3,) or (..., 3) broadcast like x."""
    x, y, z, dx, dy = _xyz_dims(x, y, z, dims)
    return ((x + dx * (y + dy * z)) & np.uint64(0xFFFFFFFF)).astype(np.uint32)


def key_to_cell(key, dims) -> np.ndarray:
    key = np.asarray(key, dtype=np.uint64) & np.uint64(int(KEY_MASK))
    dx, dy = np.uint64(int(dims[0])), np.uint64(int(dims[1]))
    return np.stack([key % dx, (key // dx) % dy, key // (dx * dy)], axis=-1).astype(np.int64)


def poisson_radius(area: float, n_points: int) -> float:
    """Poisson disk radius of n points on area A (Yuksel 2015, 2D): sqrt(A / (2 sqrt(3) n))."""
    return math.sqrt(area / (2.0 * math.sqrt(3.0) * max(int(n_points), 1)))


def next_pow2(n: int) -> int:
    return 1 << max(0, int(math.ceil(math.log2(max(int(n), 1)))))


def grid_coords(local_pos: np.ndarray, origin: np.ndarray, cell_size: float) -> np.ndarray:
    """Local positions -> continuous grid coordinates g, in cells (float64 for exact floor on faces)."""
    return (np.asarray(local_pos, dtype=np.float64) - np.asarray(origin, dtype=np.float64)) / float(cell_size)


def lookup_block_base(g: np.ndarray) -> np.ndarray:
    """First cell of the 2x2x2 block around grid coordinate g: floor(g - 0.5). Every point within r of the
    fragment lies in that block because cell_size >= 2 r."""
    return np.floor(np.asarray(g) - 0.5).astype(np.int64)


def passes_thresholds(ndot, ddot, dist2, t_n, t_d) -> np.ndarray:
    """Paper eq. 3 with normal threshold t_n and tangent-plane threshold t_d, as the shader writes it (no
    division): n_p . n_x > t_n and (n_p . d)^2 < t_d |d|^2, true at d = 0. ndot = n_p . n_x, ddot = n_p . d,
    dist2 = |d|^2 for d = p - x; arrays broadcast, float32 stays float32 when t_n and t_d are float32."""
    return (ndot > t_n) & ((ddot * ddot < t_d * dist2) | (dist2 == 0))


def in_first_step(ndot, ddot, dist2, radius) -> np.ndarray:
    """The lookup's first step counts the point: within `radius` (r, the units of dist2's square root) and
    on the fragment's own face (FIRST_T_N, FIRST_T_D). The oracle's tent weight, zero from r on, stands for
    its radius test; the GLSL writes the same test itself (shader-equals-oracle tests hold them equal)."""
    return passes_thresholds(ndot, ddot, dist2, FIRST_T_N, FIRST_T_D) & (dist2 < radius * radius)


def decode_point_local(cell_xyz: np.ndarray, qpos: np.ndarray, origin, cell_size) -> np.ndarray:
    """Cell index (..., 3) and 5-bit codes (..., 3) -> local position (float32): the centre of the point's
    1/32 step of the cell (the lookup works with the same position in grid units, cell + (q + 0.5) / 32)."""
    f = pw.dequantise_cell_fraction(qpos)
    return np.asarray(origin, dtype=np.float32) + (np.asarray(cell_xyz, dtype=np.float32) + f) * np.asarray(cell_size, dtype=np.float32)
