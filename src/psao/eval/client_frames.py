"""Score the frames a streaming client rendered itself (`psao client URL --render DIR`) against RTAO.

    scores = score_client_frames(scene, "out/demo/client_frames", count=2, settings=ReferenceSettings(spp=64))

The client writes each frame's AO as an 8-bit PNG and a line of DIR/frames.jsonl with the camera time,
the server time and the instance transforms it drew with. For each picked frame the same G-buffer is
drawn again here (same renderer, same camera, transforms and skinning pose), SSAO is rendered on it for
comparison, and the RTAO reference is traced from it; the client's PSAO image is the one it wrote, so
what is scored is what the streaming client showed (8-bit AO: at most 1/510 of rounding).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from psao.eval.errors import EvalError
from psao.eval.metrics import Scores, composite_ao, score
from psao.eval.reference import FrameKey, ReferenceSettings, reference_ao


@dataclass
class ClientFrame:
    frame: int
    time: float  # camera time on the path, seconds
    skin_time: float | None  # skinned meshes were posed at this time (None: rest pose)
    transforms: np.ndarray  # (n, 4, 4)
    camera_path: str | None
    size: tuple[int, int]
    wall: float | None = None  # time.time() when the client wrote it (None: a log without it)


@dataclass
class ClientFrameScores:
    frame: int
    psao: Scores
    ssao: Scores


def load_client_frames(frames_dir) -> list[ClientFrame]:
    path = Path(frames_dir) / "frames.jsonl"
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise EvalError(f"client frames log {path}: {exc.strerror or exc}") from None
    out = []
    for k, line in enumerate(lines):
        try:
            d = json.loads(line)
            t = np.asarray(d["transforms"], np.float64).reshape(-1, 4, 4)
            out.append(ClientFrame(int(d["frame"]), float(d["time"]), d.get("skin_time"), t, d.get("camera_path"),
                                   (int(d["size"][0]), int(d["size"][1])), d.get("wall")))
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise EvalError(f"{path}, line {k + 1}: not a frame record ({exc})") from None
    return out


def pick(frames: list[ClientFrame], count: int) -> list[ClientFrame]:
    """`count` frames spread over the run (the first is often the snapshot's, before any motion)."""
    if not frames or count < 1:
        return []
    idx = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    return [frames[i] for i in idx]


def read_ao_png(path: Path, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    try:
        img = np.asarray(Image.open(path).convert("L"), np.float32) / 255.0
    except OSError as exc:
        raise EvalError(f"client frame {path}: {exc}") from None
    if img.shape != (size[1], size[0]):
        raise EvalError(f"client frame {path} is {img.shape[1]}x{img.shape[0]}, its log says {size[0]}x{size[1]}")
    return img


def score_client_frames(scene, frames_dir, count: int, settings: ReferenceSettings, show_progress: bool = False,
                        pose=None, frames: list[ClientFrame] | None = None) -> list[ClientFrameScores]:
    """PSAO (the client's own PNG) and SSAO (drawn here on the same G-buffer) against RTAO, per frame:
    `count` of `frames` (all the log's by default). The G-buffer and the reference take the transforms and
    skinning time the client drew with, or `pose(frame)` -> (transforms, skin time): e.g. the scene's pose at
    the server's time when the frame was shown, so that a client whose mirror lags is scored against what
    it should have shown."""
    from psao.client.render.renderer import FrameRenderer
    from psao.client.render.views import path_matrices
    from psao.scene import scene_camera

    frames_dir = Path(frames_dir)
    picked = pick(load_client_frames(frames_dir) if frames is None else frames, count)
    if not picked:
        return []
    size = picked[0].size
    out = []
    with FrameRenderer(scene, size, "ssao") as r:
        for f in picked:
            name = f.camera_path if f.camera_path in scene.camera_paths else None
            view, proj = path_matrices(scene, scene_camera(scene, name), f.time, size)
            transforms, skin_time = (f.transforms, f.skin_time) if pose is None else pose(f)
            r.set_transforms(transforms)
            r.set_skin_time(skin_time)
            frame = r.render(view, proj)
            mask = frame.gbuffer.mask
            psao = composite_ao(read_ao_png(frames_dir / f"frame_{f.frame:05d}_ao_psao.png", size), mask)
            ssao = composite_ao(frame.ao["ssao"], mask)
            ao = reference_ao(scene, frame.gbuffer, transforms, replace(settings, skin_time=skin_time),
                              FrameKey(view, proj, f.time), show_progress=show_progress)
            ref = composite_ao(ao, mask)
            out.append(ClientFrameScores(f.frame, score(ref, psao)[0], score(ref, ssao)[0]))
    return out
