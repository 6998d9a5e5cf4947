"""The reference lookup (the shader's oracle) against brute force over every point of the instance."""
import numpy as np

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.protocol.gridformat import T_D, T_N
from psao.protocol.reconstruct import reconstruct_ao
from psao.server.grid import Grid


def brute_force(grid: Grid, inst, x, n_x):
    """eq. 2-4 over ALL decoded points of the instance whose normal also passes FIRST_T_N and whose offset
    passes FIRST_T_D, no grid lookup; where no point has weight, the points of the 2x2x2 block around x
    with the radius times FALLBACK_SCALE whose normal passes SECOND_T_N, then all those passing eq. 3;
    where none of those has weight, the points of the 3x3x3 block around x's cell within RING_SCALE times the
    radius with the normal threshold RING_T_N. Weights (radius - d) / radius to the power WEIGHT_POWER."""
    rec = grid.instances[inst]
    slots = np.flatnonzero(grid.cell_instance == inst)
    words = grid.cells[slots, : gf.POINTS_PER_CELL]
    alloc, q, ncode, ao = pw.unpack_point(words)
    cell = gf.key_to_cell(grid.cells[slots, gf.KEY_WORD], rec["dims"])
    p = gf.decode_point_local(np.repeat(cell[:, None, :], 7, axis=1), q, rec["origin"], rec["cell_size"])[alloc]
    point_cell = np.repeat(cell[:, None, :], 7, axis=1)[alloc]
    n_p = pw.oct_decode(ncode[alloc])
    a = pw.dequantise_ao(ao[alloc])
    r = float(rec["radius"])
    out = []
    for xi, ni in zip(x, n_x):
        d = p - xi
        dist = np.linalg.norm(d, axis=1)
        cosd = np.where(dist > 0, (n_p * d).sum(1) / np.where(dist > 0, dist, 1), 0)
        counts = ((n_p @ ni) > T_N) & (cosd ** 2 < T_D)
        ring = ((n_p @ ni) > gf.RING_T_N) & (cosd ** 2 < T_D)
        block = gf.lookup_block_base(gf.grid_coords(xi, rec["origin"], rec["cell_size"]))
        in_block = np.all((point_cell >= block) & (point_cell <= block + 1), axis=1)
        own = np.floor(gf.grid_coords(xi, rec["origin"], rec["cell_size"])).astype(np.int64)
        in_ring = np.all(np.abs(point_cell - own) <= 1, axis=1)
        first = counts & gf.in_first_step(n_p @ ni, (n_p * d).sum(1), dist * dist, r)
        second = counts & in_block & ((n_p @ ni) > gf.SECOND_T_N)
        wide = r * gf.FALLBACK_SCALE
        for radius, among in ((r, first), (wide, second), (wide, counts & in_block), (r * gf.RING_SCALE, ring & in_ring)):
            w = np.where(among, np.maximum(0, (radius - dist) / radius) ** gf.WEIGHT_POWER, 0)
            if w.sum() > 0:
                break
        out.append((w * a).sum() / w.sum() if w.sum() > 0 else 1.0)
    return np.array(out)


def test_lookup_equals_brute_force_on_random_surfaces():
    rng = np.random.default_rng(0)
    # a folded surface: floor + wall + slanted plane, points with random AO
    m = 6000
    u, v = rng.random(m), rng.random(m)
    kind = rng.integers(0, 3, m)
    p = np.where(kind[:, None] == 0, np.column_stack([u, v, 0 * u]),
                 np.where(kind[:, None] == 1, np.column_stack([u, 0 * u, v]), np.column_stack([u, v, v * 0.5])))
    nrm = np.where(kind[:, None] == 0, [0, 0, 1.0], np.where(kind[:, None] == 1, [0, 1.0, 0], [0, -0.4472136, 0.8944272]))
    grid = Grid.build([(p, nrm, 0.012, 0)])
    t = grid.point_table()
    grid.set_ao(t.slot, t.index, rng.integers(0, 256, len(t)))
    probes = rng.choice(m, 400, replace=False)
    x = p[probes] + rng.normal(scale=0.003, size=(400, 3))
    nx = nrm[probes].astype(np.float32)
    ao, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(400, int), x, nx)
    ref = brute_force(grid, 0, x.astype(np.float32), nx)
    np.testing.assert_allclose(ao, ref, atol=2e-5)
    assert (wsum > 0).mean() > 0.99


