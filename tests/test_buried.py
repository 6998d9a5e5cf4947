"""Points on surfaces buried inside closed static geometry: found by the buried test, not generated."""
from __future__ import annotations

import numpy as np

from psao.scene import builtin_shapes as shapes
from psao.scene.builtin import SceneBuilder, trs
from psao.server.points.buried import BuriedTest
from psao.server.points.generate import PointSettings, generate_scene_points


def crossing_boxes():
    """A 1 m cube with a 0.4 m bar pushed half-way into its +x face."""
    b = SceneBuilder("crossing")
    b.place("cube", shapes.box((1.0, 1.0, 1.0)), trs((0, 0, 0)))
    b.place("bar", shapes.box((1.0, 0.4, 0.4)), trs((0.5, 0, 0)))
    return b.build(ao_distance=0.5)


def test_buried_test_finds_the_surface_inside_the_other_solid_and_nothing_outside():
    scene = crossing_boxes()
    test = BuriedTest(scene)
    # the bar's end face inside the cube (x = 0, normal -x) and the bar's sides within the cube (x < 0.5)
    inside = np.array([[0.0, 0.0, 0.0], [0.2, 0.2, 0.0], [0.3, 0.0, -0.2]])
    inside_n = np.array([[-1, 0, 0], [0, 1, 0], [0, 0, -1]], np.float32)
    # the cube's faces outside the bar, and the bar's sides outside the cube (x > 0.5)
    outside = np.array([[0.5, 0.35, 0.35], [0.0, 0.5, 0.0], [0.8, 0.2, 0.0], [0.8, 0.0, -0.2]])
    outside_n = np.array([[1, 0, 0], [0, 1, 0], [0, 1, 0], [0, 0, -1]], np.float32)
    assert test.mask(inside, inside_n).all()
    assert not test.mask(outside, outside_n).any()


def test_generation_keeps_points_off_buried_surfaces_at_the_same_density():
    scene = crossing_boxes()
    settings = PointSettings(density=400.0)
    plain = generate_scene_points(scene, settings)
    skipped = generate_scene_points(scene, settings, buried=BuriedTest(scene))
    bar_plain, bar = plain[1].positions, skipped[1].positions
    # the bar's part inside the cube (x < 0.5 in the bar's local frame: x < 0) has no points left
    assert (bar_plain[:, 0] < -0.05).sum() > 100
    assert (bar[:, 0] < -0.05).sum() == 0
    # what is visible keeps its density: the count outside the cube stays within sampling noise
    out_plain, out = (bar_plain[:, 0] > 0.05).sum(), (bar[:, 0] > 0.05).sum()
    assert abs(out - out_plain) < 0.1 * out_plain, (out, out_plain)
    assert skipped[1].poisson_radius == plain[1].poisson_radius
