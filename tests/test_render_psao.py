"""The PSAO shader against the Python oracle src/psao/protocol/reconstruct.reconstruct_ao, at the very G-buffer
positions and normals the shader saw; incremental upload against full upload; G-buffer local space."""
from __future__ import annotations

import numpy as np
import pytest
from test_render_gridbuild import floor_and_box_scene, floor_box_grid, server_grid

from psao.protocol.reconstruct import reconstruct_ao
from psao.client.errors import RenderError
from psao.client.render.renderer import FrameRenderer
from psao.client.render.views import path_matrices

TOL = 2.0 / 255.0


def oracle(frame, instances, buckets, cells):
    gb = frame.gbuffer
    m = gb.mask
    ao, wsum = reconstruct_ao(instances, buckets, cells, gb.instance[m], gb.local[m], gb.local_normal[m],
                              back=gb.back_side[m])
    return m, ao, wsum


def assert_matches_oracle(frame, instances, buckets, cells):
    m, ao, wsum = oracle(frame, instances, buckets, cells)
    shader = frame.ao["psao"]
    diff = np.abs(shader[m] - ao)
    assert np.mean(diff <= TOL) >= 0.999, f"max diff {diff.max():.4f}, {np.mean(diff > TOL):.4%} above 2/255"
    assert np.all(shader[~m] == 1.0)
    # The weight sums agree too (relative), and the frame is not trivially all-ones.
    np.testing.assert_allclose(frame.psao_weight[m], wsum, rtol=1e-3, atol=1e-4)
    assert np.std(ao) > 0.03 and np.mean(wsum > 0) > 0.9
    return diff


def test_shader_equals_oracle_on_floor_and_box(ctx):
    scene = floor_and_box_scene()
    grid = floor_box_grid(scene)
    from psao.client.render.views import look_at, perspective

    view, proj = look_at([1.6, 1.2, 1.9], [0, 0.3, 0]), perspective(60, 320 / 180, 0.05, 20)
    with FrameRenderer(scene, (320, 180), "psao", ctx=ctx) as r:
        r.upload_grid(*grid)
        frame = r.render(view, proj)
    assert frame.gbuffer.mask.mean() > 0.3
    assert_matches_oracle(frame, *grid)


def test_back_side_of_a_double_sided_plane_reads_back_side_cells(ctx):
    """A double-sided plane whose front points carry AO 1 and back points AO 0: seen from below, every
    pixel is flagged back-side and finds the back cells; seen from above, the front ones."""
    import dataclasses

    from psao.client.render.views import look_at, perspective
    from psao.scene.model import Instance, Scene
    from psao.server.bake import build_scene_grid
    from psao.server.points.generate import generate_points
    from psao.server.settings import PointSettings
    from test_render_gridbuild import plane_mesh

    mesh = dataclasses.replace(plane_mesh("sheet"), double_sided=True)
    scene = Scene("sheet", [mesh], [Instance("sheet", 0, np.eye(4))], ao_distance=0.5)
    ps = generate_points(mesh, np.eye(4), PointSettings(density=256))
    grid = build_scene_grid(scene, [ps])
    t = grid.point_table()
    grid.set_ao(t.slot, t.index, np.where(t.local_normal[:, 1] > 0, 255, 0).astype(np.uint32))
    arrays = (grid.instances, grid.buckets, grid.cells)
    proj = perspective(60, 4 / 3, 0.05, 20)
    with FrameRenderer(scene, (160, 120), "psao", ctx=ctx) as r:
        r.upload_grid(*arrays)
        for eye, back, expect in (([0.3, -1.5, 0.2], True, 0.0), ([0.3, 1.5, 0.2], False, 1.0)):
            frame = r.render(look_at(eye, [0, 0, 0], up=(0, 0, 1)), proj)
            m = frame.gbuffer.mask
            assert m.mean() > 0.5 and np.all(frame.gbuffer.back_side[m] == back)
            assert_matches_oracle_loose(frame, *arrays)
            found = m & (frame.psao_weight > 0)
            assert found.sum() > 0.9 * m.sum() and np.all(np.abs(frame.ao["psao"][found] - expect) < 1e-6)


def assert_matches_oracle_loose(frame, instances, buckets, cells):
    """Shader equals oracle (without the field-variation check of assert_matches_oracle)."""
    m, ao, _ = oracle(frame, instances, buckets, cells)
    diff = np.abs(frame.ao["psao"][m] - ao)
    assert np.mean(diff <= TOL) >= 0.999


@pytest.mark.parametrize("spec,density,size", [("builtin:cornell", 1024, (320, 240)), ("builtin:courtyard", 64, (640, 360))])
def test_shader_equals_oracle_on_builtin_scenes(ctx, spec, density, size):
    import psao.scene
    scene = psao.scene.load_scene(spec)
    grid = server_grid(scene, density)
    path = psao.scene.scene_camera(scene)
    view, proj = path_matrices(scene, path, path.keys[0].time, size)
    with FrameRenderer(scene, size, "psao", ctx=ctx) as r:
        r.upload_grid(grid.instances, grid.buckets, grid.cells)
        frame = r.render(view, proj)
    assert frame.gbuffer.mask.mean() > 0.5
    assert_matches_oracle(frame, grid.instances, grid.buckets, grid.cells)


