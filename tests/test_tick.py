"""The server tick against brute force: a static scene costs nothing after the first sync, skipping is
right (a full re-trace agrees within the threshold), rigid motion leaves point words alone, skinned
points are traced on their deformed triangles while the grid keeps them in the rest pose, the view
restricts tracing, and the same time gives the same AO."""
import numpy as np
import pytest

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.scene.camera import look_at, perspective
from psao.scene.skinning import skin_points_reference
from psao.server.tick.selection import frustum_planes, in_frustum



def full_retrace_codes(tick, t):
    """AO codes of every point the tick holds, traced now at time t with the tick's own tracer."""
    ids = np.flatnonzero(tick.present())
    frame = tick.animator.frame(t)
    pos, nrm = tick.world_points(frame, ids)
    tick.tracer.set_dynamic(frame.dynamic_vertices, frame.dynamic_faces)
    return ids, pw.quantise_ao(tick.tracer.visibility(pos, nrm, ids, tick.trace_settings)).astype(np.int64)


def stored_codes(tick, ids):
    return (tick.grid.cells[tick.slot[ids], tick.index[ids]] & 0xFF).astype(np.int64)


@pytest.mark.parametrize("baked_time", [0.0, None])
def test_static_scene_traces_nothing_after_first_sync(make_tick, baked_time):
    tick, bake = make_tick("cornell", density=64, baked_time=baked_time)
    try:
        first = tick(bake.grid, 0.0)
        assert first.traced == (0 if baked_time is not None else first.considered)
        bake.grid.take_dirty()
        for t in (0.1, 0.5, 3.0):
            s = tick(bake.grid, t)
            assert s.traced == 0 and s.changed == 0 and s.cells_dirty == 0
            b, c = bake.grid.take_dirty()
            assert len(b) == 0 and len(c) == 0
    finally:
        tick.close()


def test_courtyard_skipped_points_agree_with_full_retrace(make_tick):
    tick, bake = make_tick("courtyard")
    try:
        for t in (0.4, 0.8):
            s = tick(bake.grid, t)
        assert 0 < s.traced < s.considered // 5, s
        ids, full = full_retrace_codes(tick, 0.8)
        diff = np.abs(stored_codes(tick, ids) - full)
        assert diff.max() <= tick.settings.threshold, f"max |stored - full| = {diff.max()} codes"
        # and the skipping was real: the points near the boulders changed more than the threshold
        assert s.changed > 0
    finally:
        tick.close()


def test_same_time_twice_gives_no_update(make_tick):
    tick, bake = make_tick("courtyard")
    try:
        tick(bake.grid, 1.0)
        bake.grid.take_dirty()
        s = tick(bake.grid, 1.0)
        assert s.traced == 0 and s.changed == 0 and s.cells_dirty == 0  # nothing moved since: nothing to trace
    finally:
        tick.close()


def rigid_words(tick, inst):
    cells = np.flatnonzero(tick.grid.cell_instance == inst)
    return cells, tick.grid.cells[cells].copy()


def test_rigid_motion_keeps_point_words(make_tick):
    tick, bake = make_tick("courtyard")
    try:
        rolling = tick.kinds.rigid
        assert len(rolling) == 3
        before = {i: rigid_words(tick, i) for i in rolling}
        t0 = tick.transforms().copy()
        for t in (0.5, 1.0, 2.0):
            tick(bake.grid, t)
        assert not np.allclose(tick.transforms()[rolling], t0[rolling])  # they did move
        for i in rolling:
            cells, words = before[i]
            cells2, words2 = rigid_words(tick, i)
            np.testing.assert_array_equal(cells, cells2)  # no cell allocated or freed
            np.testing.assert_array_equal(words2[:, 7], words[:, 7])  # keys
            # position and normal bits unchanged; only the AO byte may change (the floor under it)
            np.testing.assert_array_equal(words2[:, :7] & 0xFFFFFF00, words[:, :7] & 0xFFFFFF00)
    finally:
        tick.close()


def test_far_rigid_motion_dirties_nothing(make_tick):
    """builtin:space: the tumbling asteroids are far from everything: no cell is dirtied by their motion."""
    tick, bake = make_tick("space", density=8)
    try:
        for t in (1.0, 2.0, 5.0):
            s = tick(bake.grid, t)
            assert s.traced == 0 and s.cells_dirty == 0
        assert not np.allclose(tick.transforms()[tick.kinds.rigid], tick.animator.transforms(0.0)[tick.kinds.rigid])
    finally:
        tick.close()


