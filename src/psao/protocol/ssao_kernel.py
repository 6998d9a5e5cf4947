"""The SSAO baseline's sample kernel and rotation noise: one definition for the desktop client's SsaoPass and
the web page (served in /psao_constants.js), so both clients draw the same SSAO and their frames compare.

Normal-oriented hemisphere SSAO as in Crytek / LearnOpenGL: SAMPLES points in the +z unit hemisphere, denser
near the centre, rotated per pixel by a 4x4 noise tile. Both are seeded numpy draws: frames repeat.
"""
from __future__ import annotations

import numpy as np

SAMPLES = 16  # kernel points (the page's shader has this many)
SEED = 7  # the kernel's draw; the noise uses SEED + 1


def hemisphere_kernel(samples: int = SAMPLES, seed: int = SEED) -> np.ndarray:
    """(samples, 3) float32 points in the +z unit hemisphere, scaled as lerp(0.1, 1, (i/n)^2) (LearnOpenGL)."""
    rng = np.random.default_rng(seed)
    v = rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 1.0], size=(samples, 3))
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    v *= rng.uniform(0.0, 1.0, size=(samples, 1))
    scale = (np.arange(samples) / max(samples, 1)) ** 2
    v *= (0.1 + 0.9 * scale)[:, None]
    return v.astype(np.float32)


def rotation_noise(seed: int = SEED) -> np.ndarray:
    """(4, 4, 4) float32: 4x4 random tangent-plane rotation vectors (x, y in [-1, 1], z = w = 0), RGBA texels."""
    rng = np.random.default_rng(seed + 1)
    noise = np.zeros((4, 4, 4), dtype=np.float32)
    noise[..., :2] = rng.uniform(-1.0, 1.0, size=(4, 4, 2))
    return noise
