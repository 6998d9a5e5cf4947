"""The tracer interface every back-end implements.

A tracer owns world-space triangles (a static part built once, a dynamic part replaced per tick) in a
frame re-centred on the scene (tracing in float32 far from the origin would lose the geometry's detail)
and answers one question: the visibility of points, the fraction of K cosine-weighted rays that leave
the point unoccluded within the AO distance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.server.errors import ConfigError
from psao.server.settings import TraceSettings


def recentre(vertices: np.ndarray, center: np.ndarray) -> np.ndarray:
    """World -> the tracers' float32 frame centred on the scene."""
    return (np.asarray(vertices, np.float64) - center).astype(np.float32)


def recentre_poses(rigid_transforms, center: np.ndarray) -> np.ndarray | None:
    """4x4 local-to-world poses -> local-to-re-centred-frame (None stays None: no rigid meshes)."""
    if rigid_transforms is None:
        return None
    poses = np.asarray(rigid_transforms, np.float64).reshape(-1, 4, 4).copy()
    poses[:, :3, 3] -= center
    return poses


class CpuAccount:
    """Rays traced and the seconds spent on them: in the bare query (Embree's occlusion call; the Warp
    kernel) and in total (making the rays too), and (`wall`) the share of the callers' wall time those
    totals stand for (a pooled call's worker seconds over its workers), which the tick's budget takes apart
    from a call's fixed cost."""

    def __init__(self):
        self.rays = 0
        self.cpu_query = 0.0
        self.cpu_total = 0.0
        self.wall = 0.0  # each job's total over the processes that ran its call's jobs side by side

    def add(self, rays: int, cpu_query: float, cpu_total: float, side_by_side: int = 1) -> None:
        self.rays += rays
        self.cpu_query += cpu_query
        self.cpu_total += cpu_total
        self.wall += cpu_total / max(side_by_side, 1)

    def rates(self, workers: int) -> dict:
        """Rays per second of the tracer and of the bare query with `workers` processes fully busy."""
        return {"rays_per_second": self.rays * workers / max(self.cpu_total, 1e-9),
                "embree_rays_per_second": self.rays * workers / max(self.cpu_query, 1e-9),
                "trace_efficiency": self.cpu_query / max(self.cpu_total, 1e-9)}


@dataclass
class TracePart:
    """One batch of EmbreeTracer.visibility_parts: points, their settings and, optionally, the slice of each
    point's ray set to trace (slice_of), the static scene's answers known already (static_hit: whole ray
    sets, (P, rays) bool or (P, ceil(rays / 8)) packed uint8), or a request to keep them (keep_static)."""
    positions: np.ndarray
    normals: np.ndarray
    point_ids: np.ndarray
    settings: TraceSettings
    slice_of: np.ndarray | None = None
    static_hit: np.ndarray | None = None
    keep_static: bool = False


class Tracer:
    """What the bake and the server tick call on a tracer. Back-ends override set_static, set_dynamic and
    visibility; the rest has defaults here for a back-end without them (no workers to start, no static
    hits of its own, no measured rays)."""

    name = "base"
    # whether visibility_and_static_hits works and visibility_parts takes and keeps the static scene's
    # answers (TracePart.static_hit, keep_static): the Embree back-end's static and moving scenes
    supports_static_hits = False
    # the rays traced and the seconds they took (the tick's budget reads CpuAccount.wall); None: not measured
    account: CpuAccount | None = None
    tasks_done = 0  # work items finished on other machines' workers (only the Dask back-end sends any)
    _rigid_meshes: tuple | list[tuple[np.ndarray, np.ndarray]] = ()  # what the default set_rigid keeps

    def set_static(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        raise NotImplementedError

    def set_rigid(self, meshes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Rigidly moving meshes, (local vertices, faces) each, placed per tick by set_dynamic's
        `rigid_transforms`. Call before tracing starts. This default keeps them to merge into world
        triangles (merge_rigid) for back-ends that rebuild their moving scene every tick anyway."""
        self._rigid_meshes = [(np.asarray(v, np.float64), np.asarray(f, np.int64)) for v, f in meshes]

    def set_dynamic(self, vertices: np.ndarray, faces: np.ndarray, rigid_transforms: np.ndarray | None = None,
                    parts=None) -> None:
        """The moving part of the scene now: world triangles that deform (None: none), optionally the vertex
        count of each separately deforming piece of them (`parts`, consecutive; a back-end may keep one
        acceleration structure per piece and refit it), and the 4x4 local-to-world transforms of the
        set_rigid meshes (None: leave them out)."""
        raise NotImplementedError

    def merge_rigid(self, vertices, faces, rigid_transforms) -> tuple[np.ndarray | None, np.ndarray]:
        """World triangles of the deforming part and of the rigid meshes at their transforms, merged."""
        parts_v = [] if vertices is None else [np.asarray(vertices, np.float64)]
        parts_f = [] if vertices is None else [np.asarray(faces, np.int64)]
        base = sum(len(v) for v in parts_v)
        if rigid_transforms is not None:
            for (v, f), m in zip(self._rigid_meshes, np.asarray(rigid_transforms, np.float64)):
                parts_v.append(v @ m[:3, :3].T + m[:3, 3])
                parts_f.append(f + base)
                base += len(v)
        if not parts_v:
            return None, np.zeros((0, 3), np.int64)
        return np.concatenate(parts_v), np.concatenate(parts_f)

    def visibility(self, positions: np.ndarray, normals: np.ndarray, point_ids: np.ndarray,
                   settings: TraceSettings, progress=None, slice_of: np.ndarray | None = None) -> np.ndarray:
        """(P,) float32 visibility in [0, 1] for world-space points and unit normals, over the slice
        `settings.slice` of each point's ray set, or with `slice_of` ((P,) ints) a slice per point (the
        Embree and Warp back-ends; `settings.slices` must then divide `settings.rays`)."""
        raise NotImplementedError

    def visibility_and_static_hits(self, positions: np.ndarray, normals: np.ndarray, point_ids: np.ndarray,
                                   settings: TraceSettings, progress=None) -> tuple[np.ndarray, np.ndarray]:
        """visibility, and which of each point's rays the static scene occludes (bit-packed per point),
        for a back-end with supports_static_hits; this default refuses."""
        raise ConfigError(f"the {self.name} tracer takes no static hits (it keeps no static scene's answers)")

    def visibility_parts(self, parts: list[TracePart]) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """(visibility, static hits kept or None) of each part, traced together where the back-end can.
        This default traces part by part with visibility and keeps no static hits: a part that carries them
        (static_hit) or asks to keep them (keep_static) is refused rather than traced without them."""
        if any(p.static_hit is not None or p.keep_static for p in parts):
            raise ConfigError(f"the {self.name} tracer takes no static hits (not supports_static_hits)")
        return [(self.visibility(p.positions, p.normals, p.point_ids, p.settings,
                                 **({} if p.slice_of is None else {"slice_of": p.slice_of})), None) for p in parts]

    def warm_up(self) -> None:
        """Start whatever the back-end's first trace would (worker processes, a cluster's scene), so that
        start-up is not counted as tracing time. Nothing to start by default."""

    def throughput(self) -> dict:
        """Measured so far: rays_per_second, and where the back-end can tell, embree_rays_per_second (the
        bare occlusion query on the same rays and workers) and trace_efficiency (their ratio)."""
        return {}

    def progress_note(self) -> str:
        """A few words for the progress line beyond points and rays (e.g. a cluster's tasks done / total)."""
        return ""

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
