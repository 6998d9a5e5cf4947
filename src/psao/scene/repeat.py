"""Large scenes made from a builtin one: `builtin:NAME-NXxNZ` is builtin NAME copied NX x NZ times side by
side on the ground plane (X and Z), a tenth of its extent apart; e.g. builtin:courtyard-8x8 (64 courtyards,
1.5 million triangles), the large scene of the scale-out benchmark (benchmarks/bench_dask.py).

The copies are static: animations and skins are dropped (a bake-sized scene, not a show). They share the
original's meshes; instance names get the copy's grid position, `name@i,k`.
"""
from __future__ import annotations

import re
from dataclasses import replace

import numpy as np

from psao.scene.model import Scene

REPEAT_PATTERN = re.compile(r"^(?P<name>[a-z_]+)-(?P<nx>\d+)x(?P<nz>\d+)$")
GAP = 0.1  # space between copies, as a fraction of the scene's extent
MAX_COPIES = 4096


def parse_repeat(name: str) -> tuple[str, int, int] | None:
    """(builtin name, nx, nz) of a `NAME-NXxNZ` builtin name, or None."""
    m = REPEAT_PATTERN.match(name)
    return (m["name"], int(m["nx"]), int(m["nz"])) if m else None


def repeat_scene(scene: Scene, nx: int, nz: int) -> Scene:
    lo, hi = scene.world_bounds()
    step = (hi - lo) * (1.0 + GAP)
    meshes = [replace(m, skin=None) if m.skin is not None else m for m in scene.meshes]
    instances = []
    for i in range(nx):
        for k in range(nz):
            offset = np.eye(4)
            offset[0, 3], offset[2, 3] = i * step[0], k * step[2]
            instances += [replace(inst, name=f"{inst.name}@{i},{k}", transform=offset @ inst.transform, animation=None)
                          for inst in scene.instances]
    return Scene(name=f"{scene.name}-{nx}x{nz}", meshes=meshes, instances=instances, ao_distance=scene.ao_distance,
                 camera_paths=scene.camera_paths, source=f"{scene.source}-{nx}x{nz}")
