"""How many points a scene gets: the scale-aware default density, a total point budget, and the estimate
of points and memory checked against a limit before anything is generated.

Density N counts final points per world unit^2, so a fixed N depends on the file's units: a model in
centimetres gets 10^4 times the points of the same model in metres. The default therefore follows the
scene's AO distance d (its own length scale: what a point's AO depends on): N = POINTS_PER_AO_AREA / d^2,
calibrated so the built-in courtyard (d = 1.5) gets N = 256, the density its figures were measured at.
`--density` keeps absolute control; `--points` asks for a total instead.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from psao_server.errors import ConfigError

if TYPE_CHECKING:  # the CLI imports this module for its arguments; loading scenes pulls in Warp
    from psao_scene.model import Scene

# Final points per AO-distance squared: the courtyard's 256 points per unit^2 at its AO distance of 1.5.
POINTS_PER_AO_AREA = 256.0 * 1.5 ** 2
# Peak resident bytes per final point of a bake (point generation, grid, tracing), measured on the
# courtyard at N = 256 and 1024 (446 and 300 bytes per point above the interpreter's own); rounded up.
BYTES_PER_POINT = 512
# Default limit on the points one bake may generate: about 10 GiB by the estimate above, under half of
# a 24 GiB machine.
DEFAULT_MAX_POINTS = 20_000_000


@dataclass
class SamplingSettings:
    density: float | None = None  # final points per world unit^2; None: POINTS_PER_AO_AREA / ao_distance^2
    points: float | None = None  # total point budget instead of a density (both sides of double-sided meshes)
    max_points: float = DEFAULT_MAX_POINTS  # refuse to generate more than this many points

    def check(self) -> None:
        if self.density is not None and self.points is not None:
            raise ConfigError("give either a density or a point budget, not both")
        for name, value in (("density", self.density), ("point budget", self.points), ("max points", self.max_points)):
            if value is not None and not (_is_number(value) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value}")
        if self.points is not None and self.points < 1:
            raise ConfigError(f"point budget must be at least 1 point, got {self.points}")


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def add_arguments(p) -> None:
    """--density / --points / --max-points on an argparse parser (bake and serve)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument("--density", type=float, default=None,
                       help=f"points per world unit^2 after elimination; without it {POINTS_PER_AO_AREA:g} / AO distance^2, "
                            "the courtyard's 256 at its AO distance 1.5, so files in any units get the same sampling")
    group.add_argument("--points", type=float, default=None, metavar="COUNT",
                       help="total point budget instead of a density (e.g. 2e6)")
    p.add_argument("--max-points", type=float, default=SamplingSettings.max_points, metavar="COUNT",
                   help=f"refuse, before generating anything, a setting estimated above this many points "
                        f"({DEFAULT_MAX_POINTS:,} is about {DEFAULT_MAX_POINTS * BYTES_PER_POINT / 2 ** 30:.0f} GiB)")


def bake_kwargs(args) -> dict:
    """BakeSettings fields from the arguments add_arguments defined."""
    return {"density": args.density, "points": args.points, "max_points": args.max_points}


def instance_areas(scene: Scene) -> np.ndarray:
    """World surface area of each instance, counted once per side (double-sided meshes twice)."""
    out = np.empty(len(scene.instances))
    for k, inst in enumerate(scene.instances):
        mesh = scene.meshes[inst.mesh]
        out[k] = mesh.area(np.asarray(inst.transform, np.float64)[:3, :3]) * (2 if mesh.double_sided else 1)
    return out


def default_density(scene: Scene) -> float:
    return POINTS_PER_AO_AREA / float(scene.ao_distance) ** 2


def estimate_points(scene: Scene, density: float, min_points: int, areas: np.ndarray | None = None) -> int:
    """Final points generation will produce at `density` (before any overflow): per instance and side
    max(min_points, round(N * area))."""
    areas = instance_areas(scene) if areas is None else areas
    sides = np.array([2 if scene.meshes[i.mesh].double_sided else 1 for i in scene.instances])
    per_side = np.maximum(float(min_points), np.round(density * areas / sides))
    return int((per_side * sides).sum())


def resolve_density(scene: Scene, settings: SamplingSettings, min_points: int) -> tuple[float, int]:
    """(density, estimated points) for a scene, or ConfigError with one line naming the count and what to
    pass when the estimate exceeds settings.max_points. Costs one pass over the triangles."""
    settings.check()
    areas = instance_areas(scene)
    total_area = float(areas.sum())
    if not (math.isfinite(total_area) and total_area > 0):
        raise ConfigError(f"scene {scene.name}: surface area is {total_area}, cannot place points")
    if settings.density is not None:
        density = float(settings.density)
    elif settings.points is not None:
        density = settings.points / total_area
    else:
        density = default_density(scene)
    count = estimate_points(scene, density, min_points, areas)
    if count > settings.max_points:
        fit = settings.max_points / total_area
        raise ConfigError(
            f"scene {scene.name}: density {density:.4g} per unit^2 would generate about {count:,} points "
            f"(~{count * BYTES_PER_POINT / 2 ** 30:.1f} GiB), above the limit of {settings.max_points:,.0f}; "
            f"pass --density {fit:.4g} or --points {settings.max_points:.0f} (or raise --max-points)")
    return density, count
