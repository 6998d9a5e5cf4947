"""Grid memory management: layout invariants after every kind of edit, against brute force."""
import numpy as np
import pytest

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.protocol.reconstruct import reconstruct_ao
from psao.server.errors import GridError
from psao.server.grid import Grid
from psao.server.settings import GridSettings


def plane_points(n, rng, size=1.0):
    p = np.zeros((n, 3))
    p[:, :2] = rng.random((n, 2)) * size
    return p, np.tile([0.0, 0.0, 1.0], (n, 1)).astype(np.float32)


def check_invariants(grid: Grid):
    """Every structural rule of DESIGN.md holds for the whole grid."""
    used = grid.buckets[:, :, 0] != gf.EMPTY
    # used entries first, empty entries fully EMPTY
    assert not (np.diff(used.astype(int), axis=1) > 0).any()
    assert (grid.buckets[~used] == gf.EMPTY).all()
    # a key's entries (several cells of one crowded key) are next to each other, as the lookup reads them
    keys = grid.buckets[:, :, 0]
    starts = used & np.concatenate([np.ones((len(keys), 1), bool), keys[:, 1:] != keys[:, :-1]], axis=1)
    for b in np.flatnonzero(used.any(axis=1)):
        assert starts[b].sum() == len(np.unique(keys[b][used[b]])), f"bucket {b}: a key's entries are apart"
    live = grid.allocated_cells()
    referenced = grid.buckets[used][:, 1]
    assert sorted(referenced.tolist()) == sorted(live.tolist()), "bucket entries and allocated cells disagree"
    for b, e in zip(*np.nonzero(used)):
        key, slot = grid.buckets[b, e]
        assert grid.cells[slot, gf.KEY_WORD] == key
        inst = grid.cell_instance[slot]
        rec = grid.instances[inst]
        c = gf.key_to_cell(key, rec["dims"])
        assert gf.bucket_index(c[0], c[1], c[2], rec["dims"], rec["bucket_offset"], rec["bucket_count"]) == b
    alloc = (grid.cells[:, : gf.POINTS_PER_CELL] >> 31) == 1
    assert not (np.diff(alloc.astype(int), axis=1) > 0).any(), "allocated points must come first"
    assert (alloc == (grid.point_id != -1)).all()
    assert alloc[live].any(axis=1).all(), "an allocated cell must not be empty"
    free = np.setdiff1d(np.arange(grid.capacity), live)
    assert (grid.cells[free] == gf.FREE_CELL).all()
    assert sorted(grid.free_slots) == free.tolist()
    # every point word decodes to within one quantisation step of its exact position, inside its cell
    slot, idx = np.nonzero(alloc)
    for inst in np.unique(grid.cell_instance[slot]):
        sel = grid.cell_instance[slot] == inst
        rec = grid.instances[inst]
        cell = gf.key_to_cell(grid.cells[slot[sel], gf.KEY_WORD], rec["dims"])
        _, q, _, _ = pw.unpack_point(grid.cells[slot[sel], idx[sel]])
        decoded = gf.decode_point_local(cell, q, rec["origin"], rec["cell_size"])
        err = np.abs(decoded - grid.point_local[slot[sel], idx[sel]]).max()
        assert err <= rec["cell_size"] / 64 * 1.001 + 1e-6


def test_build_keeps_points_and_invariants():
    rng = np.random.default_rng(0)
    p, n = plane_points(5000, rng)
    grid = Grid.build([(p, n, 0.01, 0)])
    check_invariants(grid)
    assert grid.stats.inserted + grid.stats.dropped == 5000
    assert grid.n_points() == grid.stats.inserted
    rec = grid.instances[0]
    assert rec["cell_size"] >= 2 * rec["radius"] - 1e-7
    assert rec["bucket_count"] & (rec["bucket_count"] - 1) == 0


def test_full_cell_overflows_into_more_cells_of_its_key():
    # 20 points in one cell: three cells share the key in its bucket, nothing is dropped, and the
    # lookup sums all of them.
    rng = np.random.default_rng(1)
    p = 0.5 + rng.random((20, 3)) * 0.01
    n = np.tile([0, 0, 1.0], (20, 1))
    grid = Grid.build([(np.vstack([p, [[0.0] * 3, [1.0] * 3]]), np.vstack([n, n[:2]]), 0.1, 0)])
    assert grid.stats.inserted == 22 and grid.stats.dropped == 0
    keys = grid.cells[grid.allocated_cells(), gf.KEY_WORD]
    assert len(keys) == 5 and np.unique(keys, return_counts=True)[1].max() == 3
    check_invariants(grid)
    t = grid.point_table()
    _, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, [0], p[:1], n[:1])
    rec = grid.instances[0]
    decoded = p  # within a quantisation step; recompute the exact weight sum the lookup must reach
    d = np.linalg.norm(decoded - p[0], axis=1)
    expected = np.maximum(0, (rec["radius"] - d) / rec["radius"]).sum()
    assert wsum[0] == pytest.approx(expected, rel=0.05)
    # removing points frees the emptied overflow cells and only their bucket entries
    t = grid.point_table()
    grid.remove_points(t.slot[:10], t.index[:10])
    check_invariants(grid)
    assert grid.n_points() == 12


