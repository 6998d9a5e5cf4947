"""Warp kernels for the grid's per-point work when a skinned instance moves (Grid.move_points): where each
point lands (cell, inside the box, key, still in its cell) and writing points into the cell pool (packed
word, exact position, normal, id) in one pass each, instead of a dozen numpy passes with temporaries.

The numpy code they replace stays the reference (gridformat.grid_coords / cell_key, pointword's
quantise_cell_fraction / oct_encode / pack_point): the same float64 operations in the same order, so
the words are bit for bit the same (tests/test_grid_kernels.py). They run on Warp's CPU device, on the
grid's own numpy arrays (no copies).

    cell, inside, key, same = locate(positions, record, side, old_key)
    write_points(grid, slots, index, record, cell, positions, normals, ao, ids)
"""
from __future__ import annotations

import numpy as np
import warp as wp

from protocol import gridformat as gf
from protocol import pointword as pw

wp.config.quiet = True

POSITION_LEVELS = wp.constant(wp.float64(pw.POSITION_LEVELS))
POSITION_MAX = wp.constant(wp.float64(pw.POSITION_LEVELS - 1))
OCT_HALF = wp.constant(wp.float64(pw.OCT_LEVELS_HALF))
OCT_MAX = wp.constant(wp.float64(2 * pw.OCT_LEVELS_HALF))
ALLOCATED = wp.constant(wp.uint32(int(pw.ALLOCATED_BIT)))
POSITION_MASK = wp.constant(wp.uint32(pw.POSITION_MASK))
CODE_MASK = wp.constant(wp.uint32(pw.CODE_MASK))
SHIFT_X = wp.constant(wp.uint32(pw.SHIFT_X))
SHIFT_Y = wp.constant(wp.uint32(pw.SHIFT_Y))
SHIFT_Z = wp.constant(wp.uint32(pw.SHIFT_Z))
SHIFT_NORMAL = wp.constant(wp.uint32(pw.SHIFT_NORMAL))
SHIFT_U = wp.constant(wp.uint32(4))
KEY_BITS = wp.constant(wp.int64(0xFFFFFFFF))


@wp.func
def grid_coord(p: wp.float64, origin: wp.float64, cell_size: wp.float64) -> wp.float64:
    return (p - origin) / cell_size  # gridformat.grid_coords


@wp.func
def position_code(p: wp.float64, origin: wp.float64, cell_size: wp.float64, cell: wp.int32) -> wp.uint32:
    # pointword.quantise_cell_fraction of grid_coords(p) - cell
    q = wp.floor((grid_coord(p, origin, cell_size) - wp.float64(cell)) * POSITION_LEVELS)
    return wp.uint32(wp.clamp(q, wp.float64(0.0), POSITION_MAX))


@wp.func
def oct_level(f: wp.float64) -> wp.uint32:
    return wp.uint32(wp.clamp(wp.rint(f * OCT_HALF) + OCT_HALF, wp.float64(0.0), OCT_MAX))


@wp.func
def oct_code(n: wp.vec3f) -> wp.uint32:
    # pointword.oct_encode, in float64 as there
    x = wp.float64(n[0])
    y = wp.float64(n[1])
    z = wp.float64(n[2])
    l1 = wp.abs(x) + wp.abs(y) + wp.abs(z)
    if not (l1 > wp.float64(0.0)):
        l1 = wp.float64(1.0)
    u = x / l1
    v = y / l1
    fu = u
    fv = v
    if z < wp.float64(0.0):
        fu = wp.copysign(wp.float64(1.0) - wp.abs(v), u + wp.float64(0.0))
        fv = wp.copysign(wp.float64(1.0) - wp.abs(u), v + wp.float64(0.0))
    return (oct_level(fu) << SHIFT_U) | oct_level(fv)


@wp.kernel
def locate_kernel(pos: wp.array(dtype=wp.vec3d), origin: wp.vec3d, cell_size: wp.float64, dims: wp.vec3i,
                  side: wp.array(dtype=wp.uint32), old_key: wp.array(dtype=wp.uint32),
                  out_cell: wp.array(dtype=wp.vec3i), out_inside: wp.array(dtype=wp.uint8),
                  out_key: wp.array(dtype=wp.uint32), out_same: wp.array(dtype=wp.uint8)):
    # Grid.cell_of and gridformat.cell_key: 0 <= g < dims per axis is floor(g) in [0, dims) for finite g,
    # and false for NaN and infinities, so no integer conversion happens outside the box.
    i = wp.tid()
    p = pos[i]
    inside = int(1)
    cell = wp.vec3i(0, 0, 0)
    for a in range(3):
        g = grid_coord(p[a], origin[a], cell_size)
        if g >= wp.float64(0.0) and g < wp.float64(dims[a]):
            cell[a] = wp.int32(wp.floor(g))
        else:
            inside = 0
    if inside == 0:
        cell = wp.vec3i(0, 0, 0)
    key = wp.uint32((wp.int64(cell[0]) + wp.int64(dims[0]) * (wp.int64(cell[1]) + wp.int64(dims[1]) * wp.int64(cell[2])))
                    & KEY_BITS) | side[i]
    out_cell[i] = cell
    out_inside[i] = wp.uint8(inside)
    out_key[i] = key
    out_same[i] = wp.uint8(0)
    if inside == 1 and key == old_key[i]:
        out_same[i] = wp.uint8(1)


