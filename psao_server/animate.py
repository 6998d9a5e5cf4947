"""The scene at time t for the server tick: instance transforms, skinned geometry, world bounds, and the
world geometry split into a static part (traced in one Embree scene built once) and a moving part
(rebuilt every tick).

Instances are of three kinds:
    static   no animation and no skin: geometry and points never change
    rigid    a RigidAnimation and no skin: points stay in the instance's local space, only the
             transform changes (the client applies it; no point is re-sent for the motion itself)
    skinned  a mesh with a Skin (possibly also moved rigidly): the mesh deforms, so its AO points move
             in local space and are re-quantised into the grid

Skinned AO points follow their triangles exactly: a point is the same barycentric combination of its
triangle's skinned corners (Warp skinning of the mesh vertices, psao_scene.skinning), and its normal is
the skinned triangle's normal on the side the point was generated on. So points stay on the deformed
surface, which blending per-point skin weights would not guarantee.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psao_scene.animation import instance_transform
from psao_scene.model import Scene
from psao_scene.skinning import SceneSkinner
from psao_server.bake import scene_world_geometry
from psao_server.points import PointSet


@dataclass
class InstanceKinds:
    static: list[int]
    rigid: list[int]
    skinned: list[int]

    @property
    def moving(self) -> list[int]:
        return sorted(self.rigid + self.skinned)


def classify_instances(scene: Scene) -> InstanceKinds:
    kinds = InstanceKinds([], [], [])
    for i, inst in enumerate(scene.instances):
        if scene.meshes[inst.mesh].skin is not None:
            kinds.skinned.append(i)
        elif inst.animation is not None:
            kinds.rigid.append(i)
        else:
            kinds.static.append(i)
    return kinds


@dataclass
class Frame:
    """The moving part of the scene at one time."""
    t: float
    transforms: np.ndarray  # (n_instances, 4, 4) float64 local-to-world
    mesh_vertices: dict[int, np.ndarray]  # skinned mesh index -> (V, 3) mesh-local vertices at t
    bounds: dict[int, tuple[np.ndarray, np.ndarray]]  # moving instance -> world (lo, hi) at t
    dynamic_vertices: np.ndarray  # (V, 3) world, all moving instances merged
    dynamic_faces: np.ndarray  # (F, 3) int64
    seconds_skinning: float = 0.0


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def world_box(vertices_local: np.ndarray, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact world AABB of local vertices under a 4x4 transform."""
    w = vertices_local @ transform[:3, :3].T + transform[:3, 3]
    return w.min(axis=0), w.max(axis=0)


class SceneAnimator:
    """Evaluates a scene's animation at time t; built once, reused every tick."""

    def __init__(self, scene: Scene, device: str | None = "cpu"):
        self.scene = scene
        self.kinds = classify_instances(scene)
        self.skinner = SceneSkinner(scene, device=device)
        self._rest_transforms = np.array([inst.transform for inst in scene.instances], dtype=np.float64).reshape(-1, 4, 4)
        # local corner boxes of rigid meshes: a transformed box is a cheap conservative world bound
        self._local_corners = {i: _box_corners(scene.meshes[scene.instances[i].mesh].vertices.min(axis=0),
                                               scene.meshes[scene.instances[i].mesh].vertices.max(axis=0))
                               for i in self.kinds.rigid}

    # ------------------------------------------------------------------ static part
    def static_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """World triangles of the static instances (rest transforms), for the tracer's static scene."""
        return scene_world_geometry(self.scene, self.kinds.static)

    def static_bounds(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """World AABB of every static instance."""
        out = {}
        for i in self.kinds.static:
            inst = self.scene.instances[i]
            out[i] = world_box(self.scene.meshes[inst.mesh].vertices, inst.transform)
        return out

    # ------------------------------------------------------------------ moving part
    def transforms(self, t: float) -> np.ndarray:
        """(n, 4, 4) float64 local-to-world transforms at time t."""
        out = self._rest_transforms.copy()
        for i in self.kinds.moving:
            out[i] = instance_transform(self.scene, i, t)
        return out

    def frame(self, t: float) -> Frame:
        import time
        transforms = self.transforms(t)
        t0 = time.perf_counter()
        mesh_vertices = {}
        for i in self.kinds.skinned:
            m = self.scene.instances[i].mesh
            if m not in mesh_vertices:
                mesh_vertices[m] = self.skinner.vertices(m, t)
        seconds_skinning = time.perf_counter() - t0
        bounds, verts, faces, base = {}, [], [], 0
        for i in self.kinds.moving:
            inst = self.scene.instances[i]
            mesh = self.scene.meshes[inst.mesh]
            local = mesh_vertices.get(inst.mesh, mesh.vertices)
            m = transforms[i]
            w = local @ m[:3, :3].T + m[:3, 3]
            if i in self._local_corners:  # rigid: transformed local box (conservative, 8 points)
                bounds[i] = world_box(self._local_corners[i], m)
            else:
                bounds[i] = (w.min(axis=0), w.max(axis=0))
            verts.append(w)
            faces.append(mesh.faces + base)
            base += len(w)
        dv = np.concatenate(verts) if verts else np.zeros((0, 3))
        df = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        return Frame(float(t), transforms, mesh_vertices, bounds, dv, df, seconds_skinning)


# ---------------------------------------------------------------------------------- skinned points

@dataclass
class SkinnedPoints:
    """The AO points of one skinned instance, tied to their triangles (from the instance's PointSet)."""
    faces: np.ndarray  # (P,) triangle of each point
    bary: np.ndarray  # (P, 3) float64
    side: np.ndarray  # (P,) +1 / -1: the point's normal along / against its triangle's normal
    rest_normals: np.ndarray = field(repr=False, default=None)  # (P, 3) fallback for degenerate triangles

    @classmethod
    def from_pointset(cls, mesh, ps: PointSet) -> "SkinnedPoints":
        faces = np.asarray(ps.faces, np.int64)
        face_n = mesh.face_normals()[faces]
        side = np.where(np.einsum("ij,ij->i", face_n, ps.normals) >= 0, 1.0, -1.0)
        return cls(faces, np.asarray(ps.barycentrics, np.float64), side, np.asarray(ps.normals, np.float64))

    def follow(self, mesh_faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local positions (P, 3) float64 and unit normals (P, 3) float32 on the deformed mesh."""
        corners = vertices[mesh_faces[self.faces]]  # (P, 3, 3)
        pos = np.einsum("pk,pkj->pj", self.bary, corners)
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(n, axis=1)
        ok = length > 1e-20
        nrm = np.where(ok[:, None], n / np.where(ok, length, 1.0)[:, None] * self.side[:, None], self.rest_normals)
        return pos, nrm.astype(np.float32)