def test_bucket_overflow_drops_and_counts():
    # One bucket for the instance: the 9th distinct cell cannot be placed.
    p = np.array([[i * 0.5, 0.0, 0.0] for i in range(12)])
    n = np.tile([0, 0, 1.0], (12, 1))
    grid = Grid.build([(p, n, 0.05, 0)], GridSettings(bucket_factor=0.5))
    assert grid.instances[0]["bucket_count"] == 1
    assert grid.stats.inserted == 8 and grid.stats.dropped_bucket_full == 4
    check_invariants(grid)


def test_random_edits_keep_invariants_and_dirty_flags():
    rng = np.random.default_rng(5)
    p, n = plane_points(3000, rng)
    p2, n2 = plane_points(2000, rng, 2.0)
    grid = Grid.build([(p, n, 0.01, 0), (p2, n2, 0.02, gf.FLAG_DOUBLE_SIDED)])
    grid.take_dirty()
    for step in range(30):
        t = grid.point_table()
        pick = rng.choice(len(t), 40, replace=False)
        kind = step % 3
        before = grid.cells.copy(), grid.buckets.copy()
        if kind == 0:
            grid.set_ao(t.slot[pick], t.index[pick], rng.integers(0, 256, 40))
        elif kind == 1:
            grid.remove_points(t.slot[pick], t.index[pick])
        else:
            newpos = t.local_pos[pick] + rng.normal(scale=0.05, size=(40, 3)) * [1, 1, 0]
            grid.move_points(t.slot[pick], t.index[pick], newpos, t.local_normal[pick])
        check_invariants(grid)
        db, dc = grid.take_dirty()
        # every changed row is flagged (flags may be a superset, never a subset)
        cap = min(len(before[0]), grid.capacity)
        changed_c = np.flatnonzero((grid.cells[:cap] != before[0][:cap]).any(axis=1))
        changed_b = np.flatnonzero((grid.buckets != before[1]).any(axis=(1, 2)))
        assert set(changed_c) <= set(dc.tolist())
        assert set(changed_b) <= set(db.tolist())


@pytest.mark.parametrize("moved_fraction", [1.0, 0.9])
def test_moving_most_points_of_an_instance(moved_fraction):
    """An instance moving all or most of its points: every point is held once at
    its new position with its id, AO and side, the other instance is untouched, invariants and dirty flags
    hold, and the pool does not grow."""
    rng = np.random.default_rng(7)
    p, n = plane_points(3000, rng)
    p2, n2 = plane_points(500, rng, 2.0)
    back = rng.random(3000) < 0.3
    grid = Grid.build([(p, n, 0.01, gf.FLAG_DOUBLE_SIDED, back), (p2, n2, 0.02, 0)])
    t = grid.point_table()
    grid.set_ao(t.slot, t.index, rng.integers(0, 256, len(t)))
    grid.take_dirty()
    t = grid.point_table()
    assert (cells_before_sides := (grid.cells[t.slot, gf.KEY_WORD] & gf.BACK_BIT)).any()
    other = t.instance == 1
    before_other = {int(i): int(w) for i, w in zip(t.point_id[other], grid.cells[t.slot[other], t.index[other]])}
    mine = np.flatnonzero(t.instance == 0)
    pick = mine[: int(moved_fraction * len(mine))]  # at 0.9 some points of the instance stay put
    newpos = t.local_pos[rng.permutation(pick)]  # inside the box, cells no fuller than before
    cells_before, buckets_before, capacity = grid.cells.copy(), grid.buckets.copy(), grid.capacity
    kept = grid.move_points(t.slot[pick], t.index[pick], newpos, t.local_normal[pick])
    assert kept.all() and grid.capacity == capacity
    check_invariants(grid)
    after = grid.point_table()
    where = {int(i): k for k, i in enumerate(after.point_id)}
    assert len(where) == len(t)
    expect = t.local_pos.copy()
    expect[pick] = newpos
    at = np.array([where[int(i)] for i in t.point_id])
    np.testing.assert_array_equal(after.local_pos[at], expect)
    np.testing.assert_array_equal(after.ao_code[at], t.ao_code)
    np.testing.assert_array_equal(cells_before[t.slot, gf.KEY_WORD] & gf.BACK_BIT,
                                  grid.cells[after.slot[at], gf.KEY_WORD] & gf.BACK_BIT)
    assert {int(i): int(grid.cells[after.slot[where[i]], after.index[where[i]]]) for i in before_other} == before_other
    db, dc = grid.take_dirty()
    changed_c = np.flatnonzero((grid.cells != cells_before).any(axis=1))
    changed_b = np.flatnonzero((grid.buckets != buckets_before).any(axis=(1, 2)))
    assert set(changed_c) <= set(dc.tolist()) and set(changed_b) <= set(db.tolist())


