"""How many points a scene gets: the scale-aware default density, a total point budget, and the estimate
of points and memory checked against a limit before anything is generated.

Density N counts final points per world unit^2, so a fixed N depends on the file's units: a model in
centimetres gets 10^4 times the points of the same model in metres. The default therefore follows the
scene's AO distance d (its own length scale: what a point's AO depends on): N = POINTS_PER_AO_AREA / d^2,
calibrated so the built-in courtyard (d = 1.5) gets N = 256, the density its figures were measured at.
An instance with its own sampling scale s (Instance.sampling_scale: each [[instance]] of a TOML scene
that sets no AO distance, 0.4 x its own diagonal, at most d) gets N (d / s)^2 instead: a character in a
cathedral is sampled at its own size, not the cathedral's (instance_factors).
`--density` keeps absolute control, the same N everywhere; `--points` asks for a total instead, keeping
the instances' factors.

With the default density (and a point budget) N is the density on large faces: a triangle small against
the point spacing (mouldings, capitals, a character's folds: geometry finer than the points, where the AO
changes within a few of them) gets up to DETAIL_FACTOR times N (detail_factors). `--density` is absolute:
N on every triangle unless `--detail-factor` asks for the levels. The estimate counts every level.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from psao.server.errors import ConfigError

if TYPE_CHECKING:  # the CLI imports this module for its arguments; loading scenes pulls in Warp
    from psao.scene.model import Scene

# Final points per AO-distance squared: the courtyard's 256 points per unit^2 at its AO distance of 1.5.
POINTS_PER_AO_AREA = 256.0 * 1.5 ** 2
# Peak resident bytes per final point of a bake (point generation, grid, tracing), measured on the
# courtyard at N = 256 and 1024 (446 and 300 bytes per point above the interpreter's own); rounded up.
BYTES_PER_POINT = 512
# Default limit on the points one bake may generate: about 10 GiB by the estimate above, under half of
# a 24 GiB machine.
DEFAULT_MAX_POINTS = 20_000_000
# Detail levels: a triangle is sampled at the largest power of two times N, at most DETAIL_FACTOR, at which
# it holds at most DETAIL_POINTS points; one holding more at N keeps N. On Sponza (the 15,662 visible probes
# of benchmarks/recon_error, 8192-ray truth) the recon MAE was 0.0257 at N, 0.0188 with these levels (2.4
# times the points) and 0.0187 at 4 N everywhere; at N, 70% of it sat on the triangles holding fewer than 4
# points, a quarter of the surface.
DETAIL_POINTS = 128.0
DETAIL_FACTOR = 4


@dataclass
class SamplingSettings:
    # final points per world unit^2 on every instance; None: POINTS_PER_AO_AREA / ao_distance^2 times each
    # instance's factor (instance_factors)
    density: float | None = None
    points: float | None = None  # total point budget instead of a density (both sides of double-sided meshes)
    max_points: float = DEFAULT_MAX_POINTS  # refuse to generate more than this many points
    # most times N a small triangle gets (detail_factors), 1: N everywhere; None: DETAIL_FACTOR with the default
    # density or a point budget, 1 with an explicit density
    detail_factor: int | None = None

    def check(self) -> None:
        if self.density is not None and self.points is not None:
            raise ConfigError("give either a density or a point budget, not both")
        for name, value in (("density", self.density), ("point budget", self.points), ("max points", self.max_points)):
            if value is not None and not (_is_number(value) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value}")
        if self.points is not None and self.points < 1:
            raise ConfigError(f"point budget must be at least 1 point, got {self.points}")
        if self.detail_factor is not None:
            check_detail_factor(self.detail_factor)

    def factor(self) -> int:
        """The detail factor this setting samples with (detail_factor resolved)."""
        if self.detail_factor is not None:
            return int(self.detail_factor)
        return 1 if self.density is not None else DETAIL_FACTOR


def check_detail_factor(value) -> None:
    if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and 1 <= value <= 64
            and value & (value - 1) == 0):
        raise ConfigError(f"detail factor must be a power of two within 1..64, got {value}")


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def add_arguments(p) -> None:
    """--density / --points / --max-points on an argparse parser (bake and serve)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument("--density", type=float, default=None,
                       help=f"points per world unit^2 after elimination, on every instance; without it {POINTS_PER_AO_AREA:g} / "
                            "AO distance^2, the courtyard's 256 at its AO distance 1.5, so files in any units get the same "
                            "sampling (each [[instance]] of a TOML scene without ao_distance at its own size)")
    group.add_argument("--points", type=float, default=None, metavar="COUNT",
                       help="total point budget instead of a density (e.g. 2e6)")
    p.add_argument("--detail-factor", type=int, default=SamplingSettings.detail_factor, metavar="F",
                   help=f"a triangle that holds fewer than {DETAIL_POINTS:g} points gets up to F times the density, as many "
                        f"as keep it under (a power of two; 1: the same density everywhere; default {DETAIL_FACTOR} without "
                        "--density, 1 with it)")
    p.add_argument("--max-points", type=float, default=SamplingSettings.max_points, metavar="COUNT",
                   help=f"refuse, before generating anything, a setting estimated above this many points "
                        f"({DEFAULT_MAX_POINTS:,} is about {DEFAULT_MAX_POINTS * BYTES_PER_POINT / 2 ** 30:.0f} GiB)")


