"""Python oracle of the client's per-fragment AO lookup (DESIGN.md "AO at a fragment", paper eq. 2-4).

It reads exactly the arrays the client holds (instances, buckets, cells) and does exactly what
`src/psao/protocol/shaders/psao_lookup.glsl` does, vectorised over fragments: the 2x2x2 block floor(g - 0.5) + {0,1}^3,
hash -> bucket -> linear scan for the key's first entry -> the allocated points of its cell and of the
cells of the entries right after it with the same key (a key holding more than 7 points owns up to
KEY_CELLS consecutive entries of its bucket), points zeroed when n_p . n_x <= T_n or
(n_p . (p - x))^2 >= T_d |p - x|^2 (p != x), weights max(0, 1 - d / rho)^WEIGHT_POWER, and the
weighted mean of the first of three steps that finds weight: radius r with n_p . n_x > FIRST_T_N and
(n_p . (p - x))^2 < FIRST_T_D |p - x|^2 too; radius R = FALLBACK_SCALE * r with n_p . n_x > SECOND_T_N;
radius R with eq. 3 alone. Where none does, the 3x3x3 block floor(g) + {-1,0,1}^3 with the
normal threshold RING_T_N instead of T_n at radius RING_SCALE * r, and 1 where that finds no weight. Positions are in grid units (one
cell = 1), as the shader computes them: g = (x - origin) / cell_size, a point's offset from the fragment
(cell + (q + 0.5) / 32) - g. On double-sided instances (FLAG_DOUBLE_SIDED) a fragment with `back` set
(the G-buffer's back-side flag) looks up the back-side cells (key | BACK_BIT) instead, as the shader
does; without `back` (a probe whose side nobody flagged) both keys are scanned and eq. 3's normal test
keeps the right side's points. Arithmetic is float32 like the shader's so the two agree to rounding.
"""
from __future__ import annotations

import numpy as np

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.protocol.gridformat import T_D, T_N