def test_fallback_ring_fills_gaps_wider_than_r_and_nothing_beyond_its_radius():
    """Points on a lattice 1.6 r apart: probes in the middle of a square are farther than r from every
    point (a hole for eq. 2-4 alone), the ring finds the four corners; a probe half a radius farther off the
    plane than the ring reaches finds nothing (AO 1)."""
    r_poisson = 0.01
    grid = Grid.build([(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), r_poisson, 0)])
    r = float(grid.instances[0]["radius"])
    u = np.arange(20) * 1.6 * r
    gx, gy = np.meshgrid(u, u)
    p = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    grid = Grid.build([(p, np.tile([0, 0, 1.0], (len(p), 1)), r_poisson, 0)])
    assert float(grid.instances[0]["radius"]) == r
    t = grid.point_table()
    rng = np.random.default_rng(5)
    grid.set_ao(t.slot, t.index, rng.integers(0, 256, len(t)))
    centres = np.column_stack([u[3:15] + 0.8 * r, u[3:15] + 0.8 * r, np.zeros(12)])
    x = np.vstack([centres, [[u[8], u[8], (gf.RING_SCALE + 0.5) * r]]])
    n = np.tile([0, 0, 1.0], (len(x), 1))
    ao, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(len(x), int), x, n)
    assert np.all(np.linalg.norm(t.local_pos[None, :, :] - centres[:, None, :], axis=2).min(axis=1) > r)
    assert np.all(wsum[:-1] > 0) and wsum[-1] == 0 and ao[-1] == 1.0
    np.testing.assert_allclose(ao, brute_force(grid, 0, x.astype(np.float32), n.astype(np.float32)), atol=2e-5)


def test_no_points_gives_one_and_outside_grid_is_safe():
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.random(500), rng.random(500), np.zeros(500)])
    grid = Grid.build([(p, np.tile([0, 0, 1.0], (500, 1)), 0.02, 0)])
    x = np.array([[5.0, 5.0, 5.0], [-3, 0.5, 0], [0.5, 0.5, 0.0]])
    n = np.tile([0, 0, 1.0], (3, 1))
    ao, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(3, int), x, n)
    assert ao[0] == 1.0 and ao[1] == 1.0 and wsum[0] == 0
    assert wsum[2] > 0


def test_back_side_points_are_ignored():
    rng = np.random.default_rng(2)
    p = np.column_stack([rng.random(2000), rng.random(2000), np.zeros(2000)])
    up = np.tile([0, 0, 1.0], (1000, 1))
    back = np.arange(2000) >= 1000
    grid = Grid.build([(p, np.vstack([up, -up]), 0.017, gf.FLAG_DOUBLE_SIDED, back)])
    keys = grid.cells[grid.allocated_cells(), gf.KEY_WORD]
    assert ((keys & gf.BACK_BIT) != 0).any() and ((keys & gf.BACK_BIT) == 0).any()
    t = grid.point_table()
    ao_code = np.where(t.local_normal[:, 2] > 0, 255, 0)
    grid.set_ao(t.slot, t.index, ao_code)
    x = np.column_stack([rng.random(100) * 0.8 + 0.1, rng.random(100) * 0.8 + 0.1, np.zeros(100)])
    top, w_top = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(100, int), x, np.tile([0, 0, 1.0], (100, 1)))
    bottom, w_bot = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(100, int), x, np.tile([0, 0, -1.0], (100, 1)))
    # (random, not Poisson, points leave some probes without neighbours: those fall back to 1)
    assert (w_top > 0).mean() > 0.6 and (w_bot > 0).mean() > 0.6
    assert np.all(top[w_top > 0] == 1.0) and np.all(bottom[w_bot > 0] == 0.0)
    # With the side flagged (the G-buffer's back-side bit, the shader's one-key lookup) the result is
    # the same as scanning both keys and letting eq. 3's normal test pick the side.
    ones, zeros = np.ones(100, bool), np.zeros(100, bool)
    for nz, back, ao, w in ((1.0, zeros, top, w_top), (-1.0, ones, bottom, w_bot)):
        ao1, w1 = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(100, int), x,
                                 np.tile([0, 0, nz], (100, 1)), back=back)
        np.testing.assert_array_equal(ao1, ao)
        np.testing.assert_array_equal(w1, w)
    # The wrong side flagged finds only points facing away: no weight at all.
    _, w_wrong = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(100, int), x,
                                np.tile([0, 0, 1.0], (100, 1)), back=ones)
    assert np.all(w_wrong == 0)


