"""Warp back-end: the same visibility computation as a Warp kernel over wp.Mesh BVHs.

Runs on CUDA when a GPU is present and on Warp's CPU device otherwise (useful for testing the kernel
against the Embree back-end here). Directions follow psao_server/tracer/directions.py exactly (same hash,
same stratified set, same frame), so both back-ends trace the same rays up to float rounding.
"""
from __future__ import annotations

import numpy as np

from psao_server.errors import TracerError
from psao_server.tracer.base import TraceSettings, Tracer
from psao_server.tracer.directions import OFFSET_AO, OFFSET_REL, rotation_of

try:
    import warp as wp
    _IMPORT_ERROR = None
except ImportError as exc:  # pragma: no cover
    wp = None
    _IMPORT_ERROR = exc

if wp is not None:
    wp.config.quiet = True

    @wp.func
    def _occluded(mesh: wp.uint64, o: wp.vec3, d: wp.vec3, tmax: float) -> int:
        if mesh == wp.uint64(0):
            return 0
        q = wp.mesh_query_ray(mesh, o, d, tmax)
        if q.result:
            return 1
        return 0

    @wp.kernel
    def visibility_kernel(
        static_mesh: wp.uint64,
        dynamic_mesh: wp.uint64,
        positions: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        rot_a: wp.array(dtype=float),
        rot_b: wp.array(dtype=float),
        rays: int,
        ao_distance: float,
        offset_rel: float,
        offset_ao: float,
        out_visibility: wp.array(dtype=float),
    ):
        i = wp.tid()
        p = positions[i]
        n = normals[i]
        mag = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2]))
        o = p + n * (offset_rel * mag + offset_ao * ao_distance)
        sign = 1.0
        if n[2] < 0.0:
            sign = -1.0
        a = -1.0 / (sign + n[2])
        b = n[0] * n[1] * a
        t = wp.vec3(1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0])
        bt = wp.vec3(b, sign + n[1] * n[1] * a, -n[1])
        free = int(0)
        for j in range(rays):
            u1 = (float(j) + 0.5) / float(rays) + rot_a[i]
            u1 = u1 - wp.floor(u1)
            u2 = float(j) * 0.6180339887498949
            u2 = u2 - wp.floor(u2) + rot_b[i]
            u2 = u2 - wp.floor(u2)
            r = wp.sqrt(u1)
            phi = 6.283185307179586 * u2
            d = t * (r * wp.cos(phi)) + bt * (r * wp.sin(phi)) + n * wp.sqrt(wp.max(0.0, 1.0 - u1))
            if _occluded(static_mesh, o, d, ao_distance) == 0:
                if _occluded(dynamic_mesh, o, d, ao_distance) == 0:
                    free += 1
        out_visibility[i] = float(free) / float(rays)


class WarpTracer(Tracer):
    name = "warp"

    def __init__(self, center=(0.0, 0.0, 0.0), device: str | None = None):
        if _IMPORT_ERROR is not None:
            raise TracerError(f"the warp back-end needs warp-lang: {_IMPORT_ERROR}")
        wp.init()
        self.device = device or ("cuda" if wp.is_cuda_available() else "cpu")
        self.center = np.asarray(center, np.float64)
        self._static = None
        self._dynamic = None

    def _mesh(self, vertices, faces):
        if vertices is None or len(faces) == 0:
            return None
        v = (np.asarray(vertices, np.float64) - self.center).astype(np.float32)
        return wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=self.device),
                       indices=wp.array(np.asarray(faces, np.int32).reshape(-1), dtype=wp.int32, device=self.device))

    def set_static(self, vertices, faces) -> None:
        self._static = self._mesh(vertices, faces)

    def set_dynamic(self, vertices, faces) -> None:
        self._dynamic = self._mesh(vertices, faces) if vertices is not None else None

    def visibility(self, positions, normals, point_ids, settings: TraceSettings, progress=None) -> np.ndarray:
        n = len(positions)
        if n == 0:
            return np.zeros(0, np.float32)
        ra, rb = rotation_of(point_ids, settings.seed)
        pos = (np.asarray(positions, np.float64) - self.center).astype(np.float32)
        dev = self.device
        out = wp.zeros(n, dtype=float, device=dev)
        wp.launch(
            visibility_kernel, dim=n,
            inputs=[self._static.id if self._static else wp.uint64(0), self._dynamic.id if self._dynamic else wp.uint64(0),
                    wp.array(pos, dtype=wp.vec3, device=dev), wp.array(np.asarray(normals, np.float32), dtype=wp.vec3, device=dev),
                    wp.array(ra, dtype=float, device=dev), wp.array(rb, dtype=float, device=dev),
                    int(settings.rays), float(settings.ao_distance), float(OFFSET_REL), float(OFFSET_AO)],
            outputs=[out], device=dev,
        )
        vis = out.numpy()
        if progress is not None:
            progress(n)
        return vis

    def raw_occlusion_rate(self, positions, normals, point_ids, settings) -> float:
        import time
        wp.synchronize()
        t0 = time.perf_counter()
        self.visibility(positions, normals, point_ids, settings)
        wp.synchronize()
        return len(positions) * settings.rays / (time.perf_counter() - t0)
