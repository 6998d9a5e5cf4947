"""Tracer back-ends behind one interface (as trimesh's ray module does): import errors are deferred
until a back-end is asked for, so a missing optional back-end never breaks the package.

    make_tracer("embree", center)    Embree through embreex, worker processes (default)
    make_tracer("warp", center)      Warp kernel: CUDA when present, else Warp's CPU device
    make_tracer("dask", center, cluster=ClusterSettings("tcp://host:8786"))
                                     Embree on the workers of a Dask cluster (optional: psao[dask])
"""
from __future__ import annotations

from psao.server.errors import TracerError
from psao.server.settings import TraceSettings
from psao.server.tracer.base import Tracer

BACKENDS = ("embree", "warp", "dask")


def make_tracer(name: str = "embree", center=(0.0, 0.0, 0.0), **kwargs) -> Tracer:
    # each back-end imported only when asked for: its optional dependency's error surfaces here, not on import
    if name == "embree":
        from psao.server.tracer.embree import EmbreeTracer
        return EmbreeTracer(center, **kwargs)
    if name == "warp":
        from psao.server.tracer.warp_backend import WarpTracer
        return WarpTracer(center, **kwargs)
    if name == "dask":
        from psao.server.tracer.dask_backend import DaskTracer
        return DaskTracer(center, **kwargs)
    raise TracerError(f"unknown tracer back-end {name!r} (known: {', '.join(BACKENDS)})")


def available_backends() -> list[str]:
    """Back-ends that can be constructed on this machine without further settings (dask needs a cluster)."""
    found = []
    for name in BACKENDS:
        try:
            make_tracer(name).close()
            found.append(name)
        except TracerError:
            pass
    return found


__all__ = ["BACKENDS", "TraceSettings", "Tracer", "TracerError", "available_backends", "make_tracer"]
