"""Scale-aware default density, point budgets and the estimate checked before anything is generated."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from psao.scene import load_scene
from psao.server.errors import ConfigError
from psao.server.points.sampling import (DETAIL_FACTOR, POINTS_PER_AO_AREA, SamplingSettings, default_density,
                                  estimate_points, resolve_density)
from support.cli import psao

REPO = Path(__file__).resolve().parents[1]


def write_box_obj(path: Path, size: float) -> Path:
    """A closed box of edge `size` (12 triangles) as an OBJ file."""
    v = [(x, y, z) for x in (0, size) for y in (0, size) for z in (0, size)]
    f = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7), (1, 3, 7),
         (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(f"f {a} {b} {c}\n" for a, b, c in f))
    return path


def test_courtyard_default_is_its_measured_density():
    scene = load_scene("builtin:courtyard")
    assert default_density(scene) == pytest.approx(256.0)
    d = resolve_density(scene, SamplingSettings(), min_points=64)
    density, count = d.plain, d.estimate
    assert density == pytest.approx(256.0) and count == estimate_points(scene, 256.0, 64, DETAIL_FACTOR)


def test_default_sampling_does_not_depend_on_units(tmp_path):
    small = load_scene(write_box_obj(tmp_path / "mm.obj", 2.0))
    huge = load_scene(write_box_obj(tmp_path / "km.obj", 2.0e5))
    n_small = resolve_density(small, SamplingSettings(), 64).estimate
    n_huge = resolve_density(huge, SamplingSettings(), 64).estimate
    assert n_small == n_huge > 64 * 6
    # points per AO-distance squared, as promised
    area = 6 * 2.0 ** 2
    assert n_small == pytest.approx(POINTS_PER_AO_AREA * area / small.ao_distance ** 2, rel=1e-6)


def test_point_budget_sets_the_density(tmp_path):
    scene = load_scene(write_box_obj(tmp_path / "b.obj", 3.0))
    d = resolve_density(scene, SamplingSettings(points=5000), 1)
    density, count = d.plain, d.estimate
    assert density == pytest.approx(5000 / 54.0) and count == pytest.approx(5000, abs=6)


def quad_and_fine_strip():
    """One mesh: a 1 x 1 quad (two large triangles) and a 1 x 0.1 strip cut into 0.01 x 0.01 squares."""
    from psao.scene.model import Instance, Mesh, Scene

    v = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    f = [[0, 1, 2], [0, 2, 3]]
    for i in range(100):
        for j in range(10):
            k = len(v)
            x, y = i * 0.01, 2 + j * 0.01
            v += [[x, y, 0], [x + 0.01, y, 0], [x + 0.01, y + 0.01, 0], [x, y + 0.01, 0]]
            f += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    mesh = Mesh("strip", np.array(v, float), np.array(f, np.int64))
    return Scene("strip", [mesh], [Instance("strip", 0, np.eye(4))], ao_distance=0.5)


def test_default_density_samples_small_triangles_denser_and_counts_them():
    scene = quad_and_fine_strip()
    n = default_density(scene)
    d = resolve_density(scene, SamplingSettings(), 1)
    density, count = d.plain, d.estimate
    assert density == n and count == estimate_points(scene, n, 1, DETAIL_FACTOR)
    assert count == round(n * 1.0) + round(DETAIL_FACTOR * n * 0.1)  # the quad at N, the strip at 4 N
    # an explicit density is the same on every triangle unless the levels are asked for
    assert resolve_density(scene, SamplingSettings(density=n), 1).estimate == round(n * 1.1)
    assert resolve_density(scene, SamplingSettings(density=n, detail_factor=4), 1).estimate == count
    assert resolve_density(scene, SamplingSettings(detail_factor=1), 1).estimate == round(n * 1.1)


def test_a_budget_equal_to_the_limit_is_never_refused():
    """A point budget P with --max-points P resolves (its estimate is at most P, rounding included), and the
    density a refusal advises fits the limit."""
    from psao.scene.model import Instance, Mesh, Scene

    quad = Mesh("quad", np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]))
    quads = Scene("quads", [quad], [Instance(f"q{k}", 0, np.eye(4)) for k in range(3)], ao_distance=0.5)
    for scene in (quad_and_fine_strip(), quads):  # 3 quads at 3002: each rounds 1000.67 up (3003 at budget / area)
        for budget in (1000, 2999, 3000, 3001, 3002, 12345):
            assert resolve_density(scene, SamplingSettings(points=budget, max_points=budget), 1).estimate <= budget
    scene = quad_and_fine_strip()
    with pytest.raises(ConfigError, match="pass --density") as refused:
        resolve_density(scene, SamplingSettings(density=default_density(scene) * 10, max_points=3000), 1)
    advised = float(str(refused.value).split("pass --density ")[1].split()[0])
    assert resolve_density(scene, SamplingSettings(density=advised, max_points=3000), 1).estimate <= 3000


def test_point_budget_counts_the_detail_levels():
    scene = quad_and_fine_strip()
    d = resolve_density(scene, SamplingSettings(points=3000), 1)
    density, count = d.plain, d.estimate
    assert 0.97 * 3000 <= count <= 3000 and count == estimate_points(scene, density, 1, DETAIL_FACTOR)


def boxes_toml(tmp_path: Path, boxes: dict[str, tuple[float, float]], head: str = "") -> Path:
    """A TOML scene of boxes NAME -> (edge, x of its centre), each its own mesh and [[instance]]."""
    text = f"[scene]\n{head}\n" + "".join(
        f'[[mesh]]\nname = "{n}"\ngenerator = "box"\nsize = [{e}, {e}, {e}]\n'
        f'[[instance]]\nname = "{n}"\nmesh = "{n}"\ntranslate = [{x}, 0.0, 0.0]\n' for n, (e, x) in boxes.items())
    path = tmp_path / f"{'_'.join(boxes)}{len(head)}.toml"
    path.write_text(text)
    return path


def test_each_instance_of_a_toml_scene_without_ao_distance_is_sampled_at_its_own_size(tmp_path):
    """Without an AO distance a TOML scene's [[instance]]s get the default density of OBJECT_SAMPLING_FRACTION
    x their own diagonal: a small box gets the same density beside a large box as beside a larger one; the
    scene's AO distance, an explicit AO distance and an explicit density are the same on every instance."""
    from psao.scene.model import OBJECT_SAMPLING_FRACTION

    big, small = (20.0, 0.0), (0.5, 30.0)
    both = load_scene(boxes_toml(tmp_path, {"big": big, "small": small}))
    other = load_scene(boxes_toml(tmp_path, {"huge": (60.0, 0.0), "small": small}))
    d, e = (resolve_density(s, SamplingSettings(), 1) for s in (both, other))
    assert d.plain == default_density(both) and d.factors[1] > d.factors[0] >= 1
    own = POINTS_PER_AO_AREA / (OBJECT_SAMPLING_FRACTION * 0.5 * math.sqrt(3)) ** 2
    assert d.of(1) == pytest.approx(own, rel=1e-9) and e.of(1) == pytest.approx(own, rel=1e-9)
    assert d.estimate == estimate_points(both, d.plain, 1, DETAIL_FACTOR, factors=d.factors)
    assert d.estimate > estimate_points(both, d.plain, 1, DETAIL_FACTOR)
    # an explicit density: the same on both; an AO distance in the scene or on the command line: its density on both
    explicit = resolve_density(both, SamplingSettings(density=d.plain), 1)
    assert (explicit.factors == 1).all() and explicit.estimate == estimate_points(both, d.plain, 1, 1)
    for scene in (load_scene(boxes_toml(tmp_path, {"big": big, "small": small}, "ao_distance = 1.0")),
                  load_scene(boxes_toml(tmp_path, {"big": big, "small": small}), ao_distance=1.0)):
        fixed = resolve_density(scene, SamplingSettings(), 1)
        assert fixed.plain == POINTS_PER_AO_AREA and (fixed.factors == 1).all()
    # a point budget keeps the instances' factors
    budget = resolve_density(both, SamplingSettings(points=5000), 1)
    assert (budget.factors == d.factors).all() and budget.estimate <= 5000