def test_moving_a_few_points_of_a_large_instance_leaves_the_rest_alone():
    """A few points moved out of their cells in a large instance (an edit, a small part): every point is
    kept, and only the cells those points leave or enter are marked dirty (the rest of the instance does
    not go on the wire)."""
    rng = np.random.default_rng(8)
    p, n = plane_points(4000, rng)
    grid = Grid.build([(p, n, 0.01, 0)])
    grid.take_dirty()
    t = grid.point_table()
    pick = rng.choice(len(t), 40, replace=False)
    newpos = t.local_pos[pick].copy()
    newpos[:, :2] = (newpos[:, :2] + 0.05) % 1.0  # several cells away, inside the plane
    kept = grid.move_points(t.slot[pick], t.index[pick], newpos, t.local_normal[pick])
    assert kept.all()
    check_invariants(grid)
    assert len(grid.point_table()) == len(t)
    _, dirty_cells = grid.take_dirty()
    assert len(dirty_cells) <= 2 * len(pick) * gf.KEY_CELLS


def test_pool_grows_when_full():
    rng = np.random.default_rng(6)
    p, n = plane_points(200, rng)
    grid = Grid.build([(p, n, 0.01, 0)], GridSettings(pool_headroom=0.0, bucket_factor=64))
    cap = grid.capacity
    far = np.column_stack([rng.random(3000), rng.random(3000), np.zeros(3000)])
    grid.insert_points(0, far, np.tile([0, 0, 1.0], (3000, 1)), 255)
    assert grid.capacity > cap
    check_invariants(grid)


def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(8)
    p, n = plane_points(1000, rng)
    grid = Grid.build([(p, n, 0.02, 0)])
    grid.save(tmp_path / "g.npz", scene_hash="abc", meta={"density": 5})
    g2, h, meta = Grid.load(tmp_path / "g.npz")
    assert h == "abc" and meta == {"density": 5}
    for name in ("instances", "buckets", "cells", "point_local", "point_id"):
        np.testing.assert_array_equal(getattr(g2, name), getattr(grid, name))
    check_invariants(g2)


def test_load_rejects_garbage(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(GridError, match="not a PSAO grid"):
        Grid.load(bad)


def test_instance_without_points():
    rng = np.random.default_rng(9)
    p, n = plane_points(100, rng)
    grid = Grid.build([(np.zeros((0, 3)), np.zeros((0, 3)), 0.1, 0), (p, n, 0.05, 0)])
    check_invariants(grid)
    assert grid.n_points() == 100 - grid.stats.dropped


def test_cell_factor_below_two_is_rejected():
    with pytest.raises(GridError, match="cell_factor"):
        GridSettings(cell_factor=1.5)


def test_crowded_cell_keeps_points_on_every_surface():
    # A corner: 12 points on the floor, 3 on a wall, all in one cell: every one is kept.
    rng = np.random.default_rng(10)
    floor = np.column_stack([rng.random(12) * 0.06 + 0.03, rng.random(12) * 0.06 + 0.03, np.full(12, 0.03)])
    wall = np.column_stack([np.full(3, 0.03), rng.random(3) * 0.06 + 0.03, rng.random(3) * 0.06 + 0.03])
    p = np.vstack([floor, wall, [[0.0, 0.0, 0.0], [0.12, 0.12, 0.12]]])  # two far points pin the grid origin
    n = np.vstack([np.tile([0, 0, 1.0], (12, 1)), np.tile([1.0, 0, 0], (3, 1)), [[0, 0, 1.0], [0, 0, 1.0]]])
    grid = Grid.build([(p, n, 0.025, 0)])
    assert grid.stats.dropped == 0 and grid.n_points() == len(p)
    check_invariants(grid)
    _, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(3, int), wall, np.tile([1.0, 0, 0], (3, 1)))
    assert (wsum > 0).all()


def test_a_key_takes_at_most_key_cells_cells():
    p = np.vstack([0.5 + np.random.default_rng(2).random((30, 3)) * 0.01, [[0.0] * 3, [1.0] * 3]])
    n = np.tile([0, 0, 1.0], (32, 1))
    grid = Grid.build([(p, n, 0.1, 0)])
    cap = gf.KEY_CELLS * gf.POINTS_PER_CELL
    assert grid.stats.dropped_cell_full == 30 - cap and grid.n_points() == cap + 2
    check_invariants(grid)
