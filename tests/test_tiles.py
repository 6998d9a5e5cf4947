"""Spatial tiles: a tile traced against only the triangles its rays can reach answers as the whole scene does."""
import numpy as np
import pytest

from psao.scene import load_scene
from psao.server.bake import sample_probes
from psao.server.geometry import scene_center, scene_world_geometry
from psao.server.tracer import make_tracer
from psao.server.settings import TraceSettings
from psao.server.tracer.base import recentre
from psao.server.tracer.tiles import cut_triangles, make_tiles, split_points, triangle_boxes


def test_split_points_partitions_into_bounded_compact_sets():
    rng = np.random.default_rng(0)
    p = rng.uniform(-10, 10, size=(5000, 3)) * [1, 0.1, 1]
    parts = split_points(p, 700)
    assert all(0 < len(idx) <= 700 for idx in parts)
    assert np.array_equal(np.sort(np.concatenate(parts)), np.arange(len(p)))
    # k-d halving keeps tiles compact: every tile is much smaller than the whole set along x and z
    ext = np.array([np.ptp(p[idx], axis=0) for idx in parts])
    assert ext[:, [0, 2]].max() < 0.6 * 20
    with pytest.raises(ValueError):
        split_points(p, 0)


def test_cut_keeps_exactly_the_overlapping_triangles():
    rng = np.random.default_rng(1)
    v = rng.uniform(-5, 5, size=(300, 3)).astype(np.float32)
    f = rng.integers(0, 300, size=(400, 3))
    lo, hi = np.array([-1.0, -1, -1]), np.array([1.0, 2, 1])
    sub_v, sub_f = cut_triangles(v, f, triangle_boxes(v, f), lo, hi)
    tri = v[f]
    overlap = np.all(tri.min(axis=1) <= hi, axis=1) & np.all(tri.max(axis=1) >= lo, axis=1)
    assert len(sub_f) == overlap.sum() and len(sub_v) <= len(v)
    # the same triangles, vertex values copied bit for bit
    np.testing.assert_array_equal(sub_v[sub_f], tri[overlap])


def test_tiled_trace_equals_whole_scene_trace():
    """Each tile of courtyard probes traced against its cut of the scene gives the untiled bits."""
    scene = load_scene("builtin:courtyard")
    v, f = scene_world_geometry(scene)
    center = scene_center(scene)
    probes = sample_probes(scene, 3000, seed=4)
    s = TraceSettings(rays=32, ao_distance=scene.ao_distance, seed=9)
    ids = np.arange(len(probes.world_pos))
    with make_tracer("embree", center, workers=1) as whole:
        whole.set_static(v, f)
        ref = whole.visibility(probes.world_pos, probes.world_normal, ids, s)
    v32 = recentre(v, center)
    boxes = triangle_boxes(v32, f)
    tiles = make_tiles(recentre(probes.world_pos, center), scene.ao_distance, 400)
    assert len(tiles) >= 8
    out = np.empty(len(ids), np.float32)
    kept = []
    for tile in tiles:
        tv, tf = cut_triangles(v32, f, boxes, tile.lo, tile.hi)
        kept.append(len(tf))
        with make_tracer("embree", (0.0, 0.0, 0.0), workers=1) as part:  # already in the tracer's frame
            part.set_static(tv, tf)
            out[tile.points] = part.visibility(recentre(probes.world_pos[tile.points], center),
                                               probes.world_normal[tile.points], ids[tile.points], s)
    np.testing.assert_array_equal(out, ref)
    assert np.median(kept) < 0.5 * len(f)  # tiles really hold less than the scene