def test_gbuffer_local_space_is_consistent_with_transforms(ctx):
    scene = floor_and_box_scene()
    from psao.client.render.views import look_at, perspective

    view, proj = look_at([1.6, 1.2, 1.9], [0, 0.3, 0]), perspective(60, 320 / 180, 0.05, 20)
    with FrameRenderer(scene, (320, 180), "psao", ctx=ctx) as r:
        moved = np.stack([i.transform for i in scene.instances])
        moved[1, :3, 3] += [-0.4, 0.0, 0.3]
        r.set_transforms(moved)
        gb = r.render(view, proj).gbuffer
    ids = gb.instance[gb.mask]
    assert set(np.unique(ids)) == {0, 1} and np.all(gb.instance[~gb.mask] == -1)
    local = gb.local[gb.mask].astype(np.float64)
    world = np.einsum("nij,nj->ni", moved[ids][:, :3, :3], local) + moved[ids][:, :3, 3]
    np.testing.assert_allclose(world, gb.world[gb.mask], atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(gb.local_normal[gb.mask], axis=1), 1.0, atol=1e-5)
    eye_dir = np.linalg.inv(view)[:3, 3] - gb.world[gb.mask]
    assert np.mean(np.sum(gb.normal[gb.mask] * eye_dir, axis=1) > 0) > 0.99  # visible faces face the camera


def test_shader_equals_oracle_in_every_lookup_step(ctx):
    """An L of two quads in one mesh, sparse random points (about 2 r apart) on the floor only, a third
    with the floor's normal, a third tilted to a cosine between SECOND_T_N and FIRST_T_N and a third to one
    between T_N and SECOND_T_N. Each of the lookup's four steps answers some floor pixels: the block's
    points within r on the fragment's face, else those within 2 r with a normal within SECOND_T_N, else
    those within 2 r that pass eq. 3 alone, else the 3x3x3 ring; wall pixels near the floor are answered by
    the ring's looser normal test (the floor's points across the edge) and the rest of the wall finds
    nothing. The shader agrees with the oracle on the pixels of each step, weight sums included."""
    from psao.protocol import gridformat as gf
    from psao.protocol import pointword as pw
    from psao.protocol.reconstruct import reconstruct_chunk
    from psao.client.render.views import look_at, perspective
    from psao.scene.model import Instance, Mesh, Scene
    from psao.server.grid import Grid

    v = np.array([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2], [-2, 2, -2], [2, 2, -2]], dtype=float)
    faces = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 5], [0, 5, 4]], dtype=np.int64)  # floor y = 0, wall z = -2
    scene = Scene("sparse", [Mesh(name="sparse", vertices=v, faces=faces)], [Instance("sparse", 0, np.eye(4))], ao_distance=0.5)
    rng = np.random.default_rng(11)
    r_poisson = 0.02  # lookup radius r = 0.04
    n = int(16.0 / (2.2 * 0.04) ** 2)  # mean spacing about 2.2 r over the 4 x 4 floor
    pos = np.column_stack([rng.uniform(-2, 2, n), np.zeros(n), rng.uniform(-2, 2, n)])
    # The point normals the grid can store (octahedral codes) that lean about x only, so the wall
    # (normal +z) sees every floor point at cosine 0 and is answered by the ring alone, as before.
    table = pw.oct_decode(np.arange(pw.NORMAL_CODES, dtype=np.uint32))
    in_xy = table[np.abs(table[:, 2]) < 1e-6]
    tilted = [in_xy[(in_xy[:, 1] > lo) & (in_xy[:, 1] < hi)] for lo, hi in ((gf.SECOND_T_N, gf.FIRST_T_N), (gf.T_N, gf.SECOND_T_N))]
    assert all(len(t) for t in tilted)
    kinds = rng.integers(0, 3, n)
    normals = np.tile([0, 1.0, 0], (n, 1))
    for kind, choices in enumerate(tilted, start=1):
        sel = kinds == kind
        normals[sel] = choices[rng.integers(0, len(choices), sel.sum())]
    grid = Grid.build([(pos, normals, r_poisson, 0)])
    t = grid.point_table()
    grid.set_ao(t.slot, t.index, rng.integers(0, 256, len(t)).astype(np.uint32))
    arrays = (grid.instances, grid.buckets, grid.cells)
    with FrameRenderer(scene, (200, 150), "psao", ctx=ctx) as r:
        r.upload_grid(*arrays)
        frame = r.render(look_at([0.2, 0.5, -1.4], [0.2, 0.05, -2.0], up=(0, 1, 0)), perspective(70, 4 / 3, 0.02, 20))
    m, ao, wsum = oracle(frame, *arrays)
    gb = frame.gbuffer
    (_, w_r), (_, w_near), (_, w_wide) = reconstruct_chunk(*arrays, gb.instance[m].astype(np.int64), gb.local[m],
                                                            gb.local_normal[m], gf.T_N, gf.T_D, gb.back_side[m])
    wall = gb.local_normal[m][:, 2] > 0.5
    # Pixels where the steps' point sets differ: the 2 r steps and eq. 3 alone answer differently there.
    mixed = (w_r == 0) & (w_near > 0) & (w_wide > w_near)
    steps = {"r": w_r > 0, "2r with SECOND_T_N": (w_r == 0) & (w_near > 0), "2r, both 2r steps' points": mixed,
             "2r with eq. 3 alone": (w_near == 0) & (w_wide > 0), "ring": (w_wide == 0) & (wsum > 0) & ~wall,
             "ring across the edge": wall & (wsum > 0), "none": wsum == 0}
    assert m.mean() > 0.9 and all(sel.mean() > 0.005 for sel in steps.values()), {k: v.mean() for k, v in steps.items()}
    diff = np.abs(frame.ao["psao"][m] - ao)
    for name, sel in steps.items():
        assert np.mean(diff[sel] <= TOL) >= 0.995, f"{name}: {np.mean(diff[sel] > TOL):.3%} above 2/255"
        np.testing.assert_allclose(frame.psao_weight[m][sel], wsum[sel], rtol=1e-3, atol=1e-4, err_msg=name)


