"""Bake: points -> grid -> traced AO, and the accuracy of what the client will reconstruct from it.

This is everything the server does before it streams anything; `psao bake` exposes it as an AO baker.
"""
from __future__ import annotations

import os
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass, fields

import numpy as np

from psao.protocol import gridformat as gf
from psao.protocol.reconstruct import reconstruct_ao
from psao.scene.model import Scene
from psao.server.geometry import scene_center, scene_point_ids, scene_world_geometry, to_world
from psao.server.points.buried import BuriedTest
from psao.server.points.densify import densify
from psao.server.points.gapfill import fill_gaps
from psao.server.grid import Grid
from psao.server.points.generate import PointSet, generate_scene_points, spawn_uniform
from psao.server.points.pool import generate_scene_points_parallel
from psao.server.points.sampling import resolve_density
from psao.server.settings import BakeSettings, GridSettings, PointSettings, ProbeSettings, TraceSettings
from psao.server.tick.animate import classify_instances
from psao.server.tracer import Tracer, make_tracer
from psao.server.tracer.grid_trace import trace_grid_points
from psao.server.tracer.static_hits import StaticHits

# A bake estimated at this many points or more generates its instances' points in `workers` processes
# (below this the points take little longer than starting the processes and sending them the scene).
PARALLEL_POINTS = 100_000


@dataclass
class BakeResult:
    scene: Scene
    grid: Grid
    pointsets: list[PointSet]
    stats: dict
    tracer: Tracer  # still open: the server keeps tracing with it; close() when done
    # which of each static point's rays the static scene occludes, kept from the bake's trace of a scene with
    # moving instances (psao.server.tracer.static_hits); None when not kept (no movers, or a tracer that cannot)
    static_hits: StaticHits | None = None


# ---------------------------------------------------------------- grid
def build_scene_grid(scene: Scene, pointsets: list[PointSet], settings: GridSettings | None = None) -> Grid:
    """The grid of a scene's point sets, one per instance: double-sided instances flagged, their
    back-side points (PointSet.back) in back-side cells, every point under its scene_point_ids id."""
    flags = [gf.FLAG_DOUBLE_SIDED if scene.meshes[i.mesh].double_sided else 0 for i in scene.instances]
    return Grid.build([(ps.positions, ps.normals, ps.poisson_radius, f, ps.back if f else None)
                       for ps, f in zip(pointsets, flags)], settings, point_ids=scene_point_ids(pointsets))


# ---------------------------------------------------------------- bake
def _progress(enabled: bool):
    if not enabled:
        return nullcontext(None)
    # (rich: imported only when a bar is shown, not by every import of the bake)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    transient=True, console=None)


def make_bake_tracer(scene: Scene, settings: BakeSettings) -> Tracer:
    """The tracer a bake uses: the dask back-end on settings.cluster, else the named local back-end."""
    center = scene_center(scene)
    if settings.cluster is not None:
        return make_tracer("dask", center, cluster=settings.cluster, scene_spec=scene.source)
    return make_tracer(settings.tracer, center, **({"workers": settings.workers} if settings.tracer == "embree" else {}))


# A bake's stages and the share of its whole each ends at, for a report(fraction, text) of the whole bake
# (psao serve's Status messages while it bakes): the trace is most of a bake's time.
STAGE_ENDS = {"points": 0.25, "gap fill": 0.35, "trace": 0.95, "densify": 1.0}


class BakeProgress:
    """The bake's progress to a rich bar (a terminal) and to report(fraction 0..1 of the whole bake, text),
    each optional: stage(name, total) gives the stage's callback (done, total) -> None."""

    def __init__(self, bar, report=None):
        self.bar, self.report = bar, report

    def stage(self, name: str, total: int):
        if self.bar is None and self.report is None:
            return None
        task = self.bar.add_task(name, total=total) if self.bar else None
        names = list(STAGE_ENDS)
        start = STAGE_ENDS[names[names.index(name) - 1]] if names.index(name) else 0.0

        def update(done: int, total: int = total, description: str | None = None) -> None:
            if self.bar is not None:
                self.bar.update(task, completed=done, **({"description": description} if description else {}))
            if self.report is not None:
                share = min(done / total, 1.0) if total else 1.0
                self.report(start + (STAGE_ENDS[name] - start) * share, f"baking: {description or name}")
        return update

    def trace(self, total: int, tracer: Tracer, rays: int):
        """A progress callback for Tracer.visibility: the points traced so far, and the rays per second
        (across all of a cluster's workers) and whatever the tracer adds (tasks done)."""
        update = self.stage("trace", total)
        if update is None:
            return None
        start = time.perf_counter()
        done = 0

        def advance(k: int) -> None:
            nonlocal done
            done += k
            rate = done * rays / max(time.perf_counter() - start, 1e-9)
            note = tracer.progress_note()
            update(done, description=f"trace {rate / 1e6:.1f} Mrays/s" + (f", {note}" if note else ""))
        return advance