def test_the_bake_samples_each_instance_at_its_factor(tmp_path):
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings

    scene = load_scene(boxes_toml(tmp_path, {"big": (20.0, 0.0), "small": (0.5, 30.0)}))
    result = bake_scene(scene, BakeSettings(points=4000, rays=4, workers=1, detail_factor=1), show_progress=False)
    result.tracer.close()
    factors = resolve_density(scene, SamplingSettings(points=4000), 1).factors
    per_area = [len(ps) / scene.meshes[i.mesh].area() for ps, i in zip(result.pointsets, scene.instances)]
    assert per_area[1] / per_area[0] == pytest.approx(factors[1] / factors[0], rel=0.02)


@pytest.mark.parametrize("factor", [0, 3, -2, 128, 2.0, True])
def test_bad_detail_factors_are_refused(factor):
    with pytest.raises(ConfigError):
        SamplingSettings(detail_factor=factor).check()


@pytest.mark.parametrize("kw", [dict(density=0.0), dict(density=-3.0), dict(density=math.nan), dict(density=math.inf),
                                dict(points=0), dict(points=-1), dict(points=math.nan), dict(max_points=0),
                                dict(max_points=math.nan), dict(density=5.0, points=100)])
def test_bad_numbers_are_refused(kw):
    with pytest.raises(ConfigError):
        SamplingSettings(**kw).check()


def test_estimate_above_the_limit_names_count_and_what_to_pass(tmp_path):
    scene = load_scene(write_box_obj(tmp_path / "big.obj", 1000.0))
    with pytest.raises(ConfigError) as err:
        resolve_density(scene, SamplingSettings(density=16.0, max_points=1e6), 64)
    text = str(err.value)
    assert "96,000,000 points" in text and "--density" in text and "--points 1000000" in text and "\n" not in text


def test_cli_refuses_a_huge_file_before_generating(tmp_path):
    """A file in huge units at an absolute density: one line naming the count, exit 2, nothing written."""
    obj = write_box_obj(tmp_path / "huge.obj", 1.0e5)
    res = psao("bake", obj, "--density", 16, "--out", tmp_path / "g.npz")
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip() and "Warp" not in ln]
    assert len(lines) == 1 and "960,000,000,000 points" in lines[0] and "--max-points" in lines[0]
    assert not (tmp_path / "g.npz").exists()


@pytest.mark.parametrize("args", [("--density", "nan"), ("--points", "0")])
def test_cli_bad_number_is_one_line(args, tmp_path):
    res = psao("bake", "builtin:cornell", *args, "--out", tmp_path / "g.npz")
    lines = [ln for ln in res.stderr.splitlines() if ln.strip() and "Warp" not in ln]
    assert res.returncode == 2 and len(lines) == 1 and "must be a finite number > 0" in lines[0]
