"""Point generation: surface placement, counts, density in world units, determinism, elimination quality,
double-sided copies, bad input, and the Warp elimination kernel against a brute-force reference."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from psao.scene.model import Mesh
from psao.server.errors import ConfigError
from psao.server.points.generate import (
    PointSettings,
    elimination_radii,
    generate_points,
    generate_scene_points,
    instance_seed,
    neighbour_graph,
    spawn_uniform,
)
from psao.server.points.elimination import eliminate_csr

SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
HEX = 2.0 * np.sqrt(3.0)


def mesh_of(tm: trimesh.Trimesh, name="m", double_sided=False) -> Mesh:
    return Mesh(name, np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64), double_sided)


def unit_square(double_sided=False) -> Mesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
    return Mesh("square", v, np.array([[0, 1, 2], [0, 2, 3]]), double_sided)


def nn_distance(p: np.ndarray) -> np.ndarray:
    d, _ = cKDTree(p).query(p, k=2)
    return d[:, 1]


def scale(s) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = np.diag(np.broadcast_to(np.asarray(s, dtype=np.float64), (3,)))
    return t


# ---------------------------------------------------------------- placement


def test_points_lie_on_their_triangle_and_on_the_mesh():
    tm = trimesh.creation.icosphere(subdivisions=2, radius=1.3)
    ps = generate_points(mesh_of(tm), np.eye(4), PointSettings(density=300))
    v, f = tm.vertices, tm.faces
    # on the plane of the triangle of origin, and inside it (barycentrics >= 0, summing to 1)
    a, b, c = (v[f[ps.faces, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    assert np.abs(((ps.positions - a) * n).sum(axis=1)).max() < 1e-12
    assert ps.barycentrics.min() >= 0 and np.allclose(ps.barycentrics.sum(axis=1), 1, atol=1e-6)
    rebuilt = sum(ps.barycentrics[:, k : k + 1].astype(np.float64) * v[f[ps.faces, k]] for k in range(3))
    assert np.abs(rebuilt - ps.positions).max() < 1e-6
    # independent check: the nearest point of the whole mesh (trimesh, every point against every triangle)
    # is the point itself (trimesh.proximity would need rtree, which is not installed)
    pts = ps.positions[:200]
    tris = tm.triangles[None].repeat(len(pts), axis=0).reshape(-1, 3, 3)
    closest = trimesh.triangles.closest_point(tris, pts.repeat(len(tm.faces), axis=0))
    dist = np.linalg.norm(closest - pts.repeat(len(tm.faces), axis=0), axis=1).reshape(len(pts), -1).min(axis=1)
    assert dist.max() < 1e-9


def test_normals_are_unit_face_normals():
    tm = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    ps = generate_points(mesh_of(tm), np.eye(4), PointSettings(density=200))
    assert ps.normals.dtype == np.float32 and ps.faces.dtype == np.int64
    assert np.allclose(ps.normals, tm.face_normals[ps.faces], atol=1e-6)
    assert np.allclose(np.linalg.norm(ps.normals, axis=1), 1, atol=1e-6)


def test_spawn_is_area_weighted_and_uniform_in_the_triangle():
    rng = np.random.default_rng(5)
    areas = np.array([1.0, 3.0, 0.0, 6.0])  # a degenerate triangle must never be chosen
    faces, bary = spawn_uniform(rng, areas, 200_000)
    share = np.bincount(faces, minlength=4) / len(faces)
    assert np.allclose(share, areas / areas.sum(), atol=0.005)
    assert share[2] == 0
    # uniform over a triangle: each barycentric has mean 1/3 and P(b0 > 1/2) = 1/4
    assert np.allclose(bary.mean(axis=0), 1 / 3, atol=0.005)
    assert abs((bary[:, 0] > 0.5).mean() - 0.25) < 0.005


# ---------------------------------------------------------------- counts and density


def test_count_is_density_times_area_and_half_the_spawn():
    tm = trimesh.creation.icosphere(subdivisions=3)
    s = PointSettings(density=150)
    ps = generate_points(mesh_of(tm), np.eye(4), s)
    expected = round(150 * tm.area)
    assert len(ps) == expected
    assert ps.spawned == 2 * expected
    assert ps.poisson_radius == pytest.approx(np.sqrt(tm.area / (HEX * expected)))


@pytest.mark.parametrize("s", [3.0, (2.0, 1.0, 1.0), (0.5, 4.0, 1.0)])
def test_scaled_instance_gets_the_density_in_world_units(s):
    sq = unit_square()
    t = scale(s)
    t[:3, 3] = (1e5, -2e5, 3.0)  # the translation changes nothing
    ps = generate_points(sq, t, PointSettings(density=400, seed=3))
    world_area = np.prod(np.broadcast_to(np.asarray(s, dtype=np.float64), (3,))[:2])
    assert len(ps) == round(400 * world_area)
    # positions stay in mesh-local space, radius in local units
    assert ps.positions[:, :2].min() >= 0 and ps.positions[:, :2].max() <= 1 and np.all(ps.positions[:, 2] == 0)
    assert ps.poisson_radius == pytest.approx(np.sqrt(1.0 / (HEX * len(ps))))
    # spacing is even in WORLD units: a world NN distance near the world Poisson radius
    world = ps.positions @ t[:3, :3].T
    assert nn_distance(world).mean() / np.sqrt(world_area / (HEX * len(ps))) > 1.2


def test_tiny_instance_gets_the_minimum_count():
    tm = trimesh.creation.icosphere(subdivisions=1)
    ps = generate_points(mesh_of(tm), scale(1e-3), PointSettings(density=256, min_points=64))
    assert len(ps) == 64 and ps.spawned == 128
    ds = generate_points(mesh_of(tm, double_sided=True), scale(1e-3), PointSettings(density=256, min_points=64))
    assert len(ds) == 128


def test_double_sided_points_exist_on_both_sides():
    s = PointSettings(density=500, seed=9)
    one = generate_points(unit_square(), np.eye(4), s)
    two = generate_points(unit_square(double_sided=True), np.eye(4), s)
    k = len(one)
    assert len(two) == 2 * k and two.spawned == 2 * one.spawned
    assert np.array_equal(two.positions[:k], one.positions) and np.array_equal(two.positions[k:], one.positions)
    assert np.allclose(two.normals[:k], [0, 0, 1]) and np.allclose(two.normals[k:], [0, 0, -1])
    assert np.array_equal(two.faces[k:], two.faces[:k]) and np.array_equal(two.barycentrics[k:], two.barycentrics[:k])
    assert two.poisson_radius == one.poisson_radius  # spacing on each side is what counts


# ---------------------------------------------------------------- determinism


def test_deterministic_for_a_seed_and_different_for_another():
    m = mesh_of(trimesh.creation.icosphere(subdivisions=2))
    s = PointSettings(density=200, seed=1)
    a = generate_points(m, np.eye(4), s)
    b = generate_points(m, np.eye(4), s)
    c = generate_points(m, np.eye(4), s, seed=2)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.faces, b.faces)
    assert len(c) == len(a) and not np.array_equal(a.positions, c.positions)
    assert instance_seed(0, 0) != instance_seed(0, 1) and instance_seed(7, 3) == instance_seed(7, 3)


# ---------------------------------------------------------------- elimination quality


def test_elimination_spreads_points_unlike_a_random_half():
    # on a plane, a random set of P points has ~20% of its nearest-neighbour distances below 0.5 r
    # (Poisson process: 1 - exp(-pi / (8 sqrt 3))); elimination must leave none, and a min spacing
    # far above anything a random subset reaches
    ps = generate_points(unit_square(), np.eye(4), PointSettings(density=4000, seed=4))
    r = ps.poisson_radius
    nn = nn_distance(ps.positions)
    rng = np.random.default_rng(0)
    rand = np.c_[rng.random((len(ps), 2)), np.zeros(len(ps))]
    nn_rand = nn_distance(rand)
    assert (nn_rand < 0.5 * r).mean() > 0.15
    assert (nn < 0.5 * r).mean() == 0
    assert nn.min() > 0.8 * r and nn_rand.min() < 0.1 * r
    assert nn.mean() > 1.3 * r  # a random set has mean NN 0.93 r
    assert nn.std() / nn.mean() < 0.2  # a random set has a CV of NN distance of about 0.52


def test_normal_gate_keeps_both_faces_of_a_thin_slab():
    # two parallel faces 0.01 apart, facing away from each other: far closer than the Poisson radius (~0.03)
    top = unit_square()
    bottom = Mesh("b", top.vertices - [0, 0, 0.01], top.faces[:, ::-1])
    slab = Mesh("slab", np.concatenate([top.vertices, bottom.vertices]), np.concatenate([top.faces, bottom.faces + 4]))
    gated = generate_points(slab, np.eye(4), PointSettings(density=300, seed=2))
    plain = generate_points(slab, np.eye(4), PointSettings(density=300, seed=2, normal_cos_min=-1.0))
    for ps in (gated, plain):
        up = ps.normals[:, 2] > 0
        assert abs(up.mean() - 0.5) < 0.05
    r = gated.poisson_radius
    # with the gate each face is a well-spaced set on its own; without it the faces share one spacing
    # (each face alone has spacing ~sqrt 2 larger, with many close pairs inside one face)
    up = gated.normals[:, 2] > 0
    assert nn_distance(gated.positions[up]).min() > 0.8 * r
    up = plain.normals[:, 2] > 0
    assert nn_distance(plain.positions[up]).min() < 0.5 * r


# ---------------------------------------------------------------- Warp kernel against a brute-force reference


def reference_elimination(positions, normals, d_max, d_min, alpha, normal_cos_min, keep):
    """Brute force: full distance matrix, Yuksel's weights, remove the argmax (ties: lower index) one at a time."""
    n = len(positions)
    diff = positions[:, None, :] - positions[None, :, :]
    dist = np.sqrt((diff * diff).sum(axis=2))
    near = dist < d_max
    np.fill_diagonal(near, False)
    if normal_cos_min > -1.0:
        near &= normals @ normals.T > normal_cos_min
    w = np.where(near, np.power(1.0 - np.maximum(dist, d_min) / d_max, alpha), 0.0)
    weight = [0.0] * n
    for i in range(n):
        for j in np.flatnonzero(near[i]):  # same summation order as the kernel: columns ascending
            weight[i] += w[i, j]
    alive = np.ones(n, dtype=bool)
    for _ in range(n - keep):
        best = max(np.flatnonzero(alive), key=lambda i: (weight[i], -i))
        alive[best] = False
        for j in np.flatnonzero(near[best] & alive):
            weight[j] -= w[best, j]
    return alive