def load_bake_geometry(tracer: Tracer, scene: Scene, settings: BakeSettings) -> tuple[list[int], list[int]] | None:
    """The whole scene (at its instances' transforms) into the bake's tracer. With moving instances and a
    tracer that keeps static hits (settings.keep_static_hits), the static instances go into its static
    scene and the moving ones into its moving part, so each trace answers from the static scene first
    and its answers can be kept: returns (static, moving) instance lists then, else None."""
    kinds = classify_instances(scene)
    if not (settings.keep_static_hits and kinds.moving and tracer.supports_static_hits):
        tracer.set_static(*scene_world_geometry(scene))
        return None
    tracer.set_static(*scene_world_geometry(scene, kinds.static))
    tracer.set_dynamic(*scene_world_geometry(scene, kinds.moving))
    return kinds.static, kinds.moving


def bake_scene(scene: Scene, settings: BakeSettings | None = None, show_progress: bool | None = None,
               report=None) -> BakeResult:
    """Points, grid and traced AO of `scene`. A progress bar on a terminal (show_progress None) or when
    asked; `report(fraction 0..1, text)`, if given, hears the whole bake's progress (BakeProgress)."""
    settings = settings or BakeSettings()
    settings.check()
    if show_progress is None:
        show_progress = sys.stderr.isatty()
    # Before anything is allocated: the density this scene gets and the points it will take (ConfigError
    # naming the count and what to pass above settings.max_points).
    density = resolve_density(scene, settings.sampling(), settings.min_points)
    stats: dict = {"scene": scene.name, "density": density.plain,
                   "density_max": density.plain * float(density.factors.max()), "points_estimated": density.estimate,
                   "rays": settings.rays, "seed": settings.seed}
    tracer = make_bake_tracer(scene, settings)
    try:
        return _bake_with(tracer, scene, settings, show_progress, stats, tuple(float(f) for f in density.factors), report)
    except BaseException:
        tracer.close()  # a cluster started for this bake goes with it
        raise


