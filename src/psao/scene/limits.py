"""Size limits checked while a scene is read and before a bake allocates, so an absurd file or setting
fails with one line instead of a traceback or minutes of work. `psao --scene-limit NAME=VALUE COMMAND ...`
raises one (set_limits); everything reads current()."""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

from psao.scene.errors import SceneFormatError


@dataclass(frozen=True)
class SceneLimits:
    max_scene_file_bytes: int = 64 * 1024 * 1024  # a .toml scene file
    max_instances: int = 10_000  # instances in a scene (TOML tables or glTF nodes)
    max_generator_resolution: int = 4096  # sections, rings, segments, subdivisions of a grid-like generator
    max_icosphere_subdivisions: int = 7  # sphere/boulder: 20 * 4^s triangles (7: 328k)
    max_coordinate: float = 1e7  # world units: any vertex of the placed scene (catches scale 1e30)
    max_spawn_ratio: float = 64.0  # points spawned per point kept
    max_rays: int = 4096  # AO rays per point (bake and tick)


_current = SceneLimits()


def current() -> SceneLimits:
    return _current


def set_limits(limits: SceneLimits) -> None:
    global _current
    _current = limits


def parse_overrides(items: list[str], base: SceneLimits | None = None) -> SceneLimits:
    """["max_instances=100000", ...] -> SceneLimits; a bad name or value raises SceneFormatError."""
    out = base or SceneLimits()
    types = {f.name: f.type for f in fields(SceneLimits)}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or name not in types:
            raise SceneFormatError(f"--scene-limit {item!r}: expected NAME=VALUE with NAME one of {', '.join(types)}")
        try:
            number = float(value)
        except ValueError:
            raise SceneFormatError(f"--scene-limit {item!r}: {value!r} is not a number") from None
        if not number > 0 or number != number or number == float("inf"):
            raise SceneFormatError(f"--scene-limit {item!r}: must be a finite number > 0")
        out = replace(out, **{name: int(number) if types[name] in ("int", int) else number})
    return out
