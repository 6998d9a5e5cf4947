"""Tracer back-ends against analytic AO, loops over every back-end available here."""
import numpy as np
import pytest
import trimesh

from psao.server.errors import TracerError
from psao.server.settings import TraceSettings

from psao.server.tracer import available_backends, make_tracer
from psao.server.tracer.base import TracePart
from psao.server.tracer.directions import cosine_directions, ray_origins

BACKENDS = available_backends()


def test_embree_is_available():
    assert "embree" in BACKENDS


def slab(height, size=200.0):
    """Floor at z=0 and a ceiling at z=height, both large single boxes' faces."""
    floor = trimesh.creation.box(extents=(size, size, 1.0))
    floor.apply_translation((0, 0, -0.5))
    ceil = trimesh.creation.box(extents=(size, size, 1.0))
    ceil.apply_translation((0, 0, height + 0.5))
    m = trimesh.util.concatenate([floor, ceil])
    return m.vertices, m.faces


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("ao_distance", [2.0, 4.0])
def test_visibility_under_a_ceiling_is_analytic(backend, ao_distance):
    # Cosine-weighted rays from the floor reach a ceiling at height H within D iff cos(theta) > H / D;
    # P(cos theta > c) = 1 - c^2, so the visibility is (H / D)^2.
    H = 1.0
    v, f = slab(H)
    tracer = make_tracer(backend)
    tracer.set_static(v, f)
    rng = np.random.default_rng(0)
    n = 400
    pos = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    vis = tracer.visibility(pos, nrm, np.arange(n), TraceSettings(rays=256, ao_distance=ao_distance))
    tracer.close()
    assert abs(vis.mean() - (H / ao_distance) ** 2) < 0.01
    assert vis.std() < 0.05


@pytest.mark.parametrize("backend", BACKENDS)
def test_same_point_same_rays_same_answer(backend):
    v, f = slab(1.0)
    tracer = make_tracer(backend)
    tracer.set_static(v, f)
    pos = np.array([[0.3, 0.2, 0.0], [1.0, 1.0, 0.0]])
    nrm = np.tile([0, 0, 1.0], (2, 1))
    s = TraceSettings(rays=32, ao_distance=2.0)
    a = tracer.visibility(pos, nrm, [7, 8], s)
    b = tracer.visibility(pos[::-1], nrm, [8, 7], s)
    tracer.close()
    np.testing.assert_array_equal(a, b[::-1])


def test_backends_agree():
    if "warp" not in BACKENDS:
        pytest.skip("warp back-end not available")
    box = trimesh.creation.box(extents=(2, 2, 2))
    inner = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    m = trimesh.util.concatenate([box, inner])
    rng = np.random.default_rng(1)
    pos = np.column_stack([rng.uniform(-0.9, 0.9, 300), rng.uniform(-0.9, 0.9, 300), np.full(300, -1.0)])
    nrm = np.tile([0, 0, 1.0], (300, 1))
    s = TraceSettings(rays=64, ao_distance=1.5)
    out = {}
    for name in ("embree", "warp"):
        t = make_tracer(name)
        t.set_static(m.vertices, m.faces)
        out[name] = t.visibility(pos, nrm, np.arange(300), s)
        t.close()
    # same rays up to float rounding: nearly all points agree exactly, the rest by a ray or two
    assert np.abs(out["embree"] - out["warp"]).max() <= 2 / 64
    assert (out["embree"] == out["warp"]).mean() > 0.95


