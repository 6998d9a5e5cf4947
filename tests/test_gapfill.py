"""Gap filling (psao.server.points.gapfill): fewer holes, added points on the surface, the two sides of a
double-sided instance kept aligned, the k-d pre-test never claims coverage the lookup does not give."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from psao.protocol.reconstruct import reconstruct_ao
from psao.server.bake import build_scene_grid, sample_probes
from psao.server.points.gapfill import decoded_points, fill_gaps, first_step_covered, kd_covered, surface_candidates, thin
from psao.server.settings import GapFillSettings
from psao.server.points.generate import generate_scene_points
from psao.server.settings import PointSettings

DENSITY = 64.0


@pytest.fixture(scope="module")
def scene(cornell_double_block):
    """Cornell box with its tall block made double-sided, so both point layouts are exercised."""
    return cornell_double_block


def builder(scene):
    return lambda sets: build_scene_grid(scene, sets)


def holes(grid, probes) -> float:
    _, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, probes.instance, probes.local_pos, probes.local_normal)
    return float((wsum == 0).mean())


def cut_disc(ps, radius_in_poisson_radii: float):
    """The point set without its points within that many Poisson radii of its middle point: a gap wider
    than the lookup's fallback ring, which only added points can cover."""
    centre = ps.positions[np.argsort(np.linalg.norm(ps.positions - ps.positions.mean(axis=0), axis=1))[0]]
    keep = np.linalg.norm(ps.positions - centre, axis=1) > radius_in_poisson_radii * ps.poisson_radius
    return dataclasses.replace(ps, positions=ps.positions[keep], normals=ps.normals[keep], faces=ps.faces[keep],
                               barycentrics=ps.barycentrics[keep], back=ps.back[keep])


def test_gap_fill_reduces_holes_and_keeps_points_on_the_surface(scene):
    build = builder(scene)
    before = generate_scene_points(scene, PointSettings(density=DENSITY))
    before[0] = cut_disc(before[0], 7.0)  # the floor (one-sided)
    grid0 = build(before)
    after, grid1, added = fill_gaps(scene, before, grid0, build, GapFillSettings(passes=4, ratio=4.0))
    probes = sample_probes(scene, 20000, seed=4242)  # not the candidates' seed
    h0, h1 = holes(grid0, probes), holes(grid1, probes)
    assert added > 0 and h0 > 0.002
    assert h1 < 0.5 * h0, f"holes {h0:.4%} -> {h1:.4%}"
    assert added < 0.1 * sum(len(ps) for ps in before)  # a fill, not a second point set
    for inst, ps0, ps in zip(scene.instances, before, after):
        mesh = scene.meshes[inst.mesh]
        tri = mesh.vertices[mesh.faces[ps.faces]]
        on_tri = np.einsum("pk,pkj->pj", ps.barycentrics.astype(np.float64), tri)
        assert np.abs(on_tri - ps.positions).max() < 1e-6  # on the triangle the point names
        if mesh.double_sided:
            front, back = ~ps.back, ps.back
            assert front.sum() == back.sum()  # every point has its twin on the other side
            np.testing.assert_array_equal(ps.positions[front], ps.positions[back])
            np.testing.assert_array_equal(ps.normals[front], -ps.normals[back])
            old = ps.positions[front][: int((~ps0.back).sum())]
            np.testing.assert_array_equal(old, ps0.positions[~ps0.back])  # old front points first
        else:
            np.testing.assert_array_equal(ps.positions[: len(ps0)], ps0.positions)


def test_gap_fill_off_changes_nothing(scene):
    build = builder(scene)
    before = generate_scene_points(scene, PointSettings(density=DENSITY))
    grid0 = build(before)
    after, grid1, added = fill_gaps(scene, before, grid0, build, GapFillSettings(passes=0))
    assert added == 0 and grid1 is grid0 and all(a is b for a, b in zip(after, before))


def test_kd_pretest_is_stricter_than_the_lookup(scene):
    """Wherever the k-d pre-test says covered, the exact lookup finds a point too."""
    build = builder(scene)
    grid = build(generate_scene_points(scene, PointSettings(density=DENSITY)))
    table = grid.point_table()
    rng = np.random.default_rng(5)
    checked = 0
    for i in range(len(scene.instances)):
        cand = surface_candidates(scene, i, 1.0, 3000, rng)
        ok = kd_covered(*decoded_points(grid, table, i), cand.local_pos, cand.local_normal,
                        float(grid.instances[i]["radius"]))
        _, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, np.full(ok.sum(), i),
                                 cand.local_pos[ok], cand.local_normal[ok])
        assert (wsum > 0).all()
        checked += int(ok.sum())
    assert checked > 10000


def test_thin_keeps_points_apart():
    pos = np.random.default_rng(1).random((2000, 3))
    keep = thin(pos, 0.05)
    from scipy.spatial import cKDTree
    assert 0 < len(keep) < len(pos)
    assert len(cKDTree(pos[keep]).query_pairs(0.05)) == 0
    assert len(thin(pos[:1], 0.05)) == 1 and len(thin(pos[:0], 0.05)) == 0




def first_step_gaps(grid, probes) -> float:
    """Fraction of probes where the lookup's first step (radius r, FIRST_T_N) finds no point."""
    table = grid.point_table()
    missing = 0
    for i in np.unique(probes.instance):
        sel = probes.instance == i
        covered = first_step_covered(*decoded_points(grid, table, i), probes.local_pos[sel],
                                     probes.local_normal[sel], float(grid.instances[i]["radius"]))
        missing += int((~covered).sum())
    return missing / len(probes.instance)


def test_first_step_gap_fill_gives_small_faces_points_of_their_own(scene):
    """With first_step the fill adds points where the first step finds none although the whole lookup
    finds weight (at its 2r step): such places get far fewer, and the plain fill adds none of them."""
    build = builder(scene)
    before = generate_scene_points(scene, PointSettings(density=DENSITY))
    grid0 = build(before)
    probes = sample_probes(scene, 20000, seed=4242)
    _, plain_grid, plain_added = fill_gaps(scene, before, grid0, build, GapFillSettings(passes=2))
    after, grid1, added = fill_gaps(scene, before, grid0, build, GapFillSettings(passes=2, first_step=True))
    g0, g1 = first_step_gaps(grid0, probes), first_step_gaps(grid1, probes)
    assert holes(grid0, probes) < 0.5 * g0  # most first-step gaps are not holes: the 2r step answers
    assert added > plain_added and g0 > 0.001
    assert g1 < 0.5 * g0, f"first-step gaps {g0:.4%} -> {g1:.4%}"
    assert added < 0.2 * sum(len(ps) for ps in before)
