"""The scene at time t for the server tick: instance transforms, skinned geometry, world bounds, and the
world geometry split into a static part (traced in one Embree scene built once) and a moving part
(rebuilt every tick).

Instances are of three kinds:
    static   no animation and no skin: geometry and points never change
    rigid    a RigidAnimation and no skin: points stay in the instance's local space, only the
             transform changes (the client applies it; no point is re-sent for the motion itself)
    skinned  a mesh with a Skin (possibly also moved rigidly): the mesh deforms; the grid keeps its AO
             points in the mesh's rest pose (the client looks fragments up by their rest-pose place), and
             the tick traces them from where they are on the deformed mesh

Skinned AO points follow their triangles exactly: a posed point is the same barycentric combination of its
triangle's skinned corners (Warp skinning of the mesh vertices, psao_scene.skinning) as its rest-pose
point is of the rest corners, and its normal is the skinned triangle's normal on the side the point was
generated on. So points stay on the deformed surface, which blending per-point skin weights would not
guarantee, and the client finds a posed fragment's rest-pose place the same way (same triangle, same
barycentrics).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psao_scene.rigid import instance_transform
from psao_scene.model import Scene
from psao_scene.skinning import SceneSkinner, SurfacePoints, surface_points
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
    spheres: dict[int, tuple[np.ndarray, float]]  # moving instance -> world bounding sphere (centre, radius)
    dynamic_vertices: np.ndarray  # (V, 3) world, all moving instances merged
    dynamic_faces: np.ndarray  # (F, 3) int64
    seconds_skinning: float = 0.0
    skinned_vertices: np.ndarray | None = None  # (V, 3) world, skinned instances merged (None: none)
    skinned_faces: np.ndarray | None = None  # (F, 3) int64
    skinned_parts: list[int] = field(default_factory=list)  # vertices of each skinned instance in skinned_vertices


def affine(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """(P, 3) points through a 4x4 transform. einsum, not `@`: OpenBLAS threads on (P, 3) x (3, 3)
    cost ~10x more than the arithmetic when the cores are busy with tracer workers."""
    m = np.asarray(transform, np.float64)
    return np.einsum("pj,ij->pi", np.asarray(points, np.float64), m[:3, :3]) + m[:3, 3]


def to_world_points(transform: np.ndarray, local_pos: np.ndarray, local_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """bake.to_world without BLAS (see affine): positions float64, unit normals float32."""
    m = np.asarray(transform, np.float64)
    nrm = np.einsum("pj,ji->pi", np.asarray(local_normal, np.float64), np.linalg.inv(m[:3, :3]))
    nrm /= np.maximum(np.sqrt(np.einsum("pi,pi->p", nrm, nrm))[:, None], 1e-300)
    return affine(local_pos, m), nrm.astype(np.float32)


def world_box(vertices_local: np.ndarray, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact world AABB of local vertices under a 4x4 transform."""
    w = affine(vertices_local, transform)
    return w.min(axis=0), w.max(axis=0)


def bounds_of(world_vertices: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, float]]:
    """World AABB (lo, hi) and bounding sphere (centre, radius) of world vertices. Worked on the
    coordinates as three rows: numpy reduces a (V, 3) array along its long axis several times slower
    than a (3, V) one along its rows, and this runs for every moving instance every tick."""
    rows = np.ascontiguousarray(np.asarray(world_vertices, np.float64).reshape(-1, 3).T)
    lo, hi = rows.min(axis=1), rows.max(axis=1)
    centre = 0.5 * (lo + hi)
    d = rows - centre[:, None]
    d *= d
    return (lo, hi), (centre, float(np.sqrt((d[0] + d[1] + d[2]).max())))


class SceneAnimator:
    """Evaluates a scene's animation at time t; built once, reused every tick."""

    def __init__(self, scene: Scene, device: str | None = "cpu"):
        self.scene = scene
        self.kinds = classify_instances(scene)
        self.skinner = SceneSkinner(scene, device=device)
        self._rest_transforms = np.array([inst.transform for inst in scene.instances], dtype=np.float64).reshape(-1, 4, 4)
        self.placed: dict[int, np.ndarray] = {}  # instance -> transform a scene edit gave it (replaces its animation)

    def place(self, instance: int, transform: np.ndarray) -> bool:
        """A scene edit: instance `instance` is at `transform` (local-to-world) from now on, whatever its
        animation said. A static instance becomes a rigid mover (returns True: the caller moves its
        geometry out of the static part); its bounds before the edit are in `static_bounds`."""
        self.placed[instance] = np.asarray(transform, np.float64).reshape(4, 4)
        if instance not in self.kinds.static:
            return False
        self.kinds.static.remove(instance)
        self.kinds.rigid = sorted(self.kinds.rigid + [instance])
        return True

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
            out[i] = self.placed[i] if i in self.placed else instance_transform(self.scene, i, t)
        return out

    def frame(self, t: float, bind_pose: bool = False) -> Frame:
        """The scene at time t; with `bind_pose`, its skinned meshes in their bind pose (as a bake traces
        them) instead of deformed at t."""
        import time
        transforms = self.transforms(t)
        t0 = time.perf_counter()
        mesh_vertices = {}
        for i in self.kinds.skinned:
            m = self.scene.instances[i].mesh
            if m not in mesh_vertices:  # a copy: the deformer may hand out the same buffer every call
                mesh_vertices[m] = np.array(self.scene.meshes[m].vertices if bind_pose else self.skinner.vertices(m, t),
                                            np.float64)
        seconds_skinning = time.perf_counter() - t0
        bounds, spheres, verts, faces, base = {}, {}, [], [], 0
        skinned_v, skinned_f, skinned_base, skinned_parts = [], [], 0, []
        for i in self.kinds.moving:
            inst = self.scene.instances[i]
            mesh = self.scene.meshes[inst.mesh]
            local = mesh_vertices.get(inst.mesh, mesh.vertices)
            w = affine(local, transforms[i])  # the moving scene needs them anyway: exact bounds come for free
            bounds[i], spheres[i] = bounds_of(w)
            verts.append(w)
            faces.append(mesh.faces + base)
            base += len(w)
            if inst.mesh in mesh_vertices:
                skinned_v.append(w)
                skinned_parts.append(len(w))
                skinned_f.append(mesh.faces + skinned_base)
                skinned_base += len(w)
        dv = np.concatenate(verts) if verts else np.zeros((0, 3))
        df = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        sv = np.concatenate(skinned_v) if skinned_v else None
        sf = np.concatenate(skinned_f) if skinned_f else np.zeros((0, 3), np.int64)
        return Frame(float(t), transforms, mesh_vertices, bounds, spheres, dv, df, seconds_skinning, sv, sf, skinned_parts)


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
        """Local positions (P, 3) float64 and unit normals (P, 3) float32 on the deformed mesh (the mesh's
        faces must be the same every call): Warp's SurfacePoints, valid until the next call."""
        if getattr(self, "_kernel", None) is None:
            self._kernel = SurfacePoints(mesh_faces, self.faces, self.bary, self.side, self.rest_normals)
        return self._kernel.follow(vertices)

    def follow_numpy(self, mesh_faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """follow() in numpy (the reference the kernel is tested against)."""
        pos, n = surface_points(vertices, mesh_faces, self.faces, self.bary)
        ok = np.linalg.norm(n, axis=1) > 0.5  # a triangle skinned flat keeps the point's rest normal
        nrm = np.where(ok[:, None], n * self.side[:, None], self.rest_normals)
        return pos, nrm.astype(np.float32)