@pytest.mark.parametrize("limiting,gate", [(True, -0.5), (False, -1.0), (True, -1.0)])
def test_kernel_matches_brute_force_reference(limiting, gate):
    # a bent sheet (two planes at 90 degrees) plus a face-down copy close under one of them
    rng = np.random.default_rng(11)
    n = 600
    u = rng.random((n, 2))
    pos = np.where(u[:, :1] < 0.5, np.c_[u[:, 0], u[:, 1], np.zeros(n)], np.c_[np.full(n, 0.5), u[:, 1], u[:, 0] - 0.5])
    nrm = np.where(u[:, :1] < 0.5, [[0.0, 0.0, 1.0]], [[-1.0, 0.0, 0.0]])
    under = rng.random(n) < 0.2
    pos[under] = np.c_[rng.random(under.sum()) * 0.5, rng.random(under.sum()), np.full(under.sum(), -0.01)]
    nrm[under] = [0.0, 0.0, -1.0]
    s = PointSettings(weight_limiting=limiting, normal_cos_min=gate)
    keep = n // 2
    d_max, d_min = elimination_radii(1.0, n, keep, s)
    offsets, nbrs, w = neighbour_graph(pos, nrm, d_max, d_min, s.alpha, s.normal_cos_min)
    got = eliminate_csr(offsets, nbrs, w, keep)
    want = reference_elimination(pos, nrm, d_max, d_min, s.alpha, s.normal_cos_min, keep)
    assert got.sum() == keep
    assert np.array_equal(got, want)


