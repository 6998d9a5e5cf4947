"""World-space geometry of a scene and its points: the ground floor the server's stages share.

Points (gap fill, the buried test, densify), the tracer back-ends (the Dask workers' scene), the tick and
the bake all place instances, points and normals in the world through these helpers. It imports no other
psao.server module, so any of them may import it without an import cycle.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only: nothing of psao is imported when this module is
    from psao.scene.model import Scene
    from psao.server.grid import Grid, PointTable
    from psao.server.points.generate import PointSet


def to_world(transform: np.ndarray, local_pos: np.ndarray, local_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local points and normals of an instance -> world (normals by the inverse transpose, renormalised)."""
    m = np.asarray(transform, np.float64)
    pos = np.asarray(local_pos, np.float64) @ m[:3, :3].T + m[:3, 3]
    nrm = np.asarray(local_normal, np.float64) @ np.linalg.inv(m[:3, :3])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    return pos, nrm.astype(np.float32)


def scene_point_ids(pointsets: list[PointSet]) -> list[np.ndarray]:
    """The stable id of every point, per instance: 0..P-1 over the scene's point sets in instance order.
    The grid stores them (they seed each point's rays); the server tick indexes its arrays by them."""
    sizes = [len(ps) for ps in pointsets]
    first = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    return [np.arange(first[i], first[i + 1], dtype=np.int64) for i in range(len(sizes))]


def scene_world_geometry(scene: Scene, instances=None) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles of (some) instances merged into one vertex/face array."""
    verts, faces, base = [], [], 0
    for i in (range(len(scene.instances)) if instances is None else instances):
        inst = scene.instances[i]
        mesh = scene.meshes[inst.mesh]
        v = mesh.vertices @ inst.transform[:3, :3].T + inst.transform[:3, 3]
        verts.append(v)
        faces.append(mesh.faces + base)
        base += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(verts), np.concatenate(faces)


def scene_center(scene: Scene) -> np.ndarray:
    """The centre of the scene's world bounds (the tracers' re-centred frame is centred on it)."""
    lo, hi = scene.world_bounds()
    return 0.5 * (lo + hi)


def grid_world_points(grid: Grid, scene: Scene) -> tuple[PointTable, np.ndarray, np.ndarray]:
    """(point table, world positions, world normals) of every allocated point of the grid."""
    t = grid.point_table()
    pos = np.empty((len(t), 3))
    nrm = np.empty((len(t), 3), np.float32)
    for i, inst in enumerate(scene.instances):
        sel = t.instance == i
        pos[sel], nrm[sel] = to_world(inst.transform, t.local_pos[sel], t.local_normal[sel])
    return t, pos, nrm
