"""Bare embreex on exactly the rays the tracer traces, with as many processes: the baseline of the
tracer's throughput.

The rays (origins and directions of psao_server.tracer.directions for the given points, ids, seed and
ray count) are computed before the worker processes are forked, so the bare run pays for nothing but
Embree's occlusion queries over the same scenes (static, plus the moving part of a tick merged into
world triangles, built before timing), in chunks of the same size, on a pool of the same size. Only a
count of occluded rays per chunk comes back.

    bare = BareEmbree(static_v, static_f, dynamic_v, dynamic_f, center, workers)
    seconds = bare.time(positions, normals, ids, TraceSettings(...))
"""
from __future__ import annotations

import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from psao_server.settings import TraceSettings
from psao_server.tracer.directions import cosine_directions, ray_origins

_STATE: dict = {}


def _init(static, dynamic):
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
        _STATE["org"] = np.repeat(ray_origins(pos, nrm, s.ao_distance), s.rays, axis=0).astype(np.float32)
        _STATE["dirs"] = cosine_directions(np.asarray(ids, np.int64), nrm, s.rays, s.seed).reshape(-1, 3).astype(np.float32)
        step = max(1, min(s.chunk_points, -(-len(pos) // self.workers))) * s.rays
        jobs = [(i, min(i + step, len(_STATE["org"])), s.ao_distance) for i in range(0, len(_STATE["org"]), step)]
        out = []
        with ProcessPoolExecutor(self.workers, mp_context=mp.get_context("fork"), initializer=_init,
                                 initargs=(self.static, self.dynamic)) as pool:
            list(pool.map(_warm, range(self.workers)))
            for _ in range(repeats):
                t0 = time.perf_counter()
                list(pool.map(_trace, jobs))
                out.append(time.perf_counter() - t0)
        _STATE.pop("org", None)
        _STATE.pop("dirs", None)
        return float(np.median(out))