def test_kernel_ties_go_to_the_lower_index_and_keep_all_when_nothing_to_remove():
    # a path 0-1-2-3 with equal edge weights: 1 and 2 weigh most, 1 goes first (lower index);
    # then 2 and 3 tie at 0.5 (0 is at 0) and 2 goes
    offsets = np.array([0, 1, 3, 5, 6])
    nbrs = np.array([1, 0, 2, 1, 3, 2])
    w = np.full(6, 0.5)
    assert eliminate_csr(offsets, nbrs, w, 3).tolist() == [True, False, True, True]
    assert eliminate_csr(offsets, nbrs, w, 2).tolist() == [True, False, False, True]
    assert eliminate_csr(offsets, nbrs, w, 4).all()


# ---------------------------------------------------------------- bad input


def test_bad_input_raises_config_error():
    sq = unit_square()
    with pytest.raises(ConfigError, match=r"density must be > 0, got 0"):
        generate_points(sq, np.eye(4), PointSettings(density=0))
    with pytest.raises(ConfigError, match=r"density must be > 0, got -3"):
        generate_points(sq, np.eye(4), PointSettings(density=-3.0))
    flat = Mesh("flat", np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]), np.array([[0, 1, 2], [0, 0, 1]]))
    with pytest.raises(ConfigError, match="zero surface area"):
        generate_points(flat, np.eye(4), PointSettings())
    with pytest.raises(ConfigError, match="zero surface area"):
        generate_points(sq, scale((1.0, 0.0, 1.0)), PointSettings())
    nan = Mesh("nan", sq.vertices.copy(), sq.faces)
    nan.vertices[2, 0] = np.nan
    with pytest.raises(ConfigError, match="non-finite"):
        generate_points(nan, np.eye(4), PointSettings())
    with pytest.raises(ConfigError, match="no triangles"):
        generate_points(Mesh("e", sq.vertices, np.zeros((0, 3), np.int64)), np.eye(4), PointSettings())
    with pytest.raises(ConfigError, match="4x4"):
        generate_points(sq, np.eye(3), PointSettings())


