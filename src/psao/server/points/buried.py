"""Surface points buried inside closed geometry: never visible, so the bake places no AO point there.

Models people bring are full of parts pushed into each other (a column sunk into the floor, a decimated
scan's overlapping shells, a sphere through a slab). The surface inside another solid is seen from no
viewpoint, its AO is near 0, and the lookup (paper eq. 2-4) cannot tell such a point from a visible one on
the same surface within r: it darkens a ring on the visible side of the intersection. On Sponza about a
fifth of all surface area is buried like this.

A point is buried when most rays over its normal's hemisphere first hit a back face of one-sided static
geometry (winding gives the outward side): it sits inside a closed solid. Double-sided meshes have no
inside and are not occluders here; moving and skinned instances are neither tested nor occluders, since
what is buried at rest may be exposed by the motion. Rays are not limited to the AO distance: inside a
large solid every ray still meets its inner faces.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.scene.model import Scene
from psao.server.geometry import scene_world_geometry
from psao.server.tracer.directions import ray_origins

try:  # deferred like the Embree tracer: the error surfaces when a test is asked for
    from embreex import rtcore, rtcore_scene
    from embreex.mesh_construction import TriangleMesh
except ImportError:  # pragma: no cover - embreex is a hard dependency here
    rtcore = None


@dataclass
class BuriedSettings:
    rays: int = 8  # hemisphere rays per point
    back_fraction: float = 0.5  # buried when more than this fraction of the rays first hits a back face
    # Rays start this far out (times the AO distance): a face pressed flat on another (a box standing on a
    # floor) is then inside it at every scale, instead of rounding deciding whether the ray starts inside.
    skip: float = 1e-3
    seed: int = 0x5EED


def is_static(scene: Scene, i: int) -> bool:
    inst = scene.instances[i]
    return inst.animation is None and scene.meshes[inst.mesh].skin is None


def closed_instances(scene: Scene, moving: bool = False) -> list[int]:
    """Instances that can bury surfaces and be buried: one-sided, and static unless `moving`."""
    return [i for i, inst in enumerate(scene.instances)
            if (moving or is_static(scene, i)) and not scene.meshes[inst.mesh].double_sided]


class BuriedTest:
    """One Embree scene of the occluders (world space, re-centred for float32), asked per batch of points."""

    def __init__(self, scene: Scene, settings: BuriedSettings | None = None, moving: bool = False):
        """`moving`: moving and skinned instances too, as posed at time 0 (what is hidden in that pose,
        e.g. to leave surfaces nobody sees out of an accuracy measure); the bake leaves them out."""
        self.settings = settings or BuriedSettings()
        self.instances = set(closed_instances(scene, moving))
        self.ao_distance = scene.ao_distance
        verts, faces = scene_world_geometry(scene, sorted(self.instances))
        self.centre = verts.mean(axis=0) if len(verts) else np.zeros(3)
        self._scene = None
        if len(faces) and rtcore is not None:
            self._scene = rtcore_scene.EmbreeScene(rtcore.EmbreeDevice())
            TriangleMesh(self._scene, np.ascontiguousarray(verts - self.centre, np.float32),
                         np.ascontiguousarray(faces, np.int32))

    def applies_to(self, instance: int) -> bool:
        return self._scene is not None and instance in self.instances

    def mask(self, world_pos: np.ndarray, world_normal: np.ndarray, seed: int = 0) -> np.ndarray:
        """Bool (P,): the points (world position, unit normal of the side they are on) that are buried.
        Works through the points in batches of about a million rays, drawing each batch's directions from
        one random stream, so memory stays bounded and the answer does not depend on the batch size."""
        n = len(world_pos)
        if self._scene is None or n == 0:
            return np.zeros(n, bool)
        rng = np.random.default_rng([self.settings.seed, seed])
        world_pos = np.asarray(world_pos, np.float64)
        world_normal = np.asarray(world_normal, np.float32)
        step = max(1, (1 << 20) // self.settings.rays)
        out = np.empty(n, bool)
        for s in range(0, n, step):
            sl = slice(s, s + step)
            out[sl] = self._batch(world_pos[sl], world_normal[sl], rng)
        return out

    def _batch(self, world_pos: np.ndarray, world_normal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        n, k = len(world_pos), self.settings.rays
        dirs = rng.normal(size=(n * k, 3))
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
        nrm = np.repeat(world_normal.astype(np.float64), k, axis=0)
        dirs = np.where((np.einsum("ij,ij->i", dirs, nrm) < 0)[:, None], -dirs, dirs)
        org = ray_origins(world_pos - self.centre, world_normal, self.ao_distance)
        org = (np.repeat(org, k, axis=0) + dirs * (self.settings.skip * self.ao_distance)).astype(np.float32)
        dirs = dirs.astype(np.float32)
        out = self._scene.run(org, dirs, query="INTERSECT", output=1)
        hit = out["geomID"] != np.array(-1).astype(out["geomID"].dtype)
        # Embree's geometric normal Ng points to the counter-clockwise (outward) side, as the meshes'.
        back = hit & (np.einsum("ij,ij->i", out["Ng"], dirs) > 0)
        return back.reshape(n, k).mean(axis=1) > self.settings.back_fraction


def visible_probes(scene: Scene, probes):
    """The probes (psao.server.bake.Probes) not buried in any one-sided instance as posed at time 0: the
    surface an accuracy measure should score, since nothing shows the rest."""
    return probes.subset(~BuriedTest(scene, moving=True).mask(probes.world_pos, probes.world_normal))
