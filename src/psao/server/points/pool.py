"""A scene's points generated in worker processes, one instance per task.

Instances are independent (each seeded by points.instance_seed), so the result equals
points.generate_scene_points's, array for array; on two cores a large scene's points take about half the
time. Workers come from the Embree tracer's fork server (tracer.embree.worker_context: Embree's threads
do not survive a plain fork), get the scene pickled and each builds its own buried-surface test.
"""
from __future__ import annotations

import os
import signal
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

from psao.scene.model import Scene
from psao.server.points.buried import BuriedTest
from psao.server.points.generate import PointSet, instance_points
from psao.server.settings import PointSettings
from psao.server.tracer.embree import die_with, worker_context

_JOB: tuple | None = None  # (scene, settings, buried test or None) in a worker


def _init(parent: int, scene: Scene, settings: PointSettings, skip_buried: bool) -> None:
    global _JOB
    die_with(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent shuts the pool down on Ctrl-C
    _JOB = (scene, settings, BuriedTest(scene) if skip_buried else None)


def _one(k: int) -> tuple[int, PointSet]:
    scene, settings, buried = _JOB
    return k, instance_points(scene, settings, k, buried)


def generate_scene_points_parallel(scene: Scene, settings: PointSettings, workers: int, skip_buried: bool,
                                   progress=None) -> list[PointSet]:
    """generate_scene_points(scene, settings, progress, BuriedTest(scene) if skip_buried else None) in
    `workers` processes (the largest instances first, so none is left running alone at the end)."""
    n = len(scene.instances)
    area = [scene.meshes[i.mesh].area(np.asarray(i.transform)[:3, :3]) for i in scene.instances]
    out: list[PointSet | None] = [None] * n
    with ProcessPoolExecutor(workers, mp_context=worker_context(), initializer=_init,
                             initargs=(os.getpid(), scene, settings, skip_buried)) as pool:
        futures = [pool.submit(_one, k) for k in sorted(range(n), key=lambda k: -area[k])]
        for done, f in enumerate(as_completed(futures), 1):
            k, ps = f.result()
            out[k] = ps
            if progress is not None:
                progress(done, n)
    return out