def test_degenerate_triangles_are_skipped():
    sq = unit_square()
    v = np.concatenate([sq.vertices, [[5, 5, 5], [5, 5, 5]]])
    m = Mesh("d", v, np.concatenate([sq.faces, [[4, 5, 4], [0, 4, 5]]]))  # zero-area triangles
    ps = generate_points(m, np.eye(4), PointSettings(density=300))
    assert len(ps) == 300 and set(np.unique(ps.faces)) <= {0, 1}
    assert np.isfinite(ps.positions).all() and np.isfinite(ps.normals).all()


# ---------------------------------------------------------------- scenes and real meshes


def test_scene_points_one_set_per_instance_seeded_by_index():
    from psao.scene import load_scene

    scene = load_scene("builtin:cornell")
    s = PointSettings(density=2000, seed=5)
    calls = []
    sets = generate_scene_points(scene, s, progress=lambda done, total: calls.append((done, total)))
    assert len(sets) == len(scene.instances) and calls[-1] == (len(sets), len(sets))
    for k, (inst, ps) in enumerate(zip(scene.instances, sets)):
        again = generate_points(scene.meshes[inst.mesh], inst.transform, s, seed=instance_seed(5, k))
        assert np.array_equal(ps.positions, again.positions)


def test_bunny_points_when_present():
    path = SCENES / "bunny" / "stanford-bunny.obj"
    if not path.exists():
        pytest.skip("bunny not present")
    tm = trimesh.load(path, force="mesh")
    ps = generate_points(mesh_of(tm), np.eye(4), PointSettings(density=2e5, detail_factor=1))
    assert len(ps) == round(2e5 * tm.area)
    nn = nn_distance(ps.positions)
    assert nn.min() > 0.7 * ps.poisson_radius


