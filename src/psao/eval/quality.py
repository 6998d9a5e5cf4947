"""AO quality of PSAO and SSAO against the RTAO reference, frame by frame along a camera path.

    poses = frame_poses(scene, frames=4, size=(640, 360))
    with QualityRenderer(scene, size) as qr:
        frames = qr.render(grid, poses)              # PSAO and SSAO from one renderer, one G-buffer
    refs = reference_images(scene, frames, ReferenceSettings(spp=512))
    rows = score_frames(frames, refs)                # per frame and method: Scores

PSAO and SSAO run in the same FrameRenderer ("both"), so they shade the same G-buffer the reference
traces from. The geometry is the scene at its rest transforms (a baked grid is the server's state at
t = 0; the camera moves along its path).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psao.eval.errors import EvalError
from psao.eval.metrics import Scores, composite_ao, score
from psao.eval.reference import FrameKey, ReferenceSettings, reference_ao


@dataclass
class FramePose:
    index: int
    time: float  # seconds on the camera path
    view: np.ndarray
    proj: np.ndarray


@dataclass
class RenderedFrame:
    pose: FramePose
    ao: dict[str, np.ndarray]  # method -> (H, W) AO composited (1 on background)
    mask: np.ndarray  # covered pixels
    gbuffer: object  # GBufferArrays
    gpu_ms: dict[str, float]  # method -> client GPU ms for the frame (G-buffer pass + the AO pass(es))
    holes: float = 0.0  # fraction of covered pixels where PSAO found no point (weight 0)
    transforms: np.ndarray | None = None  # (n, 4, 4) instance transforms the frame was drawn with
    composite: dict | None = None  # method -> (H, W, 3) uint8 lit colour x AO, as the client shows it
    skin_time: float | None = None  # seconds: skinned meshes were drawn posed at this time (None: rest pose)


@dataclass
class FrameScores:
    frame: int
    method: str
    scores: Scores
    flip_map: np.ndarray = field(repr=False)


def frame_poses(scene, frames: int, size: tuple[int, int], camera_path: str | None = None) -> list[FramePose]:
    """Frames spread over one period of the scene's camera path (an orbit around its bounds, with a
    warning, when it has none)."""
    from psao.client.render.views import path_matrices, path_times
    from psao.scene import scene_camera

    if frames < 1:
        raise EvalError(f"frames must be >= 1, got {frames}")
    try:
        path = scene_camera(scene, camera_path)
    except KeyError as exc:
        raise EvalError(str(exc.args[0])) from None
    poses = []
    for i, t in enumerate(path_times(path, frames)):
        view, proj = path_matrices(scene, path, float(t), size)
        poses.append(FramePose(i, float(t), view, proj))
    return poses


def rest_transforms(scene) -> np.ndarray:
    return np.stack([np.asarray(i.transform, np.float64) for i in scene.instances]) if scene.instances \
        else np.zeros((0, 4, 4))


class QualityRenderer:
    """One headless FrameRenderer rendering PSAO and the baselines together, reused for every grid and frame.
    gpu_ms of a method is the G-buffer pass plus its own passes (timer names MODE and MODE_*)."""

    def __init__(self, scene, size: tuple[int, int], ssao_samples: int = 16, methods=("psao", "ssao"), options=None):
        from psao.client.render.renderer import FrameRenderer, MethodOptions

        self.scene = scene
        self.size = tuple(size)
        options = options or MethodOptions(ssao_samples=int(ssao_samples))
        self.renderer = FrameRenderer(scene, self.size, ",".join(methods), options=options)
        self.gl_renderer = self.renderer.ctx.info.get("GL_RENDERER", "")

    def render(self, grid, poses: list[FramePose], timing_repeats: int = 3, before_frame=None) -> list[RenderedFrame]:
        """`grid` has instances, buckets and cells (a GridFile or a Grid). Each frame's pass times are
        the minimum over `timing_repeats` submissions: on a shared CPU (llvmpipe) other processes only
        ever add time. `before_frame(pose) -> (grid, transforms)`, when given, supplies the grid state and
        instance transforms of each frame (an animated scene, the server ticked up to pose.time, so skinned
        meshes are drawn posed at pose.time); otherwise the grid is drawn at rest."""
        r = self.renderer
        r.upload_grid(grid.instances, grid.buckets, grid.cells)
        r.set_transforms(rest_transforms(self.scene))
        r.set_skin_time(None)
        r.render(poses[0].view, poses[0].proj, read_gbuffer=False)  # warm-up: first-frame timings are bogus
        out = []
        for pose in poses:
            if before_frame is not None:
                g, transforms = before_frame(pose)
                r.upload_grid(g.instances, g.buckets, g.cells)
                r.set_transforms(transforms)
                r.set_skin_time(pose.time)
            frame = r.render(pose.view, pose.proj)
            mask = frame.gbuffer.mask
            ms = dict(frame.gpu_ms)
            for _ in range(max(0, timing_repeats - 1)):
                r.submit(pose.view, pose.proj)
                for k, v in {**r.timer.collect(), **r.cpu_ms()}.items():
                    ms[k] = min(ms.get(k, v), v)
            gpu = {m: ms.get("gbuffer", 0.0) + sum(v for k, v in ms.items() if k == m or k.startswith(m + "_"))
                   for m in r.modes}
            holes = 0.0 if frame.psao_weight is None else \
                float(((frame.psao_weight <= 0) & mask).sum() / max(int(mask.sum()), 1))
            out.append(RenderedFrame(pose, {m: composite_ao(a, mask) for m, a in frame.ao.items()}, mask,
                                     frame.gbuffer, gpu, holes, np.array(r.transforms, copy=True), frame.composite,
                                     r.skin_time))
        return out

    def close(self) -> None:
        self.renderer.release()

    def __enter__(self) -> "QualityRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def reference_images(scene, frames: list[RenderedFrame], settings: ReferenceSettings,
                     show_progress: bool | None = None) -> list[np.ndarray]:
    """Composited RTAO per frame (cached on disk by scene, camera, time, transforms, spp and size); the
    occluders are placed by the transforms each frame was drawn with, skinned meshes posed as drawn."""
    from dataclasses import replace

    rest = rest_transforms(scene)
    refs = []
    for f in frames:
        transforms = rest if f.transforms is None else f.transforms
        frame_settings = replace(settings, skin_time=f.skin_time)
        ao = reference_ao(scene, f.gbuffer, transforms, frame_settings, FrameKey(f.pose.view, f.pose.proj, f.pose.time),
                          show_progress=show_progress)
        refs.append(composite_ao(ao, f.mask))
    return refs


def score_frames(frames: list[RenderedFrame], refs: list[np.ndarray], methods=("psao", "ssao")) -> list[FrameScores]:
    rows = []
    for f, ref in zip(frames, refs):
        for m in methods:
            s, fmap = score(ref, f.ao[m])
            rows.append(FrameScores(f.pose.index, m, s, fmap))
    return rows


def mean_scores(rows: list[FrameScores], method: str) -> Scores:
    sel = [r.scores for r in rows if r.method == method]
    if not sel:
        raise EvalError(f"no scores for method {method!r}")
    return Scores(psnr=float(np.mean([s.psnr for s in sel])), ssim=float(np.mean([s.ssim for s in sel])),
                  flip=float(np.mean([s.flip for s in sel])), bias=float(np.mean([s.bias for s in sel])))
