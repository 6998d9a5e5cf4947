"""The 32-bit point word and the 4+4-bit octahedral normal code (DESIGN.md, "Point word").

| bits       | meaning                                                         |
|------------|-----------------------------------------------------------------|
| 31         | allocated                                                       |
| 26-30      | z position in the cell, q = clamp(floor(f * 32), 0, 31)          |
| 21-25      | y position in the cell                                          |
| 16-20      | x position in the cell                                          |
| 8-15       | normal, octahedral, 4 bits u (high) and 4 bits v (low)           |
| 0-7        | AO as visibility: 255 unoccluded, 0 fully occluded               |

Everything here is vectorised numpy and mirrors `src/psao/protocol/shaders/psao_common.glsl` and the Warp kernels bit for
bit. The octahedral code uses the levels 0..14 (q = round(u * 7) + 7, decoded as (q - 7) / 7) so that
0 and +-1 are exact: the six axis normals, which dominate architectural scenes, round-trip exactly.
Level 15 is never written; the decoder clamps it to 14.
"""
from __future__ import annotations

import numpy as np

ALLOCATED_BIT = np.uint32(1 << 31)
POSITION_BITS = 5
POSITION_LEVELS = 1 << POSITION_BITS  # 32 steps per cell axis
OCT_LEVELS_HALF = 7  # u in [-1, 1] -> q in [0, 14]
AO_LEVELS = 255

SHIFT_X, SHIFT_Y, SHIFT_Z = 16, 21, 26  # first bit of each 5-bit position code
SHIFT_NORMAL = 8  # first bit of the 8-bit normal code (AO is bits 0-7)
POSITION_MASK = POSITION_LEVELS - 1
CODE_MASK = 0xFF  # the normal and the AO code are 8 bits each
NORMAL_CODES = 1 << 8  # oct codes a decoder table needs (levels 15 included, clamped)


def quantise_cell_fraction(frac: np.ndarray) -> np.ndarray:
    """Position inside the cell, f in [0, 1) per axis -> 5-bit code, clamped (points on faces stay inside)."""
    q = np.floor(np.asarray(frac, dtype=np.float64) * POSITION_LEVELS)
    return np.clip(q, 0, POSITION_LEVELS - 1).astype(np.uint32)


def dequantise_cell_fraction(q: np.ndarray) -> np.ndarray:
    """5-bit code -> position fraction at the centre of its step, (q + 0.5) / 32."""
    return (np.asarray(q, dtype=np.float32) + np.float32(0.5)) / np.float32(POSITION_LEVELS)


def oct_encode(normals: np.ndarray) -> np.ndarray:
    """Unit normals (..., 3) -> 8-bit octahedral codes (u high nibble, v low nibble), uint32."""
    n = np.asarray(normals, dtype=np.float64)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]  # per component: no reduction along the short last axis
    l1 = np.abs(x) + np.abs(y) + np.abs(z)
    l1 = np.where(l1 > 0, l1, 1.0)
    u, v = x / l1, y / l1
    # Lower hemisphere (z / l1 < 0, i.e. z < 0) folds over the diagonals; sign(0) counts as +1 (-0.0 + 0.0
    # is +0.0) so the fold is total.
    low = z < 0
    fu = np.where(low, np.copysign(1.0 - np.abs(v), u + 0.0), u)
    fv = np.where(low, np.copysign(1.0 - np.abs(u), v + 0.0), v)
    qu = np.clip(np.rint(fu * OCT_LEVELS_HALF) + OCT_LEVELS_HALF, 0, 2 * OCT_LEVELS_HALF).astype(np.uint32)
    qv = np.clip(np.rint(fv * OCT_LEVELS_HALF) + OCT_LEVELS_HALF, 0, 2 * OCT_LEVELS_HALF).astype(np.uint32)
    return (qu << 4) | qv


def oct_decode(code: np.ndarray) -> np.ndarray:
    """8-bit octahedral codes -> unit normals (..., 3), float32, exactly as the shader decodes them."""
    code = np.asarray(code, dtype=np.uint32)
    qu = np.minimum((code >> 4) & 0xF, 2 * OCT_LEVELS_HALF).astype(np.float32)
    qv = np.minimum(code & 0xF, 2 * OCT_LEVELS_HALF).astype(np.float32)
    u = (qu - OCT_LEVELS_HALF) / np.float32(OCT_LEVELS_HALF)
    v = (qv - OCT_LEVELS_HALF) / np.float32(OCT_LEVELS_HALF)
    z = np.float32(1.0) - np.abs(u) - np.abs(v)
    t = np.maximum(-z, np.float32(0.0))
    x = u + np.where(u >= 0, -t, t)
    y = v + np.where(v >= 0, -t, t)
    n = np.stack([x, y, z], axis=-1).astype(np.float32)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def quantise_ao(visibility: np.ndarray) -> np.ndarray:
    """Visibility in [0, 1] -> 8-bit code (255 unoccluded). NaN is treated as unoccluded, never stored."""
    v = np.nan_to_num(np.asarray(visibility, dtype=np.float64), nan=1.0)
    return np.clip(np.rint(v * AO_LEVELS), 0, AO_LEVELS).astype(np.uint32)


def dequantise_ao(code: np.ndarray) -> np.ndarray:
    return (np.asarray(code, dtype=np.uint32) & CODE_MASK).astype(np.float32) / np.float32(AO_LEVELS)


def pack_point(qpos: np.ndarray, normal_code: np.ndarray, ao_code: np.ndarray) -> np.ndarray:
    """qpos (..., 3) 5-bit codes, 8-bit normal and AO codes -> allocated point words (uint32)."""
    qpos = np.asarray(qpos, dtype=np.uint32)
    return (
        ALLOCATED_BIT
        | (qpos[..., 2] & POSITION_MASK) << SHIFT_Z
        | (qpos[..., 1] & POSITION_MASK) << SHIFT_Y
        | (qpos[..., 0] & POSITION_MASK) << SHIFT_X
        | (np.asarray(normal_code, dtype=np.uint32) & CODE_MASK) << SHIFT_NORMAL
        | (np.asarray(ao_code, dtype=np.uint32) & CODE_MASK)
    ).astype(np.uint32)


def unpack_point(words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Point words -> (allocated bool, qpos (..., 3), normal code, ao code)."""
    w = np.asarray(words, dtype=np.uint32)
    allocated = (w & ALLOCATED_BIT) != 0
    qpos = np.stack([(w >> SHIFT_X) & POSITION_MASK, (w >> SHIFT_Y) & POSITION_MASK, (w >> SHIFT_Z) & POSITION_MASK], axis=-1)
    return allocated, qpos.astype(np.uint32), (w >> SHIFT_NORMAL) & CODE_MASK, w & CODE_MASK


def with_ao(words: np.ndarray, ao_code: np.ndarray) -> np.ndarray:
    """Replace the AO byte of point words, keeping everything else."""
    w = np.asarray(words, dtype=np.uint32)
    return ((w & np.uint32(0xFFFFFF00)) | (np.asarray(ao_code, dtype=np.uint32) & CODE_MASK)).astype(np.uint32)
