"""The video server's depth-aware denoise (psao.eval.video.masked_gaussian) against its definition run
the direct way, one masked scipy Gaussian pair per depth layer (`layered_gaussian`, below), on real
client G-buffers of the built-in scenes, in the same run. Targets (VERDICT lines):
  * equal: the two agree within 2e-6 on every frame (AO in [0, 1]);
  * faster: per scene, the layered filter's median time over the denoise's median, >= 3 on the
    scenes with many depth layers (robots, courtyard, space; the Cornell box has about a dozen).

    .venv/bin/python -m benchmarks.bench_denoise [--scenes builtin:robots,...] [--size 320x180] [--repeats 5]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from benchmarks.verdicts import Verdicts

LAYERED_SCENES = ("robots", "courtyard", "space")  # scenes whose frames span many depth layers


def layered_gaussian(ao: np.ndarray, mask: np.ndarray, depth: np.ndarray, sigma: float) -> np.ndarray:
    """The denoise's definition: a pixel's value is the Gaussian of the AO over the covered pixels of
    its own depth layer (5% of depth) and the two next to it, normalised by the Gaussian of their mask;
    uncovered pixels keep their value. Two scipy Gaussians per layer over the whole image."""
    from scipy.ndimage import gaussian_filter

    layer = np.floor(np.log(np.maximum(depth, 1e-6)) / 0.05)
    out = np.asarray(ao, np.float32).copy()
    for lo in np.unique(layer[mask]):
        sel = mask & (np.abs(layer - lo) <= 1)
        num = gaussian_filter(np.where(sel, ao, 0.0).astype(np.float32), sigma, mode="nearest")
        den = gaussian_filter(sel.astype(np.float32), sigma, mode="nearest")
        here = mask & (layer == lo)
        out[here] = num[here] / den[here]
    return out


def client_frames(spec: str, size: tuple[int, int], frames: int):
    """(mask, depth) of `frames` poses along the scene's camera path, drawn from a tiny grid."""
    from psao.eval.quality import QualityRenderer, frame_poses
    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings

    scene = load_scene(spec)
    poses = frame_poses(scene, frames, size, None)
    with QualityRenderer(scene, size) as qr:
        out = qr.render(bake_scene(scene, BakeSettings(density=4, rays=2)).grid, poses, timing_repeats=1)
    return scene.name, [(np.asarray(f.gbuffer.mask, bool), np.asarray(f.gbuffer.depth, np.float32)) for f in out]


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="builtin:cornell,builtin:robots,builtin:courtyard,builtin:space")
    p.add_argument("--size", default="320x180", help="frame size WxH")
    p.add_argument("--frames", type=int, default=2, help="frames per scene")
    p.add_argument("--sigma", type=float, default=1.0, help="denoise sigma in pixels (the video server's default)")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per frame and filter (median)")
    a = p.parse_args(argv)
    from psao.eval.video import masked_gaussian

    size = tuple(int(v) for v in a.size.lower().split("x"))
    v = Verdicts("bench_denoise")
    rng = np.random.default_rng(0)
    print(f"| scene | depth layers | layered ms | denoise ms | ratio | max diff |\n|---|---|---|---|---|---|")
    for spec in a.scenes.split(","):
        name, frames = client_frames(spec, size, a.frames)
        slow, fast, diff, layers = [], [], 0.0, []
        for mask, depth in frames:
            ao = np.where(mask, rng.random(mask.shape), 1.0).astype(np.float32)  # 1-spp-like noise
            want = layered_gaussian(ao, mask, depth, a.sigma)
            got = masked_gaussian(ao, mask, depth, a.sigma)
            diff = max(diff, float(np.abs(got - want).max()))
            layers.append(len(np.unique(np.floor(np.log(np.maximum(depth[mask], 1e-6)) / 0.05))))
            slow.append(_median_seconds(lambda: layered_gaussian(ao, mask, depth, a.sigma), a.repeats))
            fast.append(_median_seconds(lambda: masked_gaussian(ao, mask, depth, a.sigma), a.repeats))
        ratio = float(np.sum(slow) / np.sum(fast))
        print(f"| {name} | {np.mean(layers):.0f} | {1e3 * np.mean(slow):.1f} | {1e3 * np.mean(fast):.1f} | "
              f"{ratio:.1f} | {diff:.1e} |")
        v.check(f"{name} denoise vs layered Gaussian, max abs difference", diff, "<=", 2e-6)
        if name in LAYERED_SCENES:
            v.check(f"{name} layered / denoise time ratio at {size[0]}x{size[1]}", ratio, ">=", 3.0)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
