"""The grid's Warp kernels (psao_server/grid_kernels.py) give exactly what the numpy reference gives: where
points land, the packed words and the whole grid after a sequence of moves."""
import copy

import numpy as np
import pytest

pytest.importorskip("warp")

import psao_server.grid as grid_module  # noqa: E402
from protocol import gridformat as gf  # noqa: E402
from psao_server import grid_kernels  # noqa: E402
from psao_server.grid import Grid, instance_record  # noqa: E402
from psao_server.settings import GridSettings  # noqa: E402

GRID_STATE = ("cells", "buckets", "point_local", "point_normal", "point_id", "cell_instance", "dirty_cells", "dirty_buckets")


def awkward_positions(rec, n, rng):
    """Positions in and around an instance's box: on cell faces, NaN, infinite, -0.0 on the origin."""
    s, o = float(rec["cell_size"]), rec["origin"].astype(np.float64)
    top = o + rec["dims"].astype(np.float64) * s
    pos = o - 2 * s + (top - o + 4 * s) * rng.random((n, 3))
    pos[:n // 5] = o + np.round((pos[:n // 5] - o) / s) * s  # exactly on faces (and on the box's own faces)
    pos[n // 5:n // 5 + 10] = np.nan
    pos[n // 5 + 10:n // 5 + 20, 1] = np.inf
    pos[n // 5 + 20:n // 5 + 30] = o * 1.0 + (-0.0)
    pos[n // 5 + 30:n // 5 + 40] = top  # the far faces: outside
    return pos


def awkward_normals(n, rng):
    nrm = rng.standard_normal((n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm[:6] = np.vstack([np.eye(3), -np.eye(3)])
    nrm[6:9] = [[0, 0, -0.0], [-0.0, 0.5, -0.5], [0.5, -0.0, -0.5]]  # signed zeros in the lower hemisphere fold
    nrm[9] = 0.0  # degenerate
    nrm[10:20] = np.round(nrm[10:20] * 7) / 7  # on the octahedral levels' rounding boundaries and between
    return nrm.astype(np.float32)


@pytest.fixture
def record():
    return instance_record(np.zeros(3), np.array([2.0, 1.0, 0.5]), 0.01, 1000, 0, GridSettings())


def test_locate_equals_cell_of_and_cell_key(record):
    rng = np.random.default_rng(0)
    grid = Grid(np.array([record]), 64)
    pos = awkward_positions(record, 50_000, rng)
    side = np.where(rng.random(len(pos)) < 0.3, gf.BACK_BIT, 0).astype(np.uint32)
    with np.errstate(invalid="ignore"):
        cell, inside = grid.cell_of(0, pos)
    keys = gf.cell_key(cell[:, 0], cell[:, 1], cell[:, 2], record["dims"]) | side
    old = np.where(rng.random(len(pos)) < 0.5, keys, keys ^ np.uint32(1)).astype(np.uint32)
    got = grid_kernels.locate(pos, record, side, old)
    assert 0.2 < inside.mean() < 0.95
    for a, b in zip(got, (cell, inside, keys, inside & (keys == old))):
        np.testing.assert_array_equal(a, b)


def test_written_points_equal_numpy_words(record):
    rng = np.random.default_rng(1)
    ref, grid = Grid(np.array([record]), 3000), Grid(np.array([record]), 3000)
    pos = awkward_positions(record, 40_000, rng)
    with np.errstate(invalid="ignore"):
        cell, inside = ref.cell_of(0, pos)
    n = 20_000
    pos, cell = pos[inside][:n], cell[inside][:n]
    slots = rng.permutation(3000)[:-(-n // 7)].repeat(7)[:n]
    idx = np.tile(np.arange(7), -(-n // 7))[:n]
    nrm = awkward_normals(n, rng)
    ao = rng.integers(0, 256, n).astype(np.uint32)
    ids = rng.integers(0, 1 << 40, n)
    ref._write_points(slots, idx, record, cell, pos, nrm, ao, ids)
    grid_kernels.write_points(grid, slots, idx, record, cell, pos, nrm, ao, ids)
    for name in ("cells", "point_local", "point_normal", "point_id"):
        np.testing.assert_array_equal(getattr(grid, name), getattr(ref, name), err_msg=name)


def test_moves_with_and_without_kernels_leave_the_same_grid(monkeypatch):
    """Whole-instance refills, partial moves (points staying in their cells, and leaving them) and points
    leaving the box: every array, the free list and the statistics agree with the numpy path."""
    rng = np.random.default_rng(2)
    p = np.zeros((3000, 3))
    p[:, :2] = rng.random((3000, 2))
    nrm = np.tile(np.float32([0, 0, 1]), (3000, 1))
    kernel = Grid.build([(p[:500] * 2, nrm[:500], 0.02, 0), (p, nrm, 0.01, gf.FLAG_DOUBLE_SIDED, rng.random(3000) < 0.3)])
    numpy_grid = copy.deepcopy(kernel)
    for step in range(6):
        t = kernel.point_table()
        mine = np.flatnonzero(t.instance == 1)
        pick = rng.permutation(mine)[:len(mine) if step % 2 == 0 else len(mine) // 5]
        scale = 0.03 if step % 3 else 0.0005  # most leave their cells / most stay
        newpos = t.local_pos[pick] + rng.normal(scale=scale, size=(len(pick), 3)) * [1, 1, 0]
        newpos[::23] += 3.0  # some leave the box
        n = awkward_normals(len(pick), rng)
        monkeypatch.setattr(grid_module, "USE_KERNELS", False)
        want = numpy_grid.move_points(t.slot[pick], t.index[pick], newpos, n)
        monkeypatch.setattr(grid_module, "USE_KERNELS", True)
        got = kernel.move_points(t.slot[pick], t.index[pick], newpos, n)
        np.testing.assert_array_equal(got, want)
        for name in GRID_STATE:
            np.testing.assert_array_equal(getattr(kernel, name), getattr(numpy_grid, name), err_msg=f"step {step}: {name}")
        assert kernel.free_slots == numpy_grid.free_slots and kernel.stats == numpy_grid.stats


def test_written_rows_equal_gathered_points(record):
    """write_points(..., rows=r) writes what write_points of the gathered rows writes."""
    rng = np.random.default_rng(3)
    a, b = Grid(np.array([record]), 500), Grid(np.array([record]), 500)
    pos = record["origin"].astype(np.float64) + rng.random((4000, 3)) * 0.3
    with np.errstate(invalid="ignore"):
        cell, _ = a.cell_of(0, pos)
    nrm, ao, ids = awkward_normals(4000, rng), rng.integers(0, 256, 4000).astype(np.uint32), rng.integers(0, 1 << 40, 4000)
    rows = rng.permutation(4000)[:3000]
    slots, idx = rng.permutation(500).repeat(7)[:3000], np.tile(np.arange(7), 500)[:3000]
    grid_kernels.write_points(a, slots, idx, record, cell, pos, nrm, ao, ids, rows=rows)
    grid_kernels.write_points(b, slots, idx, record, cell[rows], pos[rows], nrm[rows], ao[rows], ids[rows])
    for name in ("cells", "point_local", "point_normal", "point_id"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
