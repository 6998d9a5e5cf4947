"""View and projection matrices for a frame of a scene's camera path (psao.scene.camera does the path)."""
from __future__ import annotations

import numpy as np

from psao.scene.camera import camera_at, look_at, perspective


def near_far(scene, eye) -> tuple[float, float]:
    """Clip planes holding the whole scene seen from eye; the near plane as far out as contact AO allows."""
    lo, hi = scene.world_bounds()
    far = float(np.linalg.norm(np.maximum(np.abs(hi - eye), np.abs(lo - eye)))) * 1.05 + 1e-3
    near = max(far * 1e-4, 0.01 * float(scene.ao_distance), 1e-4)
    return near, max(far, 2.0 * near)


def path_matrices(scene, path, t: float, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(view, proj) at time t seconds on a camera path, for a frame of size (width, height)."""
    eye, target = camera_at(path, t)
    near, far = near_far(scene, eye)
    return look_at(eye, target), perspective(path.fov_y, size[0] / size[1], near, far)


def path_times(path, frames: int) -> np.ndarray:
    """Frame times spread over one period of the path (a looping path does not repeat its first pose)."""
    t0, t1 = path.keys[0].time, path.keys[-1].time
    if frames <= 1 or t1 <= t0:
        return np.full(max(frames, 1), t0, dtype=np.float64)
    if path.loop:
        return t0 + (t1 - t0) * np.arange(frames) / frames
    return np.linspace(t0, t1, frames)