def test_directions_are_unit_cosine_distributed_and_in_hemisphere():
    rng = np.random.default_rng(2)
    n = rng.normal(size=(500, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = cosine_directions(np.arange(500), n, 256)
    assert np.allclose(np.linalg.norm(d, axis=2), 1, atol=1e-5)
    cos = (d * n[:, None, :]).sum(axis=2)
    assert cos.min() >= -1e-6
    assert abs(cos.mean() - 2 / 3) < 0.01  # E[cos] under cosine weighting is 2/3


def test_origin_offset_scales_with_magnitude_and_scene():
    p = np.array([[0.0, 0.0, 0.0], [1e5, 0.0, 0.0]])
    n = np.tile([0, 0, 1.0], (2, 1))
    o = ray_origins(p, n, 1.0)
    assert 0 < o[0, 2] < 1e-3
    assert o[1, 2] > o[0, 2] * 10
    assert ray_origins(p * 1e-3, n, 1e-3)[0, 2] == pytest.approx(o[0, 2] * 1e-3, rel=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_dynamic_scene_occludes_and_can_be_replaced(backend):
    v, f = slab(1.0)
    tracer = make_tracer(backend)
    tracer.set_static(v[:8], f[:12])  # floor only
    pos = np.zeros((1, 3))
    nrm = np.array([[0, 0, 1.0]])
    s = TraceSettings(rays=64, ao_distance=2.0)
    assert tracer.visibility(pos, nrm, [0], s)[0] == 1.0
    lid = trimesh.creation.box(extents=(10, 10, 0.1))
    lid.apply_translation((0, 0, 0.5))
    tracer.set_dynamic(lid.vertices, lid.faces)
    assert tracer.visibility(pos, nrm, [0], s)[0] < 0.2
    tracer.set_dynamic(None, np.zeros((0, 3), int))
    assert tracer.visibility(pos, nrm, [0], s)[0] == 1.0
    tracer.close()


def test_warp_ray_kernel_matches_numpy_reference():
    pytest.importorskip("warp")
    from psao.server.tracer.directions import rotation_of
    from psao.server.tracer.kernels import RayBuffers

    rng = np.random.default_rng(3)
    n = rng.normal(size=(300, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = rng.normal(scale=100, size=(300, 3)).astype(np.float32)
    ids = rng.integers(0, 2**40, 300)
    o, d = RayBuffers().rays(p, n, *rotation_of(ids, 5), 64, 2.0)
    # the kernel rotates a table of azimuths instead of calling cos/sin per ray: equal to float rounding
    np.testing.assert_allclose(d, cosine_directions(ids, n, 64, 5).reshape(-1, 3), atol=2e-5)
    np.testing.assert_array_equal(o, np.repeat(ray_origins(p, n, 2.0), 64, axis=0))


def test_numpy_rays_within_the_context_only():
    """numpy_rays(): this thread's rays from numpy (the Warp kernel's directions within float rounding), the
    Warp kernel again after it."""
    from psao.server.tracer import embree

    rng = np.random.default_rng(4)
    n = rng.normal(size=(200, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = rng.normal(scale=10, size=(200, 3)).astype(np.float32)
    ids = np.arange(200)
    s = TraceSettings(rays=16, ao_distance=2.0, seed=1)
    with embree.numpy_rays():
        o, d = embree._chunk_rays(p, n, ids, s, 0)
        assert embree._RAYS.buffers is False
    np.testing.assert_allclose(d, cosine_directions(ids, n, 16, 1).reshape(-1, 3), atol=0)
    assert getattr(embree._RAYS, "buffers", None) is not False
    o2, d2 = embree._chunk_rays(p, n, ids, s, 0)
    np.testing.assert_allclose(d2, d, atol=2e-5)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("rays,slices", [(32, 4), (24, 5)])
def test_slices_of_one_ray_set_add_up_to_its_full_trace(backend, rays, slices):
    """Tracing the interleaved slices of a point's ray set one call each and adding their unoccluded rays
    gives exactly the full trace's count (the same rays), also when the slices are of unequal sizes."""
    rng = np.random.default_rng(4)
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.apply_translation((0.2, 0.1, 0.7))
    m = trimesh.util.concatenate([box, trimesh.creation.box(extents=(8.0, 8.0, 0.2))])
    tracer = make_tracer(backend)
    tracer.set_static(m.vertices, m.faces)
    n = 300
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.full(n, 0.1)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    ids = rng.integers(0, 2**40, n)
    full = TraceSettings(rays=rays, ao_distance=2.0, seed=3)
    whole = np.rint(tracer.visibility(pos, nrm, ids, full) * rays).astype(int)
    total = np.zeros(n, int)
    for k in range(slices):
        s = TraceSettings(rays=rays, ao_distance=2.0, seed=3, slices=slices, slice=k)
        total += np.rint(tracer.visibility(pos, nrm, ids, s) * s.rays_traced).astype(int)
    if rays % slices == 0:  # one call, a slice per point (the budgeted tick's rounds): the same counts
        per_point = rng.integers(0, slices, n)
        s = TraceSettings(rays=rays, ao_distance=2.0, seed=3, slices=slices)
        mixed = tracer.visibility(pos, nrm, ids, s, slice_of=per_point)
        for k in range(slices):
            alone = tracer.visibility(pos[per_point == k], nrm[per_point == k], ids[per_point == k],
                                      TraceSettings(rays=rays, ao_distance=2.0, seed=3, slices=slices, slice=k))
            np.testing.assert_array_equal(mixed[per_point == k], alone)
    tracer.close()
    assert 0 < whole.mean() < rays  # partly occluded: the comparison means something
    np.testing.assert_array_equal(total, whole)


def test_warp_ray_kernel_slice_matches_numpy_reference():
    pytest.importorskip("warp")
    from psao.server.tracer.directions import rotation_of
    from psao.server.tracer.kernels import RayBuffers

    rng = np.random.default_rng(5)
    n = rng.normal(size=(100, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = rng.normal(size=(100, 3)).astype(np.float32)
    ids = rng.integers(0, 2**40, 100)
    _, d = RayBuffers().rays(p, n, *rotation_of(ids, 2), 32, 2.0, first=3, step=4)
    np.testing.assert_allclose(d, cosine_directions(ids, n, 32, 2)[:, 3::4].reshape(-1, 3), atol=2e-5)


@pytest.mark.parametrize("backend,workers", [(b, 1) for b in BACKENDS] + [("embree", 2)])  # workers: Embree's
def test_rigid_meshes_posed_by_transform_trace_like_their_world_triangles(backend, workers):
    """A mesh registered once with set_rigid and placed by a transform (rotation, non-uniform scale,
    translation) occludes exactly like the same triangles handed over in world space, and a pose of None
    leaves it out."""
    v, f = slab(1.0)
    kw = {"workers": workers} if backend == "embree" else {}
    posed, merged = make_tracer(backend, **kw), make_tracer(backend, **kw)
    for t in (posed, merged):
        t.set_static(v[:8], f[:12])  # floor only
    mover = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    posed.set_rigid([(mover.vertices, mover.faces)])
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(-1.5, 1.5, 400), rng.uniform(-1.5, 1.5, 400), np.zeros(400)])
    nrm = np.tile([0, 0, 1.0], (400, 1))
    s = TraceSettings(rays=32, ao_distance=2.0)
    for angle, scale, shift in ((0.3, (1.0, 2.0, 0.5), (0.2, -0.1, 0.6)), (1.2, (0.7, 0.7, 1.5), (-0.4, 0.3, 0.9))):
        c, sn = np.cos(angle), np.sin(angle)
        m = np.eye(4)
        m[:3, :3] = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ np.diag(scale)
        m[:3, 3] = shift
        posed.set_dynamic(None, np.zeros((0, 3), int), m[None])
        merged.set_dynamic(mover.vertices @ m[:3, :3].T + m[:3, 3], mover.faces)
        a = posed.visibility(pos, nrm, np.arange(400), s)
        b = merged.visibility(pos, nrm, np.arange(400), s)
        assert a.min() < 0.8  # the mover is really in the way of some points
        assert np.abs(a - b).max() <= 1.0 / 32 + 1e-6 and np.mean(a != b) < 0.02  # a grazing ray may differ
    posed.set_dynamic(None, np.zeros((0, 3), int), None)
    assert posed.visibility(pos, nrm, np.arange(400), s).min() == 1.0
    posed.close()
    merged.close()


class CountingScene:
    """A real Embree scene that counts the rays it is asked to trace: the culling tests check that the
    movers see few rays, not only that the answers are right (tracing every ray would give those too)."""

    def __init__(self, scene):
        self.scene, self.rays, self.calls = scene, 0, 0

    def run(self, origins, dirs, **kw):
        self.rays += len(origins)
        self.calls += 1
        return self.scene.run(origins, dirs, **kw)


def strip_rays(seed: int, n: int = 2000):
    """(n, positions, settings, origins, directions): 16 rays each of n upward-facing points spread over a
    strip x in [-10, 10], y in [-3, 3] on z = 0 (AO distance 1)."""
    from psao.server.tracer.embree import _chunk_rays

    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-10, 10, n), rng.uniform(-3, 3, n), np.zeros(n)]).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (n, 1))
    s = TraceSettings(rays=16, ao_distance=1.0)
    org, dirs = (a.copy() for a in _chunk_rays(pos, nrm, np.arange(n), s, 0))
    return n, pos, s, org, dirs


def test_rigid_movers_skip_only_rays_that_start_beyond_their_reach():
    """Each rigid mover traces only the rays whose segments reach its posed bounding sphere (mover_rays):
    the answers equal tracing every ray against every posed mover, over a batch where each mover is near
    some points and far from most, one of them sheared (its sphere's radius grows by the largest stretch
    of the map, more than any column's length)."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    from psao.server.tracer.embree import EmbreeScenes as _Scenes, _device

    v, f = slab(1.5)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    box = trimesh.creation.box(extents=(0.6, 0.3, 0.5))
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, :3, :3] = np.array([[1.0, 3.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # a shear
    poses[0, :3, 3] = (-6.0, 0.0, 0.5)
    poses[1, :3, :3] = np.diag((1.0, 2.0, 0.5))
    poses[1, :3, 3] = (5.0, 1.0, 0.4)
    scenes = _Scenes(np.asarray(v[:8], np.float32), np.asarray(f[:12], np.int32),
                     [(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)) for m in (sphere, box)])
    scenes.update_dynamic(0, None, None, poses)
    for mesh in scenes.rigid:
        mesh.scene = CountingScene(mesh.scene)
    n, pos, s, org, dirs = strip_rays(3)
    hit = scenes.occluded(org, dirs, s.ao_distance, s.rays)
    traced = [mesh.scene.rays for mesh in scenes.rigid]
    assert min(traced) > 0 and sum(traced) < 0.1 * len(org)  # each mover saw only the rays near it

    every = scenes.static.run(org, dirs, dists=np.full(len(org), 1.0, np.float32), query="OCCLUDED") != -1
    for mesh, pose in zip((sphere, box), poses):
        scene = rtcore_scene.EmbreeScene(_device())
        TriangleMesh(scene, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32))
        inv = np.linalg.inv(pose)
        o = (org @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)
        d = (dirs @ inv[:3, :3].T).astype(np.float32)
        every |= scene.run(o, d, dists=np.full(len(org), 1.0, np.float32), query="OCCLUDED") != -1
    near = np.abs(pos[:, 0] + 6) < 2 + 0.4
    assert hit.reshape(n, -1)[near].any() and not hit.reshape(n, -1)[np.abs(pos[:, 0]) < 3].any()
    assert np.array_equal(hit, every)


def test_segments_reach_sphere_against_dense_sampling():
    """The sphere test of the rigid movers' ray culling equals sampling each segment densely (up to
    segments that graze the sphere within the sampling step) and never drops a segment that reaches it."""
    from psao.server.tracer.embree import segments_reach_sphere

    rng = np.random.default_rng(5)
    n = 3000
    org = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    dirs = rng.normal(size=(n, 3)).astype(np.float32) * rng.uniform(0.3, 2.0, (n, 1)).astype(np.float32)
    centre, radius, tmax = np.array([0.2, -0.1, 0.3]), 0.7, 1.5
    got = segments_reach_sphere(org, dirs, tmax, centre, radius)
    t = np.linspace(0, tmax, 4001)
    dist = np.linalg.norm(org[:, None, :] + t[None, :, None] * dirs[:, None, :] - centre, axis=2).min(axis=1)
    step = tmax * np.linalg.norm(dirs, axis=1) / 4000
    assert got[dist <= radius].all()  # conservative
    clear = np.abs(dist - radius) > step + 1e-4
    np.testing.assert_array_equal(got[clear], (dist <= radius)[clear])
    assert 0.03 < got.mean() < 0.9  # both answers are well represented


def test_deforming_pieces_trace_only_rays_reaching_their_spheres_with_the_same_answers():
    """The deforming part is traced only on the rays that reach one of the bounding spheres of its pieces'
    runs of triangles (PieceSlabs): the answers equal tracing every ray against it, for pieces near some points
    and far from most, for pieces that do not cover every vertex (one piece then), and in a second pose where
    the runs chosen in the first are kept and only their spheres move."""
    from psao.server.tracer.embree import EmbreeScenes as _Scenes

    v, f = slab(1.5)
    balls = [trimesh.creation.icosphere(subdivisions=2, radius=0.4).apply_translation(c)
             for c in ((-6, 0, 0.5), (0, 1, 0.3), (5, -1, 0.6))]
    verts = np.concatenate([b.vertices for b in balls]).astype(np.float32)
    faces = np.concatenate([b.faces + sum(len(x.vertices) for x in balls[:k]) for k, b in enumerate(balls)])
    counts = [len(b.vertices) for b in balls]
    # the second pose: each ball stretched along y and carried 2 to +x (the middle one then reaches x = 2)
    moved = verts * np.float32([1, 2.5, 1]) + np.float32([2, 0, 0])
    n, pos, s, org, dirs = strip_rays(4)
    for parts in (counts, None, [counts[0]]):
        scenes = _Scenes(np.asarray(v[:8], np.float32), np.asarray(f[:12], np.int32))
        for version, pose in enumerate((verts, moved)):
            scenes.update_dynamic(version, pose, faces.astype(np.int32), None, parts)
            scenes.dynamic = counted = CountingScene(scenes.dynamic)
            hit = scenes.occluded(org, dirs, s.ao_distance, s.rays)
            scenes.dynamic = counted.scene
            # a sphere per run of each ball: few rays; one piece: runs that span two balls, still not all
            assert 0 < counted.rays < (0.15 if parts is counts else 0.75) * len(org)
            dists = np.full(len(org), 1.0, np.float32)
            every = ((scenes.static.run(org, dirs, dists=dists, query="OCCLUDED") != -1)
                     | (scenes.dynamic.run(org, dirs, dists=dists, query="OCCLUDED") != -1))
            assert np.array_equal(hit, every)
            assert hit.reshape(n, -1)[np.abs(pos[:, 0] - (5 + 2 * version)) < 1.4].any()


def test_piece_slab_spheres_hold_every_triangle_in_any_pose():
    """PieceSlabs' runs, chosen in one pose, give spheres that hold every corner of their triangles in
    another pose (randomly deformed), and every triangle belongs to one run."""
    from psao.server.tracer.embree import PIECE_SLABS, PieceSlabs

    rng = np.random.default_rng(3)
    limb = trimesh.creation.cylinder(radius=0.2, height=4.0, sections=12)
    body = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    verts = np.concatenate([limb.vertices, body.vertices])
    faces = np.concatenate([limb.faces, body.faces + len(limb.vertices)])
    parts = [len(limb.vertices), len(body.vertices)]
    slabs = PieceSlabs(verts, faces, parts)
    assert len(slabs.sizes) == 2 * PIECE_SLABS
    for _ in range(5):
        pose = verts + rng.normal(scale=0.3, size=verts.shape)
        spheres = slabs.spheres(pose)
        for k, (centre, radius) in enumerate(spheres):
            corners = pose[slabs.index[slabs.starts[k]:slabs.starts[k] + slabs.sizes[k]]]
            assert (np.linalg.norm(corners - centre, axis=1) <= radius * (1 + 1e-12)).all()
        # every triangle's three corners belong to one run
        for tri in faces[rng.choice(len(faces), 50)]:
            assert any(set(tri) <= set(slabs.index[a:a + b]) for a, b in zip(slabs.starts, slabs.sizes))
    assert slabs.same_mesh(faces, parts) and not slabs.same_mesh(faces, None)
    assert not slabs.same_mesh(faces[::-1], parts)


def test_mover_rays_compiled_equals_numpy_and_bits_may_be_shared():
    """mover_rays' Warp kernel gives the numpy form's bits exactly, with more spheres than bits (40: bit
    s % 32), and marks no ray that is hit already."""
    from psao.server.tracer.embree import _chunk_rays, mover_rays, numpy_rays, segments_reach_sphere, sphere_bits

    rng = np.random.default_rng(6)
    n = 1500
    pos = rng.uniform(-4, 4, (n, 3)).astype(np.float32)
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    s = TraceSettings(rays=8, ao_distance=1.2)
    org, dirs = (a.copy() for a in _chunk_rays(pos, nrm, np.arange(n), s, 0))
    spheres = [(rng.uniform(-4, 4, 3), float(rng.uniform(0.1, 0.8))) for _ in range(40)]
    hit = rng.random(len(org)) < 0.2
    compiled = mover_rays(org, dirs, s.ao_distance, hit, s.rays, spheres)
    with numpy_rays():
        reference = mover_rays(org, dirs, s.ao_distance, hit, s.rays, spheres)
    np.testing.assert_array_equal(compiled, reference)
    assert not compiled[hit].any() and compiled.any()
    bits = sphere_bits(len(spheres))
    for (c, r), bit in zip(spheres, bits):  # every ray not hit that reaches a sphere carries its bit
        assert ((compiled & bit) != 0)[segments_reach_sphere(org, dirs, s.ao_distance, c, r) & ~hit].all()


@pytest.mark.parametrize("moving", ["rigid", "deforming", "both"])
def test_only_the_rays_the_static_scene_lets_through_give_the_full_trace(moving):
    """visibility_given_static with static_occluded's hits (each point's whole ray set: the static scene
    once, then the moving parts on the rays it lets through) equals visibility, exactly, for points around
    rigid and deforming movers."""
    v, f = slab(1.0)
    tracer = make_tracer("embree", workers=1)
    tracer.set_static(v, f)  # floor and ceiling: the ceiling occludes the steeper rays
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    tracer.set_rigid([(ball.vertices, ball.faces)])
    box = trimesh.creation.box(extents=(0.6, 0.4, 0.8))
    rng = np.random.default_rng(1)
    n = 600
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    ids = np.arange(n) * 7
    s = TraceSettings(rays=32, ao_distance=1.5, seed=3)
    hits = tracer.static_occluded(pos, nrm, ids, s)
    assert hits.shape == (n, 32) and 0.05 < hits.mean() < 0.95
    for shift in ((0.3, 0.2, 0.45), (-0.6, 0.5, 0.7)):
        pose = np.eye(4)
        pose[:3, 3] = shift
        rigid = pose[None] if moving in ("rigid", "both") else None
        deforming = (box.vertices + np.array(shift) * [-1, -1, 1], box.faces) if moving in ("deforming", "both") \
            else (None, np.zeros((0, 3), int))
        tracer.set_dynamic(*deforming, rigid)
        full = tracer.visibility(pos, nrm, ids, s)
        assert full.min() < 0.7  # the movers are really in the way
        np.testing.assert_array_equal(tracer.visibility_given_static(pos, nrm, ids, s, hits), full)
    tracer.close()


@pytest.mark.parametrize("moving", ["rigid", "deforming"])
def test_static_hits_kept_by_a_trace_give_the_full_trace_in_the_workers(moving):
    """visibility_and_static_hits answers as visibility and keeps the static scene's answers (bit-packed,
    equal to static_occluded); visibility_given_static from those bits, traced in the worker processes,
    equals a full trace of the same rays wherever the movers stand."""
    v, f = slab(1.0)
    tracer = make_tracer("embree", workers=2)
    tracer.set_static(v, f)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    tracer.set_rigid([(ball.vertices, ball.faces)])
    box = trimesh.creation.box(extents=(0.6, 0.4, 0.8))
    rng = np.random.default_rng(2)
    n = 1500  # above local_rays: the workers trace
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    ids = np.arange(n) * 5 + 11
    s = TraceSettings(rays=24, ao_distance=1.5, seed=4)
    assert n * s.rays >= s.local_rays

    def pose(shift):
        rigid = np.eye(4)[None].copy()
        rigid[0, :3, 3] = shift
        if moving == "rigid":
            tracer.set_dynamic(None, np.zeros((0, 3), int), rigid)
        else:
            tracer.set_dynamic(box.vertices + np.array(shift), box.faces, None)

    pose((0.2, 0.1, 0.5))
    vis, bits = tracer.visibility_and_static_hits(pos, nrm, ids, s)
    assert bits.shape == (n, 3) and bits.dtype == np.uint8
    np.testing.assert_array_equal(vis, tracer.visibility(pos, nrm, ids, s))
    static = tracer.static_occluded(pos, nrm, ids, s)
    assert 0.05 < static.mean() < 0.95
    np.testing.assert_array_equal(np.unpackbits(bits, axis=1, count=s.rays).astype(bool), static)
    for shift in ((0.2, 0.1, 0.5), (-0.7, 0.4, 0.6), (5.0, 5.0, 0.5)):
        pose(shift)
        full = tracer.visibility(pos, nrm, ids, s)
        np.testing.assert_array_equal(tracer.visibility_given_static(pos, nrm, ids, s, bits), full)
        np.testing.assert_array_equal(tracer.visibility_given_static(pos, nrm, ids, s, static), full)
    assert full.min() < 1.0  # the ceiling is in the way even where the mover is not
    sliced = TraceSettings(rays=24, ao_distance=1.5, seed=4, slices=2)  # static hits hold for whole ray sets
    with pytest.raises(TracerError, match="whole ray sets only"):
        tracer.visibility_and_static_hits(pos, nrm, ids, sliced)
    with pytest.raises(TracerError, match="whole ray sets only"):
        tracer.visibility_parts([TracePart(pos, nrm, ids, sliced, keep_static=True)])
    with pytest.raises(TracerError, match="whole ray sets only"):
        tracer.visibility_given_static(pos, nrm, ids, sliced, bits)
    tracer.close()


def test_a_call_traced_in_process_equals_the_same_call_spread_over_workers():
    """A small call is traced in the calling process in one chunk, a large one in chunks over the workers:
    a point's rays do not depend on its chunk, so the answers are the same bit for bit (static, deforming
    and rigid parts, slices of the ray set)."""
    v, f = slab(1.0)
    tracer = make_tracer("embree", workers=2)
    tracer.set_static(v[:8], f[:12])
    mover = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    tracer.set_rigid([(mover.vertices, mover.faces)])
    pose = np.eye(4)
    pose[:3, 3] = (0.2, -0.1, 0.6)
    tracer.set_dynamic(mover.vertices * 0.5 + (0.6, 0.4, 0.4), mover.faces, pose[None])
    rng = np.random.default_rng(5)
    n = 700
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    slices = rng.integers(0, 4, n)
    try:
        here = tracer.visibility(pos, nrm, np.arange(n), TraceSettings(rays=32, slices=4, ao_distance=2.0,
                                                                       local_rays=10**9), slice_of=slices)
        spread = tracer.visibility(pos, nrm, np.arange(n), TraceSettings(rays=32, slices=4, ao_distance=2.0,
                                                                         local_rays=1, chunk_points=64), slice_of=slices)
        assert tracer.worker_pids and here.min() < 0.8
        np.testing.assert_array_equal(here, spread)
    finally:
        tracer.close()


def test_the_account_counts_a_pooled_calls_worker_seconds_over_its_workers():
    """CpuAccount.wall (the seconds of the callers' wall time the rays took, which the tick's budget takes
    apart from a call's fixed cost): worker seconds as they are for a call traced in process, over the
    two workers for one spread over them."""
    v, f = slab(1.0)
    tracer = make_tracer("embree", workers=2)
    tracer.set_static(v[:8], f[:12])
    rng = np.random.default_rng(6)
    n = 400
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    a = tracer.account
    try:
        for local_rays, over in ((10**9, 1), (1, 2)):
            total, wall = a.cpu_total, a.wall
            tracer.visibility(pos, nrm, np.arange(n), TraceSettings(rays=16, ao_distance=2.0, local_rays=local_rays,
                                                                    chunk_points=64))
            assert a.cpu_total > total
            assert a.wall - wall == pytest.approx((a.cpu_total - total) / over, rel=1e-9)
        assert tracer.worker_pids
    finally:
        tracer.close()


@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != "dask"])
def test_every_backend_accounts_its_rays_and_their_seconds(backend):
    """Each call adds its rays to the tracer's account, and the seconds they took (`wall`: what the tick's
    budget counts as the rays' own, the rest of the call being its fixed cost) within the call's own."""
    import time

    v, f = slab(1.0)
    tracer = make_tracer(backend)
    tracer.set_static(v, f)
    n = 300
    pos = np.column_stack([np.linspace(-1, 1, n), np.zeros(n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    s = TraceSettings(rays=16, ao_distance=2.0)
    try:
        tracer.visibility(pos[:1], nrm[:1], np.arange(1), s)  # (a first call's set-up: a kernel compiled)
        a = tracer.account
        rays, wall = a.rays, a.wall
        t0 = time.perf_counter()
        tracer.visibility(pos, nrm, np.arange(n), s)
        call = time.perf_counter() - t0
        assert a.rays - rays == n * 16
        assert 0 < a.wall - wall <= call
        assert tracer.throughput()["rays_per_second"] > 0
    finally:
        tracer.close()


def test_parts_traced_in_process_together_answer_as_each_alone():
    """A call of several parts traced in the calling process (a tick's: slices of ray sets, whole ray sets,
    whole ray sets that keep or are given their static hits) queries the static scene once, for the rays
    whose static answers are not given, and each mover once; each part's answers (visibility, the static
    hits it keeps) are the ones it gets traced alone, bit for bit."""
    v, f = slab(1.0)
    tracer = make_tracer("embree", workers=1)  # one process: every call is traced here
    tracer.set_static(v, f)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    tracer.set_rigid([(ball.vertices, ball.faces)])
    box = trimesh.creation.box(extents=(0.6, 0.4, 0.8))
    pose = np.eye(4)
    pose[:3, 3] = (0.3, 0.2, 0.45)
    tracer.set_dynamic(box.vertices + (-0.5, -0.4, 0.5), box.faces, pose[None])
    rng = np.random.default_rng(8)
    n = 400
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    ids = np.arange(n) * 3 + 1
    whole = TraceSettings(rays=32, ao_distance=1.5, seed=3)
    sliced = TraceSettings(rays=32, ao_distance=1.5, seed=3, slices=4)
    a, b, c, d = np.array_split(rng.permutation(n), 4)
    hits = tracer.static_occluded(pos[d], nrm[d], ids[d], whole)
    parts = [TracePart(pos[a], nrm[a], ids[a], sliced, slice_of=rng.integers(0, 4, len(a))),
             TracePart(pos[b], nrm[b], ids[b], whole),
             TracePart(pos[c], nrm[c], ids[c], whole, keep_static=True),
             TracePart(pos[d], nrm[d], ids[d], whole, static_hit=np.packbits(hits, axis=1))]
    alone = [tracer.visibility_parts([p])[0] for p in parts]
    local = tracer._local
    local.static = CountingScene(local.static)
    local.dynamic = CountingScene(local.dynamic)
    for mesh in local.rigid:
        mesh.scene = CountingScene(mesh.scene)
    together = tracer.visibility_parts(parts)
    assert local.static.calls == 1 and local.static.rays == (len(a) * 8 + (len(b) + len(c)) * 32)
    assert local.dynamic.calls == 1 and local.rigid[0].scene.calls == 1
    for (vis, kept), (vis_alone, kept_alone), part in zip(together, alone, parts):
        np.testing.assert_array_equal(vis, vis_alone)
        assert (kept is None) == (kept_alone is None) == (not part.keep_static)
        if kept is not None:
            np.testing.assert_array_equal(kept, kept_alone)
    assert min(v.min() for v, _ in together) < 0.7  # the movers and the ceiling are in the way
    tracer.close()


def test_a_large_call_in_process_is_traced_chunk_by_chunk():
    """A call traced in the calling process (one process: a bake there) queries the static scene once per
    chunk_points points, not once for all its rays, and reports progress after each chunk: memory stays
    bounded and progress moves while it traces."""
    v, f = slab(1.0)
    tracer = make_tracer("embree", workers=1)
    tracer.set_static(v, f)
    rng = np.random.default_rng(9)
    n, chunk = 1000, 256
    pos = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)])
    nrm = np.tile([0, 0, 1.0], (n, 1))
    s = TraceSettings(rays=16, ao_distance=1.5, seed=3, chunk_points=chunk)
    alone = tracer.visibility(pos, nrm, np.arange(n), s)
    local = tracer._local
    local.static = counted = CountingScene(local.static)
    seen = []
    vis = tracer.visibility(pos, nrm, np.arange(n), s, progress=lambda k: seen.append((k, counted.calls)))
    assert counted.calls == -(-n // chunk) and counted.rays == n * 16
    assert [c for _, c in seen] == list(range(1, counted.calls + 1)) and sum(k for k, _ in seen) == n
    np.testing.assert_array_equal(vis, alone)
    tracer.close()