def _bake_with(tracer: Tracer, scene: Scene, settings: BakeSettings, show_progress: bool, stats: dict,
               factors: tuple[float, ...], report=None) -> BakeResult:
    split = load_bake_geometry(tracer, scene, settings)
    trace_settings = TraceSettings(rays=settings.rays, ao_distance=scene.ao_distance, seed=settings.seed)
    with _progress(show_progress) as bar:
        shown = BakeProgress(bar, report)
        t0 = time.perf_counter()
        buried = BuriedTest(scene) if settings.skip_buried else None
        point_settings = PointSettings(density=stats["density"], min_points=settings.min_points, seed=settings.seed,
                                       spawn_ratio=settings.spawn_ratio, detail_factor=settings.sampling().factor(),
                                       instance_factors=factors)
        progress = shown.stage("points", len(scene.instances))
        workers = settings.workers or os.cpu_count() or 1
        if workers > 1 and len(scene.instances) > 1 and stats["points_estimated"] >= PARALLEL_POINTS:
            pointsets = generate_scene_points_parallel(scene, point_settings, workers, settings.skip_buried, progress)
        else:
            pointsets = generate_scene_points(scene, point_settings, progress=progress, buried=buried)
        stats["seconds_points"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        def build(sets: list[PointSet]) -> Grid:
            return build_scene_grid(scene, sets, settings.grid)

        grid = build(pointsets)
        stats["seconds_grid"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        added = 0
        if settings.gap_fill.passes > 0:
            pointsets, grid, added = fill_gaps(scene, pointsets, grid, build, settings.gap_fill,
                                               progress=shown.stage("gap fill", settings.gap_fill.passes),
                                               buried=buried)
        stats["points_gap_fill"] = int(added)
        stats["seconds_gap_fill"] = time.perf_counter() - t0

        tracer.warm_up()  # worker start-up is not tracing time
        n = grid.n_points()
        t0 = time.perf_counter()
        static_hits = None
        if split is not None:
            ids = scene_point_ids(pointsets)
            static_hits = StaticHits(sum(len(x) for x in ids), settings.rays, settings.seed,
                                     np.concatenate([ids[i] for i in split[0]]) if split[0] else None)
        trace_grid_points(grid, scene, tracer, trace_settings,
                          progress=shown.trace(n, tracer, settings.rays),
                          static_hits=static_hits)
        stats["seconds_trace"] = time.perf_counter() - t0
        n_traced = n  # the first trace's points (densify's traces are timed apart)

        t0 = time.perf_counter()
        added = 0
        if settings.densify.runs_with(settings.rays):
            pointsets, added = densify(scene, pointsets, grid, tracer, trace_settings, settings.densify, buried,
                                       progress=shown.stage("densify", settings.densify.rounds))
            n = grid.n_points()
            if added:
                static_hits = None  # densify renumbers the point ids the kept answers are indexed by
        stats["points_densify"] = int(added)
        stats["seconds_densify"] = time.perf_counter() - t0
    grid.take_dirty()
    stats.update(
        points_spawned=int(sum(ps.spawned for ps in pointsets)),
        points_generated=int(sum(len(ps) for ps in pointsets)),
        points_kept=n,
        points_dropped_overflow=int(grid.stats.dropped),
        cells=int(len(grid.allocated_cells())),
        buckets=int(len(grid.buckets)),
        buckets_used=int(len(grid.allocated_buckets())),
        rays_per_second_wall=n_traced * settings.rays / max(stats["seconds_trace"], 1e-9),
        tracer=tracer.name,
    )
    # rates from the seconds inside the workers (query alone and whole chunks); the wall rate above is what a user waits
    stats.update(tracer.throughput())
    stats.setdefault("rays_per_second", stats["rays_per_second_wall"])
    if static_hits is not None:
        stats["static_hits_bytes"] = static_hits.nbytes
    return BakeResult(scene=scene, grid=grid, pointsets=pointsets, stats=stats, tracer=tracer, static_hits=static_hits)


# ---------------------------------------------------------------- accuracy
@dataclass
class Probes:
    instance: np.ndarray  # (M,)
    world_pos: np.ndarray  # (M, 3)
    world_normal: np.ndarray  # (M, 3)
    local_pos: np.ndarray
    local_normal: np.ndarray

    def subset(self, mask: np.ndarray) -> "Probes":
        return Probes(*(getattr(self, f.name)[mask] for f in fields(self)))


def sample_probes(scene: Scene, count: int, seed: int = 12345) -> Probes:
    """Random surface points, area-weighted over all instances (world area), independent of the
    generation points; a random side for double-sided surfaces."""
    rng = np.random.default_rng(seed)
    per_inst = []
    for inst in scene.instances:
        mesh = scene.meshes[inst.mesh]
        per_inst.append(mesh.triangle_areas(inst.transform[:3, :3]))
    totals = np.array([a.sum() for a in per_inst])
    counts = rng.multinomial(count, totals / totals.sum())
    out = {k: [] for k in ("instance", "world_pos", "world_normal", "local_pos", "local_normal")}
    for i, (inst, areas, k) in enumerate(zip(scene.instances, per_inst, counts)):
        if k == 0:
            continue
        mesh = scene.meshes[inst.mesh]
        faces, bary = spawn_uniform(rng, areas, int(k))
        tri = mesh.vertices[mesh.faces[faces]]
        local = np.einsum("pk,pkj->pj", bary, tri)
        normal = mesh.face_normals()[faces].astype(np.float32)
        if mesh.double_sided:
            flip = rng.random(len(normal)) < 0.5
            normal[flip] *= -1
        wp_, wn = to_world(inst.transform, local, normal)
        out["instance"].append(np.full(int(k), i))
        out["world_pos"].append(wp_)
        out["world_normal"].append(wn)
        out["local_pos"].append(local)
        out["local_normal"].append(normal)
    return Probes(**{k: np.concatenate(v) for k, v in out.items()})


def reconstruction_error(grid: Grid, scene: Scene, tracer: Tracer, probes: Probes, rays: int = ProbeSettings.rays,
                         seed: int = 777) -> dict:
    """MAE between the reconstructed AO and AO traced directly at the probes (many rays), hole fraction."""
    truth = tracer.visibility(probes.world_pos, probes.world_normal, np.arange(len(probes.instance)) + (1 << 30),
                              TraceSettings(rays=rays, ao_distance=scene.ao_distance, seed=seed))
    ao, wsum = reconstruct_ao(grid.instances, grid.buckets, grid.cells, probes.instance, probes.local_pos, probes.local_normal)
    err = np.abs(ao - truth)
    return {
        "recon_mae": float(err.mean()),
        "recon_p99": float(np.quantile(err, 0.99)),
        "hole_fraction": float((wsum == 0).mean()),
        "probes": int(len(err)),
        "probe_rays": rays,
    }
