"""SceneBuilder: collects cleaned meshes, named instances and camera paths of a scene generated in code."""
from __future__ import annotations

import numpy as np

from psao.scene import builtin_shapes as shapes
from psao.scene.meshfile import clean_geometry
from psao.scene.model import CameraKey, CameraPath, Instance, Mesh, Scene

class SceneBuilder:
    """Collects cleaned meshes and named instances for a generated scene."""

    def __init__(self, name: str):
        self.name = name
        self.meshes: list[Mesh] = []
        self.instances: list[Instance] = []
        self.camera_paths: dict[str, CameraPath] = {}

    def mesh(self, name: str, geom: shapes.Geometry, color=(0.8, 0.8, 0.8), double_sided=False) -> int:
        r = clean_geometry(geom[0], geom[1], f"builtin:{self.name}: mesh '{name}'")
        self.meshes.append(Mesh(name=name, vertices=r.vertices, faces=r.faces, double_sided=double_sided,
                                color=tuple(float(c) for c in color)))
        return len(self.meshes) - 1

    def instance(self, name: str, mesh: int, transform: np.ndarray | None = None, animation=None) -> int:
        self.instances.append(Instance(name=name, mesh=mesh,
                                       transform=np.eye(4) if transform is None else transform,
                                       animation=animation))
        return len(self.instances) - 1

    def place(self, name: str, geom: shapes.Geometry, transform=None, **mesh_kw) -> int:
        """A mesh used by exactly one instance of the same name."""
        return self.instance(name, self.mesh(name, geom, **mesh_kw), transform)

    def camera(self, name: str, keys: list[tuple[float, tuple, tuple]], fov_y=60.0, loop=True) -> None:
        self.camera_paths[name] = CameraPath(
            name=name, keys=[CameraKey(float(t), tuple(map(float, e)), tuple(map(float, g))) for t, e, g in keys],
            fov_y=fov_y, loop=loop)

    def build(self, ao_distance: float) -> Scene:
        return Scene(name=self.name, meshes=self.meshes, instances=self.instances, ao_distance=ao_distance,
                     camera_paths=self.camera_paths, source=f"builtin:{self.name}")


def quad(p0, p1, p2, p3) -> shapes.Geometry:
    """One quad, counter-clockwise seen from the side it faces."""
    return np.array([p0, p1, p2, p3], dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
