"""Test helper: the AO a full local trace gives points of a server tick, to compare refined points with."""
from __future__ import annotations

import numpy as np

from psao.server.geometry import scene_center
from psao.server.settings import TraceSettings
from psao.server.tracer import make_tracer


def full_trace(tick, frame, ids: np.ndarray, rays: int, seed: int) -> np.ndarray:
    """Visibility of the tick's points `ids` traced here with their whole `rays`-ray set (the bake's rays and
    seed): static scene, rigid movers and skinned meshes as posed at `frame`."""
    scene = tick.scene
    local = make_tracer("embree", scene_center(scene), workers=1)
    try:
        local.set_static(*tick.animator.static_geometry())
        local.set_rigid([(scene.meshes[scene.instances[i].mesh].vertices, scene.meshes[scene.instances[i].mesh].faces)
                         for i in tick.kinds.rigid])
        local.set_dynamic(frame.skinned_vertices, frame.skinned_faces, frame.transforms[tick.kinds.rigid])
        pos, nrm = tick.world_points(frame, ids)
        return local.visibility(pos, nrm, ids, TraceSettings(rays=rays, ao_distance=scene.ao_distance, seed=seed))
    finally:
        local.close()