def test_skinned_points_follow_their_triangles(make_tick):
    tick, bake = make_tick("robots")
    try:
        t = 0.73
        tick(bake.grid, t)
        scene = bake.scene
        assert tick.kinds.skinned
        for i in tick.kinds.skinned:
            mesh = scene.meshes[scene.instances[i].mesh]
            ps = bake.pointsets[i]
            skin = mesh.skin
            verts = skin_points_reference(skin.skinning_matrices(t), mesh.vertices, skin.joints, skin.weights)
            tri = verts[mesh.faces[ps.faces]]
            want = np.einsum("pk,pkj->pj", ps.barycentrics.astype(np.float64), tri)
            ids = tick.ids_of[i]
            np.testing.assert_allclose(tick.local_pos[ids], want, atol=1e-9)
            moved = np.linalg.norm(want - ps.positions, axis=1)
            assert moved.max() > 0.05  # the walk really deforms the mesh
            # normals: the skinned triangle's, same side as generated
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            assert (np.einsum("ij,ij->i", n, tick.local_nrm[ids]) > 0.999).all()
    finally:
        tick.close()


def test_the_grid_keeps_skinned_points_in_the_rest_pose(make_tick):
    """At posed times the grid's skinned points are exactly the rest-pose ones the bake generated (exact
    side arrays and the words' position, normal and key bits); only AO bytes change, and no point moves."""
    tick, bake = make_tick("robots")
    try:
        before = bake.grid.cells.copy()
        slot, index = tick.slot.copy(), tick.index.copy()
        written = 0
        for t in (0.05, 0.4, 0.73, 1.3):
            s = tick(bake.grid, t)
            assert s.moved > 0 and s.traced > 0
            written += s.changed
        assert written > 0  # the walk changed AO
        np.testing.assert_array_equal(slot, tick.slot)
        np.testing.assert_array_equal(index, tick.index)
        for i in tick.kinds.skinned:
            ps, ids = bake.pointsets[i], tick.ids_of[i]
            here = tick.present()[ids]
            assert here.sum() >= 0.99 * len(ids)
            s_, k_ = tick.slot[ids[here]], tick.index[ids[here]]
            np.testing.assert_array_equal(bake.grid.point_local[s_, k_], ps.positions[here])
            np.testing.assert_array_equal(bake.grid.point_normal[s_, k_], ps.normals[here].astype(np.float32))
            assert np.abs(tick.local_pos[ids[here]] - ps.positions[here]).max() > 0.05  # traced elsewhere: posed
        keep = ~np.uint32(0xFF)
        np.testing.assert_array_equal(bake.grid.cells[:, :7] & keep, before[:, :7] & keep)
        np.testing.assert_array_equal(bake.grid.cells[:, 7], before[:, 7])
    finally:
        tick.close()


def test_view_selection_traces_inside_and_catches_up_later(make_tick):
    tick, bake = make_tick("courtyard", baked_time=None)
    try:
        cam = look_at((0.0, 1.7, 3.0), (0.0, 1.5, -5.0))
        proj = perspective(50.0, 16 / 9, 0.1, 100.0)
        tick.set_cameras([(cam, proj)])
        s = tick(bake.grid, 0.3)  # first sync, limited to the view
        assert 0 < s.traced < s.considered
        planes = frustum_planes(cam, proj, tick.settings.view.fov_margin)
        every = np.flatnonzero(tick.present())
        inside = in_frustum(tick.world_points(tick.last_frame, every)[0], planes, tick.settings.view.distance_margin)
        assert s.traced == inside.sum()
        np.testing.assert_array_equal(tick.stale[every], ~inside)  # the rest waits for a view
        tick.set_cameras([])  # no camera: everything visible, so the stale points are traced now
        s2 = tick(bake.grid, 0.3)
        assert s2.traced >= (~inside).sum() and not tick.stale.any()
        ids, full = full_retrace_codes(tick, 0.3)
        assert np.abs(stored_codes(tick, ids) - full).max() <= tick.settings.threshold
    finally:
        tick.close()