def bake_kwargs(args) -> dict:
    """BakeSettings fields from the arguments add_arguments defined."""
    return {"density": args.density, "points": args.points, "max_points": args.max_points,
            "detail_factor": args.detail_factor}


def detail_factors(world_areas: np.ndarray, density: float, max_factor: int = DETAIL_FACTOR) -> np.ndarray:
    """Density factor of each triangle (world areas) at density `density`: the largest power of two
    f <= max_factor with f * density * area <= DETAIL_POINTS, 1 where there is none."""
    want = DETAIL_POINTS / np.maximum(density * np.asarray(world_areas, np.float64), 1e-300)
    return np.exp2(np.floor(np.log2(np.clip(want, 1.0, float(max_factor))))).astype(np.int64)


def level_counts(world_areas: np.ndarray, density: float, min_points: int,
                 max_factor: int = DETAIL_FACTOR) -> list[tuple[int, np.ndarray | None]]:
    """Final points of one side of an instance, by density level: [(count, triangles of the level)]. One
    level over every triangle (None) where no triangle is detailed, or where the instance is so small that
    min_points decides its count; else one per factor, round(factor * density * area of its triangles)."""
    plain = int(round(density * float(np.sum(world_areas))))
    factor = detail_factors(world_areas, density, max_factor)
    if plain < min_points or not (factor > 1).any():
        return [(max(int(min_points), plain), None)]
    return [(int(round(f * density * float(world_areas[factor == f].sum()))), factor == f) for f in np.unique(factor)]


def scene_triangle_areas(scene: Scene) -> list[np.ndarray]:
    """World area of each triangle (one side) of every instance; instances of one mesh placed with the same
    linear part share one array."""
    seen: dict[tuple, np.ndarray] = {}
    out = []
    for inst in scene.instances:
        linear = np.asarray(inst.transform, np.float64)[:3, :3]
        key = (inst.mesh, linear.tobytes())
        if key not in seen:
            seen[key] = scene.meshes[inst.mesh].triangle_areas(linear)
        out.append(seen[key])
    return out


def default_density(scene: Scene) -> float:
    """The plain density at the scene's AO distance (instances of their own scale get instance_factors times it)."""
    return POINTS_PER_AO_AREA / float(scene.ao_distance) ** 2


