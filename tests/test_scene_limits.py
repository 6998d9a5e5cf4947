"""Absurd scene files and settings: one line, exit 2, before any big allocation; a flag raises a limit."""
from __future__ import annotations

import pytest

from support.cli import one_line_error, psao

BAKE = ["--density", "4", "--rays", "1", "--probes", "0"]


def toml_scene(tmp_path, mesh: str, instances: int = 1, scale: str = "1.0") -> str:
    text = f'[scene]\nname = "t"\n[[mesh]]\nname = "m"\n{mesh}\n'
    text += "".join(f'[[instance]]\nname = "i{k}"\nmesh = "m"\ntranslate = [{k}, 0, 0]\nscale = {scale}\n'
                    for k in range(instances))
    path = tmp_path / "s.toml"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("mesh, instances, scale, text", [
    ('generator = "cylinder"\nsections = 1000000000', 1, "1.0", "'sections' must be a whole number within 0..4096"),
    ('generator = "cloth"\nsubdivisions = 1000000', 1, "1.0", "'subdivisions' must be a whole number within 0..4096"),
    ('generator = "sphere"\nsubdivisions = 12', 1, "1.0", "'subdivisions' must be a whole number within 0..7"),
    ('generator = "box"', 1, "1e30", "reaches 5e+29 world units"),
    ('generator = "box"', 10_001, "1.0", "10001 instances, over the limit of 10000"),
])
def test_absurd_scene_values(tmp_path, mesh, instances, scale, text):
    one_line_error(psao("bake", toml_scene(tmp_path, mesh, instances, scale), *BAKE, "--out", str(tmp_path / "g.npz")),
                   text)


def test_deeply_nested_toml(tmp_path):
    path = tmp_path / "deep.toml"
    path.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    one_line_error(psao("bake", str(path), *BAKE), "nested too deeply")


@pytest.mark.parametrize("args, text", [
    (["--rays", "1000000000"], "rays must be within 1..4096"),
    (["--spawn-ratio", "1e9"], "spawn ratio must be within 1..64"),
])
def test_absurd_bake_settings(args, text):
    one_line_error(psao("bake", "builtin:cornell", "--density", "4", "--probes", "0", *args), text)


def test_a_flag_raises_a_limit(tmp_path):
    scene = toml_scene(tmp_path, 'generator = "box"', 3)
    one_line_error(psao("--scene-limit", "max_instances=2", "bake", scene, *BAKE), "3 instances, over the limit of 2")
    ok = psao("--scene-limit", "max_instances=3", "bake", scene, *BAKE, "--out", str(tmp_path / "g.npz"))
    assert ok.returncode == 0, ok.stderr
    one_line_error(psao("--scene-limit", "max_nothing=3", "bake", scene, *BAKE), "expected NAME=VALUE")


def test_garbage_obj_says_what_it_is(tmp_path):
    path = tmp_path / "garbage.obj"
    path.write_bytes(bytes(range(256)) * 8)
    one_line_error(psao("bake", str(path), *BAKE), "not a readable OBJ file (not UTF-8 text at byte 128)")