def test_selection_off_traces_every_visible_point(make_tick):
    tick, bake = make_tick("robots", selection=False)
    try:
        s = tick(bake.grid, 0.2)
        assert s.traced == int(tick.tracked.sum())
        assert len(tick.stats_json()) == 1 and tick.stats_json()[0]["traced"] == s.traced
    finally:
        tick.close()


def test_prepare_writes_nothing_and_apply_writes_it(make_tick):
    """The service may run prepare() in a thread while it reads the grid: prepare must not touch it."""
    tick, bake = make_tick("robots")
    try:
        g = tick.grid
        before = (g.cells.copy(), g.buckets.copy(), g.dirty_cells.copy(), g.dirty_buckets.copy())
        plan = tick.prepare(0.6)
        for a, b in zip(before, (g.cells, g.buckets, g.dirty_cells, g.dirty_buckets)):
            np.testing.assert_array_equal(a, b)
        assert plan.moved > 0 and len(plan.ids) > 0
        s = tick.apply(plan)
        assert s.moved == plan.moved and s.cells_dirty > 0
        assert not np.array_equal(before[0], g.cells)
        np.testing.assert_allclose(tick.transforms(), tick.animator.transforms(0.6).astype(np.float32))
    finally:
        tick.close()


def reinsert_every_point(grid):
    """Take every point out of the grid and put it back, last ids first, so points change places."""
    t = grid.point_table()
    back = (grid.cells[t.slot, gf.KEY_WORD] & gf.BACK_BIT) != 0
    grid.remove_points(t.slot, t.index)
    order = np.argsort(-t.point_id)
    for inst in np.unique(t.instance).tolist():
        sel = order[t.instance[order] == inst]
        grid.insert_points(inst, t.local_pos[sel], t.local_normal[sel], t.ao_code[sel], t.point_id[sel], back=back[sel])


def test_grid_edited_behind_the_ticks_back(make_tick):
    """Points that changed places in the grid outside the tick: the tick notices and finds them again."""
    tick, bake = make_tick("courtyard")
    try:
        tick(tick.grid, 0.3)
        ids = np.flatnonzero(tick.present())
        reinsert_every_point(tick.grid)
        assert (tick.grid.point_id[tick.slot[ids], tick.index[ids]] != ids).any()  # the tick's map is stale
        tick.grid.take_dirty()
        tick(tick.grid, 0.6)
        ids, full = full_retrace_codes(tick, 0.6)
        assert np.abs(stored_codes(tick, ids) - full).max() <= tick.settings.threshold
    finally:
        tick.close()


@pytest.mark.parametrize("name", ["robots", "courtyard"])
def test_world_points_is_each_point_through_its_instance(make_tick, name):
    """world_points (all movers' points in one pass) against a point-by-point reference: a moving
    instance's point through its own transform (normal through the inverse transpose, unit), a static
    point where the bake put it; for any subset of ids, in any order."""
    tick, _ = make_tick(name, density=16, rays=4)
    try:
        for t in (0.0, 0.4):
            tick(tick.grid, t)
        frame = tick.last_frame
        rng = np.random.default_rng(3)
        everyone = np.flatnonzero(tick.present())
        assert tick.moving_point[everyone].any() and not tick.moving_point[everyone].all()
        for ids in (everyone[:0], everyone, rng.permutation(everyone)[:97], rng.choice(everyone, 40)):
            pos, nrm = tick.world_points(frame, ids)
            assert pos.dtype == np.float64 and nrm.dtype == np.float32 and pos.shape == nrm.shape == (len(ids), 3)
            for k, i in enumerate(ids):
                if tick.moving_point[i]:
                    m = np.asarray(frame.transforms[tick.inst_of[i]], np.float64)
                    want_p = m[:3, :3] @ tick.local_pos[i] + m[:3, 3]
                    want_n = np.linalg.inv(m[:3, :3]).T @ tick.local_nrm[i]
                    want_n /= np.linalg.norm(want_n)
                else:
                    want_p, want_n = tick.world_pos[i], tick.world_nrm[i]
                np.testing.assert_allclose(pos[k], want_p, rtol=0, atol=1e-9)
                np.testing.assert_allclose(nrm[k], want_n, rtol=0, atol=2e-6)
    finally:
        tick.close()
