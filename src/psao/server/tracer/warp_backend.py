"""Warp back-end: the same visibility computation as a Warp kernel over wp.Mesh BVHs.

Runs on CUDA when a GPU is present and on Warp's CPU device otherwise (useful for testing the kernel
against the Embree back-end here). Directions follow src/psao/server/tracer/directions.py exactly (same hash,
same stratified set, same frame), so both back-ends trace the same rays up to float rounding. Its account
(CpuAccount) counts the kernel's seconds, launch to device synchronised, as the rays' own: the copies to
and from the device are the call's fixed cost.
"""
from __future__ import annotations

import time

import numpy as np

from psao.server.errors import TracerError
from psao.server.settings import TraceSettings
from psao.server.tracer.base import CpuAccount, Tracer
from psao.server.tracer.directions import OFFSET_AO, OFFSET_REL, rotation_of, slice_count

try:
    import warp as wp
    _IMPORT_ERROR = None
except ImportError as exc:  # pragma: no cover
    wp = None
    _IMPORT_ERROR = exc

if wp is not None:
    from psao.server.tracer.kernels import visibility_kernel


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
        self.account = CpuAccount()

    def _mesh(self, vertices, faces):
        if vertices is None or len(faces) == 0:
            return None
        v = (np.asarray(vertices, np.float64) - self.center).astype(np.float32)
        return wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=self.device),
                       indices=wp.array(np.asarray(faces, np.int32).reshape(-1), dtype=wp.int32, device=self.device))

    def set_static(self, vertices, faces) -> None:
        self._static = self._mesh(vertices, faces)

    def set_dynamic(self, vertices, faces, rigid_transforms=None, parts=None) -> None:
        vertices, faces = self.merge_rigid(vertices, faces, rigid_transforms)
        self._dynamic = self._mesh(vertices, faces) if vertices is not None else None

    def visibility(self, positions, normals, point_ids, settings: TraceSettings, progress=None,
                   slice_of=None) -> np.ndarray:
        n = len(positions)
        if n == 0:
            return np.zeros(0, np.float32)
        ra, rb = rotation_of(point_ids, settings.seed)
        pos = (np.asarray(positions, np.float64) - self.center).astype(np.float32)
        dev = self.device
        out = wp.zeros(n, dtype=float, device=dev)
        first = settings.slice if slice_of is None else slice_of
        inputs = [self._static.id if self._static else wp.uint64(0), self._dynamic.id if self._dynamic else wp.uint64(0),
                  wp.array(pos, dtype=wp.vec3, device=dev), wp.array(np.asarray(normals, np.float32), dtype=wp.vec3, device=dev),
                  wp.array(ra, dtype=float, device=dev), wp.array(rb, dtype=float, device=dev),
                  int(settings.rays), wp.array(np.broadcast_to(first, n).astype(np.int32), dtype=int, device=dev),
                  int(settings.slices), int(slice_count(first, settings.rays, settings.slices)),
                  float(settings.ao_distance), float(OFFSET_REL), float(OFFSET_AO)]
        wp.synchronize_device(dev)  # the uploads done: the clock below times the kernel alone
        t0 = time.perf_counter()
        wp.launch(visibility_kernel, dim=n, inputs=inputs, outputs=[out], device=dev)
        wp.synchronize_device(dev)
        seconds = time.perf_counter() - t0
        self.account.add(n * settings.rays_traced, seconds, seconds)
        vis = out.numpy()
        if progress is not None:
            progress(n)
        return vis

    def throughput(self) -> dict:
        """Rays per second of the kernel (the copies to and from the device apart)."""
        a = self.account
        return {"rays_per_second": a.rays / a.cpu_total} if a.cpu_total > 0 else {}
