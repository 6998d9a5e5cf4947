"""Scene data model shared by the server (tracing) and the client (rasterising): both load the same scene.

A Scene is meshes (geometry in mesh-local space) plus instances (a mesh placed with a 4x4 local-to-world
transform). Geometry of a mesh is float64 vertices (V, 3) and int64 faces (F, 3), already cleaned
(no NaN, no degenerate triangles). Units are scene units ("metres"); ao_distance is in world units.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

# The AO distance a scene that sets none gets: this fraction of the diagonal of its world bounding box.
DEFAULT_AO_FRACTION = 0.1
# A TOML scene without an AO distance gives each [[instance]] this fraction of its own diagonal as the length
# its default density follows (Instance.sampling_scale). On examples/composed.toml (Sponza's AO distance
# 4.58) a CesiumMan got, at 0.1 (as dense as alone), 91,440 points and a recon MAE of 0.0095 at 1024-ray
# truth; at 0.4 6,037 points and 0.0119; at 0.8 1,509 and 0.0169 (target 0.02); at the scene's 64 and 0.076.
OBJECT_SAMPLING_FRACTION = 0.4


def _edge_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3): the cross product of each triangle's edges b - a and c - a (counter-clockwise: the front side)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return np.cross(b - a, c - a)


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each triangle `faces` (F, 3) of `vertices` (V, 3): half the norm of its edges' cross product."""
    return 0.5 * np.linalg.norm(_edge_cross(vertices, faces), axis=1)


def triangle_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit front-side normal of each triangle `faces` (F, 3) of `vertices` (V, 3) (degenerate ones: zero)."""
    n = _edge_cross(vertices, faces)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


@dataclass
class Mesh:
    name: str
    vertices: np.ndarray  # (V, 3) float64, mesh-local space
    faces: np.ndarray  # (F, 3) int64
    double_sided: bool = False
    color: tuple[float, float, float] = (0.8, 0.8, 0.8)  # linear RGB albedo for the client's color pass
    skin: object | None = None  # psao.scene.skin.Skin for skinned meshes

    def face_normals(self) -> np.ndarray:
        return triangle_normals(self.vertices, self.faces)

    def triangle_areas(self, linear: np.ndarray | None = None) -> np.ndarray:
        """Area of each triangle (one side), of the mesh as placed by the 3x3 `linear` part of a transform
        when given (translation does not change areas)."""
        v = self.vertices if linear is None else self.vertices @ np.asarray(linear, np.float64).T
        return triangle_areas(v, self.faces)

    def area(self, linear: np.ndarray | None = None) -> float:
        """Surface area, of the mesh as placed by the 3x3 `linear` part of a transform when given."""
        return float(self.triangle_areas(linear).sum())


@dataclass
class Instance:
    name: str
    mesh: int  # index into Scene.meshes
    transform: np.ndarray  # (4, 4) float64 local-to-world at time 0
    animation: object | None = None  # psao.scene.rigid.RigidAnimation
    # world units: the length its default density follows as the scene's follows its AO distance
    # (psao.server.points.sampling), at most the scene's AO distance; 0: the scene's AO distance
    sampling_scale: float = 0.0


@dataclass
class CameraKey:
    time: float  # seconds
    eye: tuple[float, float, float]
    target: tuple[float, float, float]


@dataclass
class CameraPath:
    name: str
    keys: list[CameraKey]
    fov_y: float = 60.0  # degrees
    loop: bool = True


@dataclass
class Scene:
    name: str
    meshes: list[Mesh]
    instances: list[Instance]
    ao_distance: float  # world units
    camera_paths: dict[str, CameraPath] = field(default_factory=dict)
    source: str = ""  # what it was loaded from, for messages

    def world_bounds(self, instances: list[Instance] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box of the instances (default: all) at their time-0 transforms."""
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for inst in self.instances if instances is None else instances:
            v = self.meshes[inst.mesh].vertices @ inst.transform[:3, :3].T + inst.transform[:3, 3]
            lo = np.minimum(lo, v.min(axis=0))
            hi = np.maximum(hi, v.max(axis=0))
        return lo, hi

    def diagonal(self, instances: list[Instance] | None = None) -> float:
        """Length of the diagonal of the instances' (default: all) world bounds at time 0."""
        lo, hi = self.world_bounds(instances)
        return float(np.linalg.norm(hi - lo))

    def content_hash(self) -> str:
        """sha256 over geometry, instances, animation and AO distance: client and server must agree on it."""
        h = hashlib.sha256()
        h.update(np.float64(self.ao_distance).tobytes())
        for m in self.meshes:
            h.update(m.name.encode())
            h.update(np.ascontiguousarray(m.vertices, dtype=np.float64).tobytes())
            h.update(np.ascontiguousarray(m.faces, dtype=np.int64).tobytes())
            h.update(bytes([int(m.double_sided)]))
        for i in self.instances:
            h.update(i.name.encode())
            h.update(np.int64(i.mesh).tobytes())
            h.update(np.ascontiguousarray(i.transform, dtype=np.float64).tobytes())
        h.update(animation_hash(self).encode())
        return h.hexdigest()


def animation_hash(scene, times=tuple(np.linspace(0.0, 60.0, 17))) -> str:
    """sha256 of every animated transform and skinning matrix sampled at `times`: equal on two machines
    iff they animate the scene alike (Scene.content_hash covers only the geometry at rest)."""
    def stable(m) -> bytes:
        # Rounded (and -0.0 folded into 0.0) so last-ulp differences between math libraries do not count.
        return (np.round(np.asarray(m, dtype=np.float64), 6) + 0.0).tobytes()

    h = hashlib.sha256()
    for i, inst in enumerate(scene.instances):
        if inst.animation is not None:
            h.update(inst.name.encode())
            for t in times:
                h.update(stable(inst.animation.matrix(t)))
    for m in scene.meshes:
        if m.skin is not None:
            h.update(m.name.encode())
            h.update(np.ascontiguousarray(m.skin.joints, dtype=np.int64).tobytes())
            h.update(stable(m.skin.weights))
            for t in times:
                h.update(stable(m.skin.skinning_matrices(t)))
    return h.hexdigest()
