"""The random-edit test hook: its nearest-point clusters, read from a box of cells around the seed, are
the very points a search over the whole grid finds."""
import numpy as np

from psao.protocol import gridformat as gf
from psao.server.grid import Grid
from psao.server.tick.testhook import _cluster, random_edits


def whole_grid_cluster(grid: Grid, rng: np.random.Generator, k: int):
    """The k points of the seed's instance nearest to a random seed point, searched over every point."""
    table = grid.point_table()
    seed = int(rng.integers(len(table)))
    same = np.flatnonzero(table.instance == table.instance[seed])
    d = np.linalg.norm(table.local_pos[same] - table.local_pos[seed], axis=1)
    return table, same[np.argsort(d, kind="stable")[:k]]


def test_box_cluster_equals_whole_grid_search():
    rng = np.random.default_rng(3)
    sheets = []
    for size, spacing, flags in ((1.0, 0.01, 0), (3.0, 0.03, gf.FLAG_DOUBLE_SIDED), (0.2, 0.004, 0)):
        p = np.zeros((2500, 3))
        p[:, :2] = rng.random((2500, 2)) * size
        p[:, 2] = 0.02 * np.sin(7 * p[:, 0])  # not flat: cells in three dimensions
        n = np.tile([0.0, 0.0, 1.0], (2500, 1)).astype(np.float32)
        sheets.append((p, n, spacing, flags))
    grid = Grid.build(sheets)
    edits = np.random.default_rng(9)
    checked = 0
    for step in range(12):
        for k in (0, 1, 7, 140, 3000):  # 3000: more than the smaller sheets hold
            a, b = np.random.default_rng(step * 10 + k), np.random.default_rng(step * 10 + k)
            table, near = _cluster(grid, a, k)
            ref_table, ref = whole_grid_cluster(grid, b, k)
            assert np.array_equal(table.slot[near], ref_table.slot[ref])
            assert np.array_equal(table.index[near], ref_table.index[ref])
            assert np.array_equal(table.point_id[near], ref_table.point_id[ref])
            assert np.array_equal(table.local_pos[near], ref_table.local_pos[ref])
            checked += len(near)
        random_edits(grid, edits, 200)  # moves, frees and allocations between rounds
    assert checked > 10_000
