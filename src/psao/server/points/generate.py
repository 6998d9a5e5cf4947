"""Point generation per mesh instance (paper section 3.1).

Spawn `spawn_ratio * N` (2N) uniform random points per world unit area, area-weighted over the
triangles and uniform in barycentrics, then remove half of them by weighted sample elimination
(Yuksel 2015, "Sample Elimination for Generating Poisson Disk Sample Sets") so N per unit area remain.
With a detail factor above 1 (the bake's default density) triangles small against the point spacing are
sampled denser, at a power of two times N (psao.server.points.sampling.level_counts): each density level is
spawned and eliminated on its own triangles.
Double-sided meshes get every kept point twice, once per side, with opposite normals.

Areas and distances are measured on the world-transformed surface (so a scaled instance gets the right
density in world units), positions are returned in mesh-local space: the same barycentrics on the local
triangle. The translation is left out of the world-space distances: they do not depend on it, and
large offsets would only cost precision.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from psao.scene.model import Mesh, Scene, triangle_areas, triangle_normals
from psao.server.errors import ConfigError
from psao.server.points.sampling import level_counts
from psao.server.settings import PointSettings

_HEX = 2.0 * np.sqrt(3.0)  # area of the hexagonal cell per sample is _HEX * r^2 for Poisson radius r


@dataclass
class PointSet:
    positions: np.ndarray  # (P, 3) float64, mesh-local space
    normals: np.ndarray  # (P, 3) float32 unit, mesh-local, facing the side the point is on
    faces: np.ndarray  # (P,) int64, triangle of origin
    barycentrics: np.ndarray  # (P, 3) float32, weights of the triangle's vertices 0, 1, 2
    back: np.ndarray  # (P,) bool: on the back side of a double-sided mesh (normal flipped, back-side cells)
    poisson_radius: float  # local units: sqrt(A_local / (2 sqrt(3) P_side)), P_side = points on one side
    spawned: int  # points spawned before elimination (both sides counted)

    def __len__(self) -> int:
        return len(self.positions)


def instance_seed(seed: int, instance_index: int) -> int:
    """Seed of one instance: the scene seed mixed with the instance index, so instances differ."""
    return int(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(instance_index)]).generate_state(1)[0])


def _check_geometry(mesh: Mesh, transform: np.ndarray) -> np.ndarray:
    """The 3x3 linear part of the transform after checking mesh and transform; ConfigError otherwise."""
    transform = np.asarray(transform, dtype=np.float64)
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        raise ConfigError(f"mesh {mesh.name!r}: instance transform must be a finite 4x4 matrix")
    if len(mesh.faces) == 0:
        raise ConfigError(f"mesh {mesh.name!r} has no triangles")
    if not np.all(np.isfinite(mesh.vertices[mesh.faces])):
        raise ConfigError(f"mesh {mesh.name!r} has non-finite vertices")
    return transform[:3, :3]


def spawn_uniform(rng: np.random.Generator, areas: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` points uniform over the surface: area-weighted triangle choice, uniform barycentrics."""
    cdf = np.cumsum(areas)
    # sorted draws give points in face order, which meshes keep spatially coherent: the neighbour search
    # and the elimination then touch memory far less randomly (about 2x faster on Sponza)
    faces = np.searchsorted(cdf, np.sort(rng.random(count)) * cdf[-1], side="right")
    faces = np.minimum(faces, len(areas) - 1)  # guards u * total rounding up to total
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)  # the square root makes the density uniform over the triangle, not towards a vertex
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    return faces.astype(np.int64), bary