def test_parallel_generation_equals_serial():
    """Instances in worker processes (each with its own buried-surface test): the same points, array for array."""
    from psao.scene import load_scene
    from psao.server.points.buried import BuriedTest
    from psao.server.points.pool import generate_scene_points_parallel

    scene = load_scene("builtin:courtyard")
    s = PointSettings(density=4.0, seed=3)
    serial = generate_scene_points(scene, s, buried=BuriedTest(scene))
    calls = []
    parallel = generate_scene_points_parallel(scene, s, 2, True, progress=lambda done, total: calls.append((done, total)))
    assert len(parallel) == len(serial) == len(scene.instances)
    assert calls[-1] == (len(scene.instances), len(scene.instances))
    for a, b in zip(serial, parallel):
        for name in ("positions", "normals", "faces", "barycentrics", "back"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert (a.poisson_radius, a.spawned) == (b.poisson_radius, b.spawned)


# ---------------------------------------------------------------- detail levels


def folded_and_flat() -> Mesh:
    """One mesh: a flat 1 x 1 square (two triangles, z = -1) and a strip folded like an accordion (x 0..1,
    folds 0.05 apart at right angles, 0.05 deep, 0.2 long in z in four rows): small triangles meeting at
    90 degrees."""
    flat_v = np.array([[0, 0, -1.0], [1, 0, -1], [1, 1, -1], [0, 1, -1]])
    flat_f = np.array([[0, 1, 2], [0, 2, 3]])
    xs = np.arange(21) * 0.05
    ys = (np.arange(21) % 2) * 0.05
    zs = np.arange(5) * 0.05
    v = np.array([[x, y, z] for z in zs for x, y in zip(xs, ys)])
    f = []
    for j in range(4):
        for i in range(20):
            a, b, c, d = j * 21 + i, j * 21 + i + 1, (j + 1) * 21 + i + 1, (j + 1) * 21 + i
            f += [[a, b, c], [a, c, d]]
    return Mesh("folded", np.vstack([flat_v, v + [0, 2, 0]]), np.vstack([flat_f, np.array(f) + 4]).astype(np.int64))


def test_small_triangles_get_the_detail_factor_and_large_ones_the_density():
    from psao.server.points.sampling import DETAIL_POINTS, detail_factors

    mesh = folded_and_flat()
    areas = mesh.triangle_areas()
    factor = detail_factors(areas, 400.0, 4)
    assert 400.0 * areas[0] > DETAIL_POINTS and list(factor[:2]) == [1, 1] and np.all(factor[2:] == 4)
    # the largest power of two that keeps a triangle within DETAIL_POINTS points
    sizes = DETAIL_POINTS * np.array([1.0, 0.6, 0.4, 0.2, 0.01]) / 400.0
    assert list(detail_factors(sizes, 400.0, 4)) == [1, 1, 2, 4, 4]
    assert list(detail_factors(sizes, 400.0, 1)) == [1] * 5
    ps = generate_points(mesh, np.eye(4), PointSettings(density=400.0, seed=2, detail_factor=4))
    on_flat = ps.faces < 2
    assert on_flat.sum() == round(400.0 * areas[:2].sum())
    assert (~on_flat).sum() == round(4 * 400.0 * areas[2:].sum())
    # one level: the paper's uniform density everywhere
    plain = generate_points(mesh, np.eye(4), PointSettings(density=400.0, seed=2))
    assert len(plain) == round(400.0 * areas.sum())
    # the lookup radius follows the mean spacing of all the instance's points
    assert ps.poisson_radius == pytest.approx(np.sqrt(areas.sum() / (HEX * len(ps))))


def test_estimate_equals_generated_points_with_detail_levels():
    from psao.scene.model import Instance, Scene
    from psao.server.points.sampling import estimate_points

    mesh = folded_and_flat()
    scene = Scene("folded", [mesh], [Instance("a", 0, np.eye(4)), Instance("b", 0, scale(2.0))], ao_distance=0.5)
    s = PointSettings(density=100.0, seed=1, detail_factor=4)
    total = sum(len(generate_points(mesh, inst.transform, s)) for inst in scene.instances)
    assert total == estimate_points(scene, 100.0, s.min_points, 4)
    assert total > estimate_points(scene, 100.0, s.min_points, 1)


def test_triangle_areas_match_trimesh_as_placed_by_a_linear_part():
    """Mesh.triangle_areas (the one area formula of sampling, points, probes and gap filling) equals
    trimesh's per-face areas of the mesh as placed, whatever the transform's linear part."""
    tm = trimesh.creation.icosphere(subdivisions=2)
    mesh = mesh_of(tm)
    rng = np.random.default_rng(4)
    linear = rng.normal(size=(3, 3))
    placed = trimesh.Trimesh(tm.vertices @ linear.T, tm.faces, process=False)
    assert np.allclose(mesh.triangle_areas(linear), placed.area_faces, rtol=1e-12)
    assert np.allclose(mesh.triangle_areas(), tm.area_faces, rtol=1e-12)
    assert mesh.area(linear) == pytest.approx(placed.area, rel=1e-12)
