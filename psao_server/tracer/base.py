"""The tracer interface every back-end implements.

A tracer owns world-space triangles (a static part built once, a dynamic part replaced per tick) in a
frame re-centred on the scene (tracing in float32 far from the origin would lose the geometry's detail)
and answers one question: the visibility of points, the fraction of K cosine-weighted rays that leave
the point unoccluded within the AO distance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TraceSettings:
    rays: int = 128  # rays per point
    ao_distance: float = 1.0  # world units
    seed: int = 0
    workers: int = 0  # 0 = all cores
    chunk_points: int = 2048  # points per work item (bounds memory: chunk * rays directions)


class Tracer:
    name = "base"

    def set_static(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        raise NotImplementedError

    def set_dynamic(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        raise NotImplementedError

    def visibility(self, positions: np.ndarray, normals: np.ndarray, point_ids: np.ndarray,
                   settings: TraceSettings) -> np.ndarray:
        """(P,) float32 visibility in [0, 1] for world-space points and unit normals."""
        raise NotImplementedError

    def throughput(self) -> dict:
        """Measured so far: rays_per_second, and where the back-end can tell, embree_rays_per_second (the
        bare occlusion query on the same rays and workers) and trace_efficiency (their ratio)."""
        return {}

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
