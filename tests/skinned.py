"""Helpers for tests of skinned meshes: where points lie on a mesh, and a posed point's rest-pose place."""
from __future__ import annotations

import numpy as np
import trimesh


def closest_on_mesh(vertices, faces, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point: the distance to the nearest triangle, that triangle and the barycentrics of the
    closest point on it; every point against every triangle (trimesh's proximity query would need rtree,
    which is not installed)."""
    tris = np.asarray(vertices, np.float64)[faces]
    dist, face, bary = np.empty(len(points)), np.empty(len(points), np.int64), np.empty((len(points), 3))
    for k, p in enumerate(np.asarray(points, np.float64)):
        closest = trimesh.triangles.closest_point(tris, np.broadcast_to(p, (len(tris), 3)))
        d = np.linalg.norm(closest - p, axis=1)
        face[k] = f = int(d.argmin())
        dist[k] = d[f]
        bary[k] = trimesh.triangles.points_to_barycentric(tris[f:f + 1], closest[f:f + 1])[0]
    return dist, face, bary


def local_distance(vertices, faces, points) -> np.ndarray:
    """Distance of each point to the nearest triangle of the mesh."""
    return closest_on_mesh(vertices, faces, points)[0]


def rest_place(posed_vertices, rest_vertices, faces, points) -> np.ndarray:
    """The rest-pose place of points on a posed mesh: the same barycentrics of the same triangle at rest."""
    _, face, bary = closest_on_mesh(posed_vertices, faces, points)
    return np.einsum("pk,pkj->pj", bary, np.asarray(rest_vertices, np.float64)[faces[face]])