_BLOCK = np.array([[dx, dy, dz] for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], dtype=np.int64)
_RING = np.array([[dx, dy, dz] for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.int64)


def reconstruct_ao(instances, buckets, cells, inst_ids, local_pos, local_normal, t_n: float = T_N,
                   t_d: float = T_D, chunk: int = 65536, back=None) -> tuple[np.ndarray, np.ndarray]:
    """AO (M,) float32 and the weight sum (M,) of the step that answered (0: no point found); `back` (M,)
    bool: the fragment shows the back side of a double-sided instance (None: unknown, scan both)."""
    inst_ids = np.asarray(inst_ids, np.int64)
    local_pos = np.asarray(local_pos, np.float32).reshape(-1, 3)
    local_normal = np.asarray(local_normal, np.float32).reshape(-1, 3)
    ao = np.ones(len(inst_ids), np.float32)
    wsum = np.zeros(len(inst_ids), np.float32)
    back = None if back is None else np.asarray(back, bool).reshape(-1)
    for s in range(0, len(inst_ids), chunk):
        sl = slice(s, s + chunk)
        args = (instances, buckets, cells, inst_ids[sl], local_pos[sl], local_normal[sl], t_n, t_d,
                None if back is None else back[sl])
        answer_ao, answer_w = np.ones(len(inst_ids[sl]), np.float32), np.zeros(len(inst_ids[sl]), np.float32)
        for step_ao, step_w in reversed(reconstruct_chunk(*args)):  # the first step with weight answers
            found = step_w > 0
            answer_ao, answer_w = np.where(found, step_ao, answer_ao), np.where(found, step_w, answer_w)
        ao[sl], wsum[sl] = answer_ao, answer_w
        hole = np.flatnonzero(wsum[sl] == 0)
        if len(hole):  # the 3x3x3 ring where the block found no weight in any step
            ring = [a if a is None or np.ndim(a) == 0 or k < 3 else a[hole] for k, a in enumerate(args)]
            ao[s + hole], wsum[s + hole] = reconstruct_chunk(*ring, ring=True)[0]
    return ao, wsum


def reconstruct_chunk(instances, buckets, cells, inst, x, n_x, t_n, t_d, back=None, ring=False):
    """[(AO, weight sum)] of the 2x2x2 block's three steps (radius r with FIRST_T_N and FIRST_T_D,
    FALLBACK_SCALE * r with SECOND_T_N, FALLBACK_SCALE * r with eq. 3 alone), or (ring) of the 3x3x3 block
    around the fragment's cell at RING_SCALE * r with the normal threshold RING_T_N."""
    rec = instances[inst]
    origin = rec["origin"].astype(np.float32)
    s = rec["cell_size"].astype(np.float32)
    r = (rec["radius"].astype(np.float32) / s).astype(np.float32)  # grid units
    wide = (r * np.float32(gf.FALLBACK_SCALE)).astype(np.float32)
    dims = rec["dims"].astype(np.int64)
    g = ((x - origin) / s[:, None]).astype(np.float32)
    if ring:
        t_n = gf.RING_T_N
        steps = [((r * np.float32(gf.RING_SCALE)).astype(np.float32), t_n, t_d)]
        cell = np.floor(g).astype(np.int64)[:, None, :] + _RING[None, :, :]  # (M, 27, 3)
    else:
        # (radius, the step's normal threshold, its tangent-plane threshold)
        steps = [(r, np.float32(gf.FIRST_T_N), np.float32(gf.FIRST_T_D)), (wide, np.float32(gf.SECOND_T_N), np.float32(t_d)),
                 (wide, t_n, t_d)]
        cell = gf.lookup_block_base(g)[:, None, :] + _BLOCK[None, :, :]  # (M, 8, 3)
    inside = np.all((cell >= 0) & (cell < dims[:, None, :]), axis=2)
    c = np.where(inside[..., None], cell, 0)
    cx, cy, cz = c[..., 0], c[..., 1], c[..., 2]
    key = gf.cell_key(cx, cy, cz, dims[:, None, :])
    # Back-side cells of double-sided instances: same block, same buckets, key with BACK_BIT.
    two_sided = (rec["flags"] & gf.FLAG_DOUBLE_SIDED) != 0
    back_key = np.where(two_sided[:, None], key | gf.BACK_BIT, gf.EMPTY).astype(np.uint32)
    b = gf.bucket_index(cx, cy, cz, dims[:, None, :], rec["bucket_offset"][:, None], rec["bucket_count"][:, None])
    b = np.where(inside, b.astype(np.int64), 0)
    entries = buckets[b]  # (M, C, 8, 2)
    if back is not None:
        # The side is known (the shader's case): one key per cell of the block, the back one where flagged.
        keys = np.where((back & two_sided)[:, None], back_key, key)
    else:
        # Twice the block's cells: its front keys, then its back keys (EMPTY, never matched, if one-sided).
        cell = np.concatenate([cell, cell], axis=1)
        inside = np.concatenate([inside, inside & two_sided[:, None]], axis=1)
        keys = np.concatenate([key, back_key], axis=1)
        entries = np.concatenate([entries, entries], axis=1)
    # The key's first entry and the entries right after it with the same key contribute their cells, at
    # most KEY_CELLS: a key with more than 7 points owns several cells, next to each other in its bucket.
    # Entries are used-first, so "before the first EMPTY" is the same as "anywhere".
    match = (entries[..., 0] == keys[..., None]) & inside[..., None]  # (M, C, 8)
    after_first = np.cumsum(match, axis=2) > 0
    broken = np.cumsum(after_first & ~match, axis=2) > 0  # an entry of another key ended the run
    match &= ~broken & (np.cumsum(match, axis=2) <= gf.KEY_CELLS)
    mi, ci, ei = np.nonzero(match)
    slot = entries[mi, ci, ei, 1].astype(np.int64)
    words = cells[slot][:, : gf.POINTS_PER_CELL]  # (K, 7)
    allocated, qpos, ncode, aocode = pw.unpack_point(words)
    # Offset of each point from the fragment, in cells, in the shader's order of operations.
    cg = (cell[mi, ci].astype(np.float32) + np.float32(0.5 / pw.POSITION_LEVELS)) - g[mi]
    d_vec = cg[:, None, :] + qpos.astype(np.float32) * np.float32(1.0 / pw.POSITION_LEVELS)
    n_p = pw.oct_decode(ncode)
    dist2 = (d_vec * d_vec).sum(axis=-1, dtype=np.float32)
    dist = np.sqrt(dist2)
    ndot = (n_p * n_x[mi][:, None, :]).sum(axis=-1)
    ddot = (n_p * d_vec).sum(axis=-1)
    # eq. 3; the shader stops at the first unallocated word, allocated-first makes that the same as masking.
    passes = gf.passes_thresholds(ndot, ddot, dist2, t_n, np.float32(t_d)) & allocated
    ao_vals = pw.dequantise_ao(aocode)
    out = []
    for radius, step_t_n, step_t_d in steps:
        inv = (np.float32(1.0) / radius[mi]).astype(np.float32)[:, None]  # the shader multiplies by 1 / rho
        counts = passes & gf.passes_thresholds(ndot, ddot, dist2, step_t_n, step_t_d)
        tent = np.maximum(np.float32(0.0), np.float32(1.0) - dist * inv).astype(np.float32)
        w = tent
        for _ in range(gf.WEIGHT_POWER - 1):  # repeated products, as the shader computes the power
            w = (w * tent).astype(np.float32)
        w = np.where(counts, w, np.float32(0.0)).astype(np.float32)
        wsum = np.bincount(mi, weights=w.sum(axis=1, dtype=np.float32), minlength=len(inst)).astype(np.float32)
        num = np.bincount(mi, weights=(w * ao_vals).sum(axis=1, dtype=np.float32), minlength=len(inst)).astype(np.float32)
        ao = np.where(wsum > 0, num / np.where(wsum > 0, wsum, np.float32(1.0)), np.float32(1.0)).astype(np.float32)
        out.append((ao, wsum))
    return out