def _on_triangles(vertices: np.ndarray, tris: np.ndarray, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
    t = tris[faces]
    return sum(bary[:, i : i + 1] * vertices[t[:, i]] for i in range(3))


def neighbour_graph(
    positions: np.ndarray, normals: np.ndarray, d_max: float, d_min: float, alpha: float, normal_cos_min: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symmetric CSR graph of Yuksel's weights w_ij = (1 - max(d_ij, d_min) / d_max)^alpha for d_ij < d_max.

    Rows sorted, columns sorted within a row (the elimination sums them in that order).
    Returns offsets (n+1,) int32, neighbours (E,) int32, weights (E,) float64.
    """
    n = len(positions)
    pairs = cKDTree(positions).query_pairs(d_max, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    delta = positions[i] - positions[j]
    dist = np.sqrt(np.einsum("ij,ij->i", delta, delta))
    keep = dist < d_max
    if normal_cos_min > -1.0:
        keep &= np.einsum("ij,ij->i", normals[i], normals[j]) > normal_cos_min
    i, j, dist = i[keep], j[keep], dist[keep]
    w = np.power(1.0 - np.maximum(dist, d_min) / d_max, alpha)
    # scipy's COO to CSR conversion is a linear-time counting sort; sort_indices orders each short row
    graph = scipy.sparse.csr_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))
    graph.sort_indices()
    return graph.indptr.astype(np.int32), graph.indices.astype(np.int32), graph.data


def elimination_radii(area: float, spawned: int, keep: int, settings: PointSettings) -> tuple[float, float]:
    """(d_max, d_min) of Yuksel's weights: d_max = 2 r_max with r_max the 2D Poisson radius of `keep`
    samples on `area`; d_min is the weight-limiting floor (0 without weight limiting)."""
    d_max = 2.0 * np.sqrt(area / (_HEX * keep))
    if not settings.weight_limiting:
        return d_max, 0.0
    return d_max, d_max * (1.0 - (keep / spawned) ** settings.gamma) * settings.beta


def eliminate(positions: np.ndarray, normals: np.ndarray, area: float, keep: int, settings: PointSettings) -> np.ndarray:
    """Bool mask of the `keep` samples that survive weighted sample elimination on a surface of `area`."""
    if keep >= len(positions):  # nothing to eliminate (spawn ratio 1): the neighbour graph would go unused
        return np.ones(len(positions), bool)
    from psao.server.points.elimination import eliminate_csr  # imports Warp (half a second): not before it is needed

    d_max, d_min = elimination_radii(area, len(positions), keep, settings)
    offsets, nbrs, w = neighbour_graph(positions, normals, d_max, d_min, settings.alpha, settings.normal_cos_min)
    return eliminate_csr(offsets, nbrs, w, keep)


def generate_points(mesh: Mesh, transform: np.ndarray, settings: PointSettings, seed: int | None = None,
                    reject=None) -> PointSet:
    """Points of one instance of `mesh` placed by `transform` (4x4 local-to-world).

    `seed` overrides settings.seed; callers mix the instance index in (instance_seed) so instances differ.
    `reject(world_positions, world_normals) -> bool mask`, if given, removes spawned points before the
    elimination (as the paper rejects points on masked transparent surfaces): the kept count shrinks in
    proportion, so the density on what remains is unchanged.
    """
    settings.check()
    world_vertices = mesh.vertices @ _check_geometry(mesh, transform).T  # translation left out, see above
    world_areas = triangle_areas(world_vertices, mesh.faces)
    world_area = float(world_areas.sum())
    local_area = mesh.area()
    if not world_area > 0 or not local_area > 0:
        raise ConfigError(f"mesh {mesh.name!r} has zero surface area (all triangles degenerate or scaled to 0)")

    rng = np.random.default_rng(settings.seed if seed is None else seed)
    normals_local = mesh.face_normals()
    world_normals = triangle_normals(world_vertices, mesh.faces)
    levels = level_counts(world_areas, settings.density, settings.min_points, settings.detail_factor)
    parts = [_level_points(rng, world_vertices, world_areas, world_normals, mesh.faces, on, keep, settings,
                           transform, reject) for keep, on in levels]
    faces = np.concatenate([f for f, _, _ in parts])
    bary = np.concatenate([b for _, b, _ in parts])
    spawn = sum(n for _, _, n in parts)
    keep = sum(k for k, _ in levels)

    positions = _on_triangles(mesh.vertices, mesh.faces, faces, bary)
    normals = normals_local[faces]
    sides = 2 if mesh.double_sided else 1
    back = np.zeros(len(positions), bool)
    if mesh.double_sided:  # every point again on the back side, with the opposite normal
        positions = np.concatenate([positions, positions])
        normals = np.concatenate([normals, -normals])
        faces = np.concatenate([faces, faces])
        bary = np.concatenate([bary, bary])
        back = np.concatenate([back, ~back])
    return PointSet(
        positions=positions,
        normals=normals.astype(np.float32),
        faces=faces,
        barycentrics=bary.astype(np.float32),
        back=back,
        poisson_radius=float(np.sqrt(local_area / (_HEX * keep))),
        spawned=spawn * sides,
    )


def _level_points(rng, world_vertices, world_areas, world_normals, tris, on, keep, settings, transform, reject):
    """(faces, barycentrics, spawned) of `keep` points on the triangles `on` selects (None: all): spawned
    spawn_ratio times over and thinned by the elimination. `reject` removes spawned points before the
    elimination and shrinks the kept count in proportion (generate_points)."""
    areas = world_areas if on is None else np.where(on, world_areas, 0.0)
    area = float(areas.sum())
    spawn = int(round(settings.spawn_ratio * keep))
    faces, bary = spawn_uniform(rng, areas, spawn)
    world_positions = _on_triangles(world_vertices, tris, faces, bary)
    area_left, keep_left = area, keep
    if reject is not None and spawn:
        out = reject(world_positions + np.asarray(transform, np.float64)[:3, 3], world_normals[faces])
        share = 1.0 - float(np.count_nonzero(out)) / spawn
        faces, bary, world_positions = faces[~out], bary[~out], world_positions[~out]
        area_left, keep_left = area * share, min(len(faces), int(round(keep * share)))
    kept = eliminate(world_positions, world_normals[faces], area_left, keep_left, settings) if keep_left else \
        np.zeros(len(faces), bool)
    return faces[kept], bary[kept], spawn





def instance_points(scene: Scene, settings: PointSettings, k: int, buried=None) -> PointSet:
    """The PointSet of instance k, seeded by instance_seed (independent of every other instance)."""
    inst = scene.instances[k]
    seed = instance_seed(settings.seed, k)
    if settings.instance_factors:
        settings = dataclasses.replace(settings, density=settings.density * settings.instance_factors[k])
    reject = None
    if buried is not None and buried.applies_to(k):
        def reject(pos, nrm, seed=seed):
            return buried.mask(pos, nrm, seed)
    return generate_points(scene.meshes[inst.mesh], inst.transform, settings, seed, reject)


def generate_scene_points(scene: Scene, settings: PointSettings, progress=None, buried=None) -> list[PointSet]:
    """One PointSet per instance of `scene`, in instance order, each seeded by instance_seed.

    `progress`, if given, is called as progress(done_instances, total_instances) after each instance.
    `buried` (psao.server.points.buried.BuriedTest), if given, keeps points off the surfaces it finds buried.
    """
    out = []
    for k in range(len(scene.instances)):
        out.append(instance_points(scene, settings, k, buried))
        if progress is not None:
            progress(k + 1, len(scene.instances))
    return out
