"""A deforming mesh refitted in place (tracer/embree_refit.py) answers every occlusion query as a scene built
afresh from the same triangles does, through the tracer's processes as well."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("embreex")

from psao.scene import load_scene  # noqa: E402
from psao.server.tick.animate import SceneAnimator  # noqa: E402
from psao.server.settings import TraceSettings  # noqa: E402
from psao.server.tracer.embree import EmbreeTracer, _build_scene, _device  # noqa: E402
from psao.server.tracer.embree_refit import RefitMesh  # noqa: E402


@pytest.fixture(scope="module")
def robots():
    animator = SceneAnimator(load_scene("builtin:robots"))
    return animator, [animator.frame(t) for t in (0.0, 0.4, 1.3, 2.9)]


def _rays(vertices, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    org = (lo + (hi - lo) * rng.random((n, 3))).astype(np.float32)
    return org, rng.standard_normal((n, 3)).astype(np.float32), np.full(n, 0.4, np.float32)


@pytest.mark.parametrize("by_part", [True, False])
def test_refitted_mesh_occludes_as_a_fresh_build(robots, by_part):
    _, frames = robots
    first = frames[0]
    mesh = RefitMesh.build(first.skinned_vertices, first.skinned_faces, _device(),
                           first.skinned_parts if by_part else None)
    assert mesh is not None, "Embree's refit was not reachable through embreex"
    for k, frame in enumerate(frames[1:] + frames[:1]):  # back to the first pose too
        assert mesh.same_mesh(frame.skinned_vertices, frame.skinned_faces.astype(np.int32),
                              frame.skinned_parts if by_part else None)
        mesh.move(frame.skinned_vertices)
        fresh = _build_scene(frame.skinned_vertices.astype(np.float32), frame.skinned_faces.astype(np.int32))
        org, dirs, dist = _rays(frame.skinned_vertices, 50_000, k)
        got = mesh.scene.run(org, dirs, dists=dist, query="OCCLUDED") != -1
        want = fresh.run(org, dirs, dists=dist, query="OCCLUDED") != -1
        assert 0.005 < want.mean() < 0.5  # the rays see the robots, not only empty space
        assert np.array_equal(got, want)


def test_other_triangles_are_not_the_same_mesh(robots):
    _, frames = robots
    f = frames[0]
    mesh = RefitMesh.build(f.skinned_vertices, f.skinned_faces, _device(), f.skinned_parts)
    faces = f.skinned_faces.astype(np.int32)
    assert not mesh.same_mesh(f.skinned_vertices[:-3], faces[:-1], None)
    assert not mesh.same_mesh(f.skinned_vertices, faces[:, ::-1], f.skinned_parts)
    assert not mesh.same_mesh(f.skinned_vertices, faces, None)  # parts differ


def test_parts_whose_faces_cross_are_refused(robots):
    _, frames = robots
    f = frames[0]
    swapped = f.skinned_faces[::-1]  # the parts' faces out of order
    assert RefitMesh.build(f.skinned_vertices, swapped, _device(), f.skinned_parts) is None
    assert RefitMesh.build(f.skinned_vertices, f.skinned_faces, _device(), [len(f.skinned_vertices) - 1]) is None


@pytest.mark.parametrize("workers", [1, 2])
def test_tracer_over_moving_versions_equals_a_fresh_tracer(robots, workers):
    """The tick's tracer, refitting its deforming mesh from version to version (in process, or in its
    workers for a call big enough), answers as a tracer given only the last pose."""
    animator, frames = robots
    static = animator.static_geometry()
    centre = np.zeros(3)
    s = TraceSettings(rays=16, ao_distance=1.5, seed=3)
    moving = EmbreeTracer(centre, workers=workers)
    moving.set_static(*static)
    try:
        rng = np.random.default_rng(5)
        for frame in frames:
            moving.set_dynamic(frame.skinned_vertices, frame.skinned_faces, None, frame.skinned_parts)
            lo, hi = frame.skinned_vertices.min(axis=0), frame.skinned_vertices.max(axis=0)
            pos = lo + (hi - lo) * rng.random((3000, 3))
            pos[:, 1] = lo[1] + 0.05  # just above the floor, among the robots' feet and legs
            nrm = np.tile(np.float32([0, 1, 0]), (len(pos), 1))
            ids = np.arange(len(pos))
            got = moving.visibility(pos, nrm, ids, s)
            fresh = EmbreeTracer(centre, workers=1)
            fresh.set_static(*static)
            fresh.set_dynamic(frame.skinned_vertices, frame.skinned_faces)
            want = fresh.visibility(pos, nrm, ids, s)
            fresh.close()
            assert (want < 1).mean() > 0.05
            assert np.array_equal(got, want)
    finally:
        moving.close()
