"""The bake's trace of a grid's points at their exact positions (the bake's first trace, densify's re-trace
of the points it renumbered, the accuracy benchmarks' traces)."""
from __future__ import annotations

from dataclasses import fields

import numpy as np

from psao.protocol import pointword as pw
from psao.scene.model import Scene
from psao.server.geometry import grid_world_points
from psao.server.grid import Grid, PointTable
from psao.server.settings import TraceSettings
from psao.server.tracer.base import Tracer
from psao.server.tracer.static_hits import StaticHits


def trace_grid_points(grid: Grid, scene: Scene, tracer: Tracer, settings: TraceSettings, progress=None,
                      point_ids: np.ndarray | None = None, static_hits: StaticHits | None = None) -> np.ndarray:
    """Trace every allocated point (or those with the given ids) at its exact position and store the
    quantised AO. Returns visibility. With `static_hits`, the static scene's answers for the static
    points are kept there (the tracer's static scene must then hold the static instances alone)."""
    t, pos, nrm = grid_world_points(grid, scene)
    if point_ids is not None:
        sel = np.isin(t.point_id, point_ids)
        t = PointTable(*(getattr(t, f.name)[sel] for f in fields(t)))
        pos, nrm = pos[sel], nrm[sel]
    if static_hits is None:
        vis = tracer.visibility(pos, nrm, t.point_id, settings, progress=progress)
    else:
        vis, bits = tracer.visibility_and_static_hits(pos, nrm, t.point_id, settings, progress=progress)
        static = static_hits.static[t.point_id]
        static_hits.keep(t.point_id[static], bits[static])
    grid.set_ao(t.slot, t.index, pw.quantise_ao(vis))
    return vis
