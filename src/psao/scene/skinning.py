"""Linear blend skinning of vertices and AO points: SceneSkinner and one-off helpers over the Warp kernels of
skinning_kernels.py (imported on first use), and numpy references for tests.

A skinned position is  p' = (sum_k w_k M_{j_k}) p  with M = skin.skinning_matrices(t) (joint matrix times
inverse bind), in the mesh's local space; a normal is transformed by the inverse transpose of the same
blended 3x3 and renormalised. AO points on a skinned mesh carry their own 4 joints and weights,
blended from their triangle's corners by point_skin_weights() (or are placed on the skinned triangles
directly with surface_points(), which matches the client's rasteriser exactly).

skinning_kernels.SkinDeformer uploads the rest data once and keeps its output buffers: per tick only the (J, 4, 4)
matrices move to the device. float64 throughout, as the Scene's geometry.
"""
from __future__ import annotations

import numpy as np

from psao.scene.skin import Skin, skinning_matrices_of


def _deformer(*args, **kwargs):
    """skinning_kernels.SkinDeformer(*args, **kwargs), importing Warp with it at the first one made."""
    from psao.scene.skinning_kernels import SkinDeformer

    return SkinDeformer(*args, **kwargs)


def skin_points(skin: Skin, t: float, rest_pos, joints, weights, device: str | None = None) -> np.ndarray:
    """(P, 3) points skinned at time t (one-off; keep a SkinDeformer to skin the same points every tick)."""
    return _deformer(rest_pos, joints, weights, device=device).deform(skin.skinning_matrices(t))[0]


def skin_normals(skin: Skin, t: float, rest_nrm, joints, weights, device: str | None = None) -> np.ndarray:
    """(P, 3) unit normals skinned at time t."""
    d = _deformer(np.zeros((len(rest_nrm), 3)), joints, weights, rest_nrm=rest_nrm, device=device)
    return d.deform(skin.skinning_matrices(t))[1]


def skinned_vertices(mesh, t: float, device: str | None = None) -> np.ndarray:
    """The mesh's vertices at time t in its local space (the rest vertices when it has no skin)."""
    if mesh.skin is None:
        return mesh.vertices
    return skin_points(mesh.skin, t, mesh.vertices, mesh.skin.joints, mesh.skin.weights, device)


# ------------------------------------------------------------------------------------ numpy reference

def blended_matrices(matrices: np.ndarray, joints: np.ndarray, weights: np.ndarray) -> np.ndarray:
    return np.einsum("pk,pkij->pij", weights, matrices[joints])


def skin_points_reference(matrices: np.ndarray, rest_pos, joints, weights) -> np.ndarray:
    m = blended_matrices(matrices, np.asarray(joints), np.asarray(weights, dtype=np.float64))
    return np.einsum("pij,pj->pi", m[:, :3, :3], rest_pos) + m[:, :3, 3]


def skin_normals_reference(matrices: np.ndarray, rest_nrm, joints, weights) -> np.ndarray:
    m = blended_matrices(matrices, np.asarray(joints), np.asarray(weights, dtype=np.float64))[:, :3, :3]
    n = np.einsum("pji,pj->pi", np.linalg.inv(m), rest_nrm)  # inverse transpose
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# ----------------------------------------------------------------------------- per-scene convenience

class SceneSkinner:
    """One SkinDeformer per skinned mesh of a scene, or per list of them skinned together (posed), built on
    first use and reused every tick."""

    def __init__(self, scene, device: str | None = None):
        self.scene = scene
        self.device = device
        self._deformers: dict = {}  # skinning_kernels.SkinDeformer per mesh
        self._batches: dict = {}  # ... per tuple of meshes skinned together

    def posed(self, meshes: list[int], t: float) -> np.ndarray:
        """(sum of V, 3) mesh-local vertices of the skinned meshes `meshes` at time t, concatenated in their
        order (a new array): all of them in one kernel launch, their joint matrices batched
        (skin.skinning_matrices_of). The same numbers as vertices() mesh by mesh."""
        key = tuple(meshes)
        if not key:
            return np.zeros((0, 3))
        skins = [self.scene.meshes[m].skin for m in key]
        if key not in self._batches:
            first = np.cumsum([0] + [s.joint_count for s in skins[:-1]])  # each skin's joints in the batch
            self._batches[key] = _deformer(np.concatenate([self.scene.meshes[m].vertices for m in key]),
                                           np.concatenate([s.joints + f for s, f in zip(skins, first)]),
                                           np.concatenate([s.weights for s in skins]), device=self.device)
        return self._batches[key].deform(skinning_matrices_of(skins, t))[0].copy()

    def vertices(self, mesh_index: int, t: float) -> np.ndarray:
        """Mesh-local vertices of mesh `mesh_index` at time t (its rest vertices when not skinned)."""
        mesh = self.scene.meshes[mesh_index]
        if mesh.skin is None:
            return mesh.vertices
        if mesh_index not in self._deformers:
            self._deformers[mesh_index] = _deformer(mesh.vertices, mesh.skin.joints, mesh.skin.weights,
                                                    device=self.device)
        return self._deformers[mesh_index].deform(mesh.skin.skinning_matrices(t))[0]


def surface_points(vertices: np.ndarray, faces: np.ndarray, face_index: np.ndarray,
                   bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points at barycentrics `bary` of triangles `face_index` of a (skinned) vertex array, and the unit
    normals of those triangles: points stay exactly on the triangles the client rasterises from the same
    skinned vertices (skinning each point with its own blended weights would not, by the bilinear term of
    linear blend skinning)."""
    tri = vertices[faces[face_index]]  # (P, 3, 3)
    pos = np.einsum("pk,pkj->pj", bary, tri)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return pos, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
