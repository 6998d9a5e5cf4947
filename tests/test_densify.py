"""Densify (psao.server.points.densify): points added where the lookup misses the traced AO lower the error at
fresh probes, drop nothing, sit on their triangles under the ids the server uses, carry the AO of their
own ids' rays, and leave double-sided instances and quick low-ray bakes as they were."""
from __future__ import annotations


import numpy as np
import pytest

from psao.protocol import pointword as pw
from psao.protocol.reconstruct import reconstruct_ao
from psao.server.bake import bake_scene, sample_probes
from psao.server.geometry import grid_world_points, scene_point_ids
from psao.server.points.buried import visible_probes
from psao.server.settings import BakeSettings, DensifySettings, TraceSettings

DENSITY = 48.0
RAYS = 64


@pytest.fixture(scope="module")
def scene(cornell_double_block):
    """Cornell box with its tall block double-sided: densify must leave that instance's points alone."""
    return cornell_double_block


@pytest.fixture(scope="module")
def bakes(scene):
    """(plain, densified) bakes of the same points and rays."""
    out = []
    for rounds in (0, 3):
        out.append(bake_scene(scene, BakeSettings(density=DENSITY, rays=RAYS, workers=1,
                                                  densify=DensifySettings(rounds=rounds)), show_progress=False))
    yield out
    for res in out:
        res.tracer.close()


def lookup_mae(res, scene, probes, truth) -> float:
    g = res.grid
    ao, _ = reconstruct_ao(g.instances, g.buckets, g.cells, probes.instance, probes.local_pos, probes.local_normal)
    return float(np.abs(ao - truth).mean())


def test_densify_lowers_the_error_at_fresh_probes_and_drops_nothing(scene, bakes):
    plain, dense = bakes
    added = dense.stats["points_densify"]
    assert plain.stats["points_densify"] == 0 and added > 0
    assert dense.stats["points_kept"] == plain.stats["points_kept"] + added
    assert dense.stats["points_dropped_overflow"] == plain.stats["points_dropped_overflow"] == 0
    probes = visible_probes(scene, sample_probes(scene, 6000, seed=4242))  # not the candidates' seed
    truth = plain.tracer.visibility(probes.world_pos, probes.world_normal, np.arange(len(probes.instance)) + (1 << 30),
                                    TraceSettings(rays=512, ao_distance=scene.ao_distance, seed=77))
    before, after = lookup_mae(plain, scene, probes, truth), lookup_mae(dense, scene, probes, truth)
    assert after < 0.9 * before, f"MAE {before:.4f} -> {after:.4f}"


def test_added_points_sit_on_their_triangles_under_the_servers_ids(scene, bakes):
    plain, dense = bakes
    table = dense.grid.point_table()
    ids = np.concatenate(scene_point_ids(dense.pointsets))
    np.testing.assert_array_equal(np.sort(table.point_id), ids)  # every point once, ids 0..P-1
    first = np.concatenate([[0], np.cumsum([len(ps) for ps in dense.pointsets])])
    for i, (inst, ps0, ps) in enumerate(zip(scene.instances, plain.pointsets, dense.pointsets)):
        mesh = scene.meshes[inst.mesh]
        np.testing.assert_array_equal(ps.positions[: len(ps0)], ps0.positions)  # old points first, unchanged
        if mesh.double_sided:
            assert len(ps) == len(ps0)  # not densified
        tri = mesh.vertices[mesh.faces[ps.faces]]
        on_tri = np.einsum("pk,pkj->pj", ps.barycentrics.astype(np.float64), tri)
        assert np.abs(on_tri - ps.positions).max() < 1e-6
        mine = (table.point_id >= first[i]) & (table.point_id < first[i + 1])
        np.testing.assert_allclose(table.local_pos[mine], ps.positions[table.point_id[mine] - first[i]], atol=1e-9)


def test_every_point_carries_the_ao_of_its_own_ids_rays(scene, bakes):
    """A trace of every point under its final id gives exactly the stored AO: the server's later traces
    of an unchanged point change nothing."""
    _, dense = bakes
    t, pos, nrm = grid_world_points(dense.grid, scene)
    vis = dense.tracer.visibility(pos, nrm, t.point_id, TraceSettings(rays=RAYS, ao_distance=scene.ao_distance,
                                                                      seed=BakeSettings.seed))
    np.testing.assert_array_equal(pw.quantise_ao(vis), t.ao_code)


def test_a_quick_low_ray_bake_is_not_densified(scene, bakes):
    res = bake_scene(scene, BakeSettings(density=DENSITY, rays=DensifySettings.min_rays - 1, workers=1,
                                         densify=DensifySettings(rounds=3)), show_progress=False)
    try:
        assert res.stats["points_densify"] == 0
        assert res.stats["points_kept"] == bakes[0].stats["points_kept"]
    finally:
        res.tracer.close()


def test_bad_densify_settings_are_refused():
    from psao.server.errors import ConfigError

    for bad in (dict(rounds=-1), dict(ratio=0.0), dict(threshold=0.0), dict(spacing=-1.0)):
        with pytest.raises(ConfigError, match="densify"):
            BakeSettings(densify=DensifySettings(**bad)).check()


def test_quiet_candidates_are_those_the_lookup_cannot_miss():
    """A floor of evenly spread points: candidates where every point near them has one AO are quiet; those
    near a step in the AO, or with no point of their own orientation within r, are not."""
    from psao.server.points.densify import quiet

    r = 0.1
    g = np.arange(0.0, 2.0, r / 2)
    xx, yy = np.meshgrid(g, g)
    pts = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    up = np.tile(np.float32([0, 0, 1]), (len(pts), 1))
    ao = np.where(pts[:, 0] < 1.0, 0.3, 0.9).astype(np.float32)  # a step in the AO at x = 1
    cand = np.array([[0.5, 1.0, 0.0], [1.5, 1.0, 0.0], [1.01, 1.0, 0.0], [0.5, 1.0, 0.0]])
    cnrm = np.float32([[0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0]])  # the last faces another way
    settings = DensifySettings()
    assert quiet(pts, up, ao, cand, cnrm, r, settings).tolist() == [True, True, False, False]
    settings.quiet_spread = 0.0  # off: every candidate is traced
    assert not quiet(pts, up, ao, cand, cnrm, r, settings).any()
