"""Bare embreex on exactly the rays the tracer traces, with as many processes: the baseline of the
tracer's throughput.

Each worker computes the rays (origins and directions of psao.server.tracer.directions for the given
points, ids, seed and ray count) and builds its scenes (static, plus the moving part of a tick merged
into world triangles) when it starts, before timing, so the bare run pays for nothing but Embree's
occlusion queries, in chunks of the same size, on a pool of the same size. Only a count of occluded
rays per chunk comes back. The pool starts from the tracer's fork server (tracer.embree.worker_context)
for the reason given there: a plain fork can inherit a held TBB lock and wait forever.

    bare = BareEmbree(static_v, static_f, dynamic_v, dynamic_f, center, workers)
    seconds = bare.time(positions, normals, ids, TraceSettings(...))
"""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from psao.server.settings import TraceSettings
from psao.server.tracer.directions import cosine_directions, ray_origins
from psao.server.tracer.embree import worker_context

_STATE: dict = {}


def _make_rays(pos, nrm, ids, s: TraceSettings):
    """The tracer's rays for these points (recentred positions): origins and directions, float32 (R, 3)."""
    org = np.repeat(ray_origins(pos, nrm, s.ao_distance), s.rays, axis=0).astype(np.float32)
    dirs = cosine_directions(np.asarray(ids, np.int64), nrm, s.rays, s.seed).reshape(-1, 3).astype(np.float32)
    return org, dirs


def _init(static, dynamic, points):
    from embreex import rtcore, rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    device = rtcore.EmbreeDevice()
    scenes = []
    for v, f in (static, dynamic):
        if v is not None and len(f):
            s = rtcore_scene.EmbreeScene(device)
            TriangleMesh(s, np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.int32))
            scenes.append(s)
    _STATE["scenes"] = scenes
    _STATE["org"], _STATE["dirs"] = _make_rays(*points)


def _trace(job):
    lo, hi, tmax = job
    org, dirs = _STATE["org"][lo:hi], _STATE["dirs"][lo:hi]
    hit = np.zeros(len(org), bool)
    for s in _STATE["scenes"]:
        todo = np.flatnonzero(~hit)
        if len(todo) == 0:
            break
        hit[todo] = s.run(org[todo], dirs[todo], dists=np.full(len(todo), tmax, np.float32), query="OCCLUDED") != -1
    return int(hit.sum())


def _warm(_):
    return len(_STATE["scenes"])


class BareEmbree:
    def __init__(self, static_v, static_f, dynamic_v, dynamic_f, center, workers: int):
        c = np.asarray(center, np.float64)
        recentre = lambda v: None if v is None else (np.asarray(v, np.float64) - c).astype(np.float32)  # noqa: E731
        self.static = (recentre(static_v), np.asarray(static_f, np.int32))
        self.dynamic = (recentre(dynamic_v), np.asarray(dynamic_f, np.int32) if dynamic_f is not None else np.zeros((0, 3), np.int32))
        self.center = c
        self.workers = workers

    def time(self, positions, normals, ids, s: TraceSettings, repeats: int = 1) -> float:
        """Median wall seconds of tracing the rays of these points, `repeats` times, on a fresh pool."""
        pos = (np.asarray(positions, np.float64) - self.center).astype(np.float32)
        nrm = np.asarray(normals, np.float32)
        n_rays = len(pos) * s.rays
        step = max(1, min(s.chunk_points, -(-len(pos) // self.workers))) * s.rays
        jobs = [(i, min(i + step, n_rays), s.ao_distance) for i in range(0, n_rays, step)]
        out = []
        with ProcessPoolExecutor(self.workers, mp_context=worker_context(), initializer=_init,
                                 initargs=(self.static, self.dynamic, (pos, nrm, ids, s))) as pool:
            list(pool.map(_warm, range(self.workers)))
            for _ in range(repeats):
                t0 = time.perf_counter()
                list(pool.map(_trace, jobs))
                out.append(time.perf_counter() - t0)
        return float(np.median(out))