def instance_factors(scene: Scene) -> np.ndarray:
    """Per instance, the factor on the scene's plain density its own sampling scale asks for: (scene AO
    distance / Instance.sampling_scale)^2, 1 for an instance without one; never below 1."""
    d = float(scene.ao_distance)
    return np.array([max(1.0, (d / i.sampling_scale) ** 2) if i.sampling_scale > 0 else 1.0
                     for i in scene.instances], np.float64)


@dataclass
class Density:
    """The density a bake samples with: `plain` per world unit^2 times `factors[k]` on instance k."""
    plain: float
    factors: np.ndarray  # (instances,) float64, >= 1
    estimate: int  # final points, detail levels included (estimate_points)

    def of(self, k: int) -> float:
        """The plain density of instance k."""
        return self.plain * float(self.factors[k])


def estimate_points(scene: Scene, density: float, min_points: int, detail_factor: int,
                    triangle_areas: list[np.ndarray] | None = None, factors: np.ndarray | None = None) -> int:
    """Final points generation will produce at plain density `density` times each instance's factor (default
    1) before any overflow: per instance and side the sum of level_counts."""
    if triangle_areas is None:
        triangle_areas = scene_triangle_areas(scene)
    if factors is None:
        factors = np.ones(len(scene.instances))
    total = 0
    for inst, areas, f in zip(scene.instances, triangle_areas, factors):
        sides = 2 if scene.meshes[inst.mesh].double_sided else 1
        total += sides * sum(n for n, _ in level_counts(areas, density * float(f), min_points, detail_factor))
    return int(total)


def budget_density(scene: Scene, budget: float, min_points: int, detail_factor: int,
                   triangle_areas: list[np.ndarray], total_area: float, factors: np.ndarray) -> float:
    """The plain density whose points, with the instances' factors and detail levels, come to at most
    `budget`: budget / area where its estimate is within it (no triangle detailed there, no rounding up),
    else the largest density found by bisection whose estimate stays within it. `total_area` is weighted by
    the factors."""
    lo, hi = budget / (total_area * detail_factor), budget / total_area
    if estimate_points(scene, hi, min_points, detail_factor, triangle_areas, factors) <= budget:
        return hi
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        if estimate_points(scene, mid, min_points, detail_factor, triangle_areas, factors) <= budget:
            lo = mid
        else:
            hi = mid
    return lo


def resolve_density(scene: Scene, settings: SamplingSettings, min_points: int) -> Density:
    """The density for a scene, or ConfigError with one line naming the count and what to pass when the
    estimate exceeds settings.max_points. An explicit density is the same on every instance; the default
    and a point budget keep the instances' factors. Costs one pass over the triangles."""
    settings.check()
    triangle_areas = scene_triangle_areas(scene)
    factors = np.ones(len(scene.instances)) if settings.density is not None else instance_factors(scene)
    sides = np.array([2 if scene.meshes[i.mesh].double_sided else 1 for i in scene.instances])
    total_area = float(sum(float(a.sum()) * s * f for a, s, f in zip(triangle_areas, sides, factors)))
    if not (math.isfinite(total_area) and total_area > 0):
        raise ConfigError(f"scene {scene.name}: surface area is {total_area}, cannot place points")
    if settings.density is not None:
        density = float(settings.density)
    elif settings.points is not None:
        density = budget_density(scene, settings.points, min_points, settings.factor(), triangle_areas, total_area,
                                 factors)
    else:
        density = default_density(scene)
    count = estimate_points(scene, density, min_points, settings.factor(), triangle_areas, factors)
    if count > settings.max_points:
        fit = budget_density(scene, settings.max_points, min_points, settings.factor(), triangle_areas, total_area,
                             factors)
        raise ConfigError(
            f"scene {scene.name}: density {density:.4g} per unit^2 would generate about {count:,} points "
            f"(~{count * BYTES_PER_POINT / 2 ** 30:.1f} GiB), above the limit of {settings.max_points:,.0f}; "
            f"pass --density {fit:.4g} or --points {settings.max_points:.0f} (or raise --max-points)")
    return Density(density, factors, count)
