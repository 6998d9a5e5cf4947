"""The scene a server sent (psao.protocol.scenefile) as a psao.scene Scene, for clients started without one.

Skins pose from the sampled skinning matrices (psao.protocol.scenefile.skin_pose), with identity inverse
binds; rigid animation needs nothing here (the server sends every instance's transform).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.protocol.scenefile import SceneFile, SkinData, skin_pose
from psao.scene.model import CameraKey, CameraPath, Instance, Mesh, Scene
from psao.scene.skin import Skin


@dataclass
class SampledSkinAnimator:
    """Joint matrices of a received skin at time t: its sampled skinning matrices (inverse bind = I)."""

    data: SkinData

    @property
    def duration(self) -> float:
        return self.data.period

    def joint_matrices(self, t: float) -> np.ndarray:
        return skin_pose(self.data, t).astype(np.float64)

    def rest_joint_matrices(self) -> np.ndarray:
        return self.joint_matrices(0.0)


def scene_from_file(f: SceneFile, source: str = "") -> Scene:
    meshes = []
    for m in f.meshes:
        skin = None
        if m.skin is not None:
            s = m.skin
            skin = Skin(inverse_bind=np.tile(np.eye(4), (s.joint_count, 1, 1)), joints=s.joints.astype(np.int64),
                        weights=s.weights.astype(np.float64), animator=SampledSkinAnimator(s))
        meshes.append(Mesh(m.name, m.vertices.astype(np.float64), m.faces.astype(np.int64), m.double_sided,
                           tuple(float(c) for c in m.color), skin))
    instances = [Instance(i.name, i.mesh, i.transform.astype(np.float64)) for i in f.instances]
    paths = {p.name: CameraPath(p.name, [CameraKey(float(k[0]), tuple(map(float, k[1:4])), tuple(map(float, k[4:7])))
                                         for k in p.keys], p.fov_y, p.loop) for p in f.camera_paths}
    return Scene(f.name, meshes, instances, f.ao_distance, paths, source=source or f"server scene {f.name}")