@wp.kernel
def write_points_kernel(slot: wp.array(dtype=wp.int64), index: wp.array(dtype=wp.int64), rows: wp.array(dtype=wp.int64),
                        cell: wp.array(dtype=wp.vec3i), pos: wp.array(dtype=wp.vec3d), nrm: wp.array(dtype=wp.vec3f),
                        ao: wp.array(dtype=wp.uint32), ids: wp.array(dtype=wp.int64), origin: wp.vec3d, cell_size: wp.float64,
                        out_cells: wp.array2d(dtype=wp.uint32), out_local: wp.array2d(dtype=wp.vec3d),
                        out_normal: wp.array2d(dtype=wp.vec3f), out_id: wp.array2d(dtype=wp.int64)):
    # Grid._write_points: pointword.pack_point of the quantised position, oct code and AO; point i is row
    # rows[i] of the per-point inputs (no gathered copies of them)
    i = wp.tid()
    s = int(slot[i])
    k = int(index[i])
    r = int(rows[i])
    p = pos[r]
    c = cell[r]
    word = (ALLOCATED
            | ((position_code(p[2], origin[2], cell_size, c[2]) & POSITION_MASK) << SHIFT_Z)
            | ((position_code(p[1], origin[1], cell_size, c[1]) & POSITION_MASK) << SHIFT_Y)
            | ((position_code(p[0], origin[0], cell_size, c[0]) & POSITION_MASK) << SHIFT_X)
            | ((oct_code(nrm[r]) & CODE_MASK) << SHIFT_NORMAL)
            | (ao[r] & CODE_MASK))
    out_cells[s, k] = word
    out_local[s, k] = p
    out_normal[s, k] = nrm[r]
    out_id[s, k] = ids[r]


def _record(rec) -> tuple:
    """(origin, cell size, dims) of an instance record as the kernels take them (float64 of the float32s)."""
    o = rec["origin"].astype(np.float64)
    return wp.vec3d(*o), wp.float64(float(rec["cell_size"])), wp.vec3i(*(int(d) for d in rec["dims"]))


def _in(a: np.ndarray, dtype, np_dtype) -> wp.array:
    """A Warp view of a numpy array (a contiguous copy of it first where it is not one already)."""
    return wp.array(np.ascontiguousarray(a, np_dtype), dtype=dtype, device="cpu", copy=False)


def locate(positions: np.ndarray, rec, side: np.ndarray, old_key: np.ndarray):
    """For local positions (P, 3): cell (P, 3) int64 (0 outside), inside (P,) bool, key (P,) uint32 with
    the `side` bits, and same (P,) bool: inside and key equals `old_key`."""
    n = len(positions)
    cell = np.empty((n, 3), np.int32)
    inside, same = np.empty(n, np.uint8), np.empty(n, np.uint8)
    key = np.empty(n, np.uint32)
    if n:
        origin, size, dims = _record(rec)
        wp.launch(locate_kernel, dim=n, device="cpu",
                  inputs=[_in(positions, wp.vec3d, np.float64), origin, size, dims, _in(side, wp.uint32, np.uint32),
                          _in(old_key, wp.uint32, np.uint32)],
                  outputs=[_in(cell, wp.vec3i, np.int32), _in(inside, wp.uint8, np.uint8), _in(key, wp.uint32, np.uint32),
                           _in(same, wp.uint8, np.uint8)])
    return cell.astype(np.int64), inside.view(bool), key, same.view(bool)


def write_points(grid, slots, index, rec, cell, positions, normals, ao, ids, rows=None) -> None:
    """Grid._write_points in one kernel pass, into the grid's own arrays; with `rows`, point i is row
    rows[i] of cell, positions, normals, ao and ids (Grid._write_points(..., cell[rows], positions[rows], ...))."""
    n = len(slots)
    if n == 0:
        return
    rows = np.arange(n) if rows is None else rows
    origin, size, _ = _record(rec)
    wp.launch(write_points_kernel, dim=n, device="cpu",
              inputs=[_in(slots, wp.int64, np.int64), _in(index, wp.int64, np.int64), _in(rows, wp.int64, np.int64),
                      _in(cell, wp.vec3i, np.int32),
                      _in(positions, wp.vec3d, np.float64), _in(normals, wp.vec3f, np.float32), _in(ao, wp.uint32, np.uint32),
                      _in(ids, wp.int64, np.int64), origin, size],
              outputs=[wp.array(grid.cells, dtype=wp.uint32, device="cpu", copy=False),
                       wp.array(grid.point_local, dtype=wp.vec3d, device="cpu", copy=False),
                       wp.array(grid.point_normal, dtype=wp.vec3f, device="cpu", copy=False),
                       wp.array(grid.point_id, dtype=wp.int64, device="cpu", copy=False)])


def load() -> None:
    """Compile (first use on a machine: seconds) and load the kernels now, not in the first tick that moves."""
    positions = np.zeros((1, 3))
    rec = np.zeros((), dtype=[("origin", "<f4", 3), ("cell_size", "<f4"), ("dims", "<u4", 3)])
    rec["cell_size"], rec["dims"] = 1.0, 1
    cell, _, _, _ = locate(positions, rec, np.zeros(1, np.uint32), np.zeros(1, np.uint32))

    class Scratch:  # one cell of pool
        cells = np.zeros((1, gf.CELL_WORDS), np.uint32)
        point_local = np.zeros((1, gf.POINTS_PER_CELL, 3))
        point_normal = np.zeros((1, gf.POINTS_PER_CELL, 3), np.float32)
        point_id = np.zeros((1, gf.POINTS_PER_CELL), np.int64)

    write_points(Scratch, np.zeros(1, np.int64), np.zeros(1, np.int64), rec, cell, positions,
                 np.float32([[0, 0, 1]]), np.zeros(1, np.uint32), np.zeros(1, np.int64))


__all__ = ["load", "locate", "write_points"]