def test_ring_takes_the_face_across_a_sharp_edge_but_not_a_surface_facing_away():
    """Points only on a floor (normal +z) of one instance. Probes on a wall standing on it (normal +x) near
    the edge find no point passing eq. 3's normal test in the 2x2x2 block; the ring's looser threshold
    (RING_T_N) takes the floor's points there, as brute force does. Probes under the floor (normal -z)
    face its points exactly away and find nothing."""
    rng = np.random.default_rng(7)
    m = 4000
    p = np.column_stack([rng.random(m), rng.random(m), np.zeros(m)])
    grid = Grid.build([(p, np.tile([0, 0, 1.0], (m, 1)), 0.01, 0)])
    t = grid.point_table()
    grid.set_ao(t.slot, t.index, rng.integers(0, 256, len(t)))
    r = float(grid.instances[0]["radius"])
    k = 200
    wall = np.column_stack([np.full(k, 0.5), rng.random(k) * 0.8 + 0.1, rng.random(k) * 0.5 * r])
    under = np.column_stack([rng.random(k) * 0.8 + 0.1, rng.random(k) * 0.8 + 0.1, np.zeros(k)])
    x = np.vstack([wall, under])
    n = np.vstack([np.tile([1.0, 0, 0], (k, 1)), np.tile([0, 0, -1.0], (k, 1))]).astype(np.float32)
    ao, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(2 * k, int), x, n)
    assert np.all(((t.local_normal @ [1.0, 0, 0]) <= T_N))  # eq. 3 alone would leave every wall probe a hole
    assert (wsum[:k] > 0).mean() > 0.9 and np.all(wsum[k:] == 0) and np.all(ao[k:] == 1.0)
    np.testing.assert_allclose(ao, brute_force(grid, 0, x.astype(np.float32), n), atol=2e-5)


def test_first_step_keeps_the_other_face_of_a_crease_out():
    """A floor (AO 1) meeting a wall (AO 0): floor probes within r of the wall take only the floor's
    points (the wall's normal fails FIRST_T_N though it passes eq. 3's T_N), so they read 1, not a blend."""
    rng = np.random.default_rng(11)
    m = 3000
    floor = np.column_stack([rng.random(m), rng.random(m) * 0.5 + 0.5, np.zeros(m)])
    wall = np.column_stack([rng.random(m), np.full(m, 0.5), rng.random(m) * 0.5])
    up, side = np.tile([0, 0, 1.0], (m, 1)), np.tile([0, 0.6, 0.8], (m, 1))  # 53 degrees apart: cos 0.8
    grid = Grid.build([(np.vstack([floor, wall]), np.vstack([up, side]), 0.01, 0)])
    t = grid.point_table()
    grid.set_ao(t.slot, t.index, np.where(t.local_normal[:, 1] > 0.1, 0, 255))
    r = float(grid.instances[0]["radius"])
    x = np.column_stack([rng.random(200) * 0.8 + 0.1, 0.5 + rng.random(200) * 0.5 * r, np.full(200, 1e-4)])
    ao, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.zeros(200, int), x, np.tile([0, 0, 1.0], (200, 1)))
    assert gf.T_N < 0.8 < gf.FIRST_T_N
    found = wsum > 0
    assert found.mean() > 0.9 and np.all(ao[found] == 1.0)