def test_incremental_update_equals_full_upload(ctx):
    import psao.scene
    scene = psao.scene.load_scene("builtin:cornell")
    grid = server_grid(scene, 1024)
    path = psao.scene.scene_camera(scene)
    view, proj = path_matrices(scene, path, path.keys[0].time, (160, 120))
    rng = np.random.default_rng(3)
    with FrameRenderer(scene, (160, 120), "psao", ctx=ctx) as inc, FrameRenderer(scene, (160, 120), "psao", ctx=ctx) as full:
        inc.upload_grid(grid.instances, grid.buckets, grid.cells)
        for step in range(3):
            table = grid.point_table()
            pick = rng.choice(len(table), size=len(table) // 5, replace=False)
            grid.set_ao(table.slot[pick], table.index[pick], rng.integers(0, 256, len(pick)).astype(np.uint32))
            gone = rng.choice(len(table), size=len(table) // 10, replace=False)
            gone = gone[~np.isin(gone, pick)]
            grid.remove_points(table.slot[gone], table.index[gone])
            # New points (forces new cells and, on the last step, a capacity growth).
            inst = int(rng.integers(len(scene.instances)))
            lo, hi = table.local_pos[table.instance == inst].min(0), table.local_pos[table.instance == inst].max(0)
            n_new = 4000 if step == 2 else 300
            pos = lo + rng.random((n_new, 3)) * (hi - lo)
            nrm = rng.normal(size=(n_new, 3))
            grid.insert_points(inst, pos, nrm / np.linalg.norm(nrm, axis=1, keepdims=True), rng.integers(0, 256, n_new).astype(np.uint32))
            b, c = grid.take_dirty()
            inc.update_grid(b, grid.buckets[b], c, grid.cells[c], len(grid.cells))
        assert len(inc.grid.cells) == len(grid.cells)
        got = inc.grid.read_back()
        np.testing.assert_array_equal(got[1], grid.buckets)
        np.testing.assert_array_equal(got[2], grid.cells)
        full.upload_grid(grid.instances, grid.buckets, grid.cells)
        a, b = inc.render(view, proj), full.render(view, proj)
    np.testing.assert_array_equal(a.ao["psao"], b.ao["psao"])


def test_update_writes_only_the_dirty_rows(ctx):
    scene = floor_and_box_scene()
    instances, buckets, cells = floor_box_grid(scene)
    with FrameRenderer(scene, (64, 36), "psao", ctx=ctx) as r:
        r.upload_grid(instances, buckets, cells)
        before = r.grid.bytes_uploaded
        cells = cells.copy()
        cells[[3, 200], 0] ^= 0x1  # flip one AO bit in two far-apart cells
        r.update_grid([5], buckets[[5]], [3, 200], cells[[3, 200]], len(cells))
        assert r.grid.bytes_uploaded - before == 64 + 2 * 32
        np.testing.assert_array_equal(r.grid.read_back()[2], cells)


def test_bad_grid_input_is_one_line_error(ctx):
    scene = floor_and_box_scene()
    instances, buckets, cells = floor_box_grid(scene)
    with FrameRenderer(scene, (64, 36), "psao", ctx=ctx) as r:
        with pytest.raises(RenderError, match="instance records"):
            r.upload_grid(instances[:1], buckets, cells)
        r.upload_grid(instances, buckets, cells)
        with pytest.raises(RenderError, match="cell slot index"):
            r.update_grid([], buckets[:0], [len(cells) + 5], cells[:1], len(cells))
        with pytest.raises(RenderError, match="transforms have shape"):
            r.set_transforms(np.eye(4)[None])
