"""RTAO reference: ray-traced AO for every covered pixel of a renderer G-buffer.

    settings = ReferenceSettings(spp=512)
    ao = reference_ao(scene, gbuffer, transforms, settings, key=FrameKey(view, proj, time))

The pixels' world positions and normals come from the client's own G-buffer, so the reference sees
exactly the surfaces the client shaded (same visibility, same double-sided normal flips). Occluders are
the scene's triangles placed by the same instance transforms the frame was rendered with, and skinned
meshes posed at `skin_time` (the time the renderer posed them at; None = rest pose). Rays are the tracer's cosine-weighted set within the AO distance (Embree, every core),
seeded by the pixel index, so a pixel's estimate is the same on every run.

References are cached on disk (out/.cache/rtao/ by default) under a key of the scene's content hash,
the transforms, the camera matrices, the frame time, spp, seed and size.
"""
from __future__ import annotations

import hashlib
import json
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psao.eval.errors import EvalError

DEFAULT_CACHE = Path("out") / ".cache" / "rtao"


@dataclass
class ReferenceSettings:
    spp: int = 512  # cosine-weighted rays per pixel
    seed: int = 0x5EED  # added to the pixel index hash; not the bake's seed, so rays differ from the server's
    workers: int = 0  # Embree worker processes; 0 = all cores
    chunk_pixels: int = 1024  # pixels per work item (memory: chunk * spp rays)
    cache_dir: Path | None = DEFAULT_CACHE  # None = no cache
    skin_time: float | None = None  # seconds: deform skinned meshes to this time; None = rest pose

    def check(self) -> None:
        if self.spp < 1:
            raise EvalError(f"reference samples per pixel must be >= 1, got {self.spp}")
        if self.workers < 0:
            raise EvalError(f"reference workers must be >= 0, got {self.workers}")


@dataclass
class FrameKey:
    """What identifies a frame beyond the scene: camera matrices and time (seconds)."""

    view: np.ndarray
    proj: np.ndarray
    time: float = 0.0


def frame_geometry(scene, transforms: np.ndarray, skin_time: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles of every instance under `transforms` (n, 4, 4), merged."""
    transforms = np.asarray(transforms, np.float64)
    if transforms.shape != (len(scene.instances), 4, 4):
        raise EvalError(f"transforms have shape {transforms.shape}, the scene has {len(scene.instances)} instances")
    skinner = None
    if skin_time is not None and any(m.skin is not None for m in scene.meshes):
        from psao.scene.skinning import SceneSkinner
        skinner = SceneSkinner(scene)
    verts, faces, base = [], [], 0
    for inst, m in zip(scene.instances, transforms):
        mesh = scene.meshes[inst.mesh]
        local = skinner.vertices(inst.mesh, skin_time) if skinner is not None else mesh.vertices
        verts.append(np.asarray(local, np.float64) @ m[:3, :3].T + m[:3, 3])
        faces.append(np.asarray(mesh.faces, np.int64) + base)
        base += len(local)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(verts), np.concatenate(faces)


def cache_key(scene, transforms, key: FrameKey, size: tuple[int, int], settings: ReferenceSettings) -> str:
    h = hashlib.sha256()
    h.update(scene.content_hash().encode())
    h.update(np.ascontiguousarray(transforms, np.float64).tobytes())
    h.update(np.ascontiguousarray(key.view, np.float64).tobytes())
    h.update(np.ascontiguousarray(key.proj, np.float64).tobytes())
    h.update(json.dumps([float(key.time), int(settings.spp), int(settings.seed), list(map(int, size)),
                         settings.skin_time]).encode())
    return h.hexdigest()[:32]


def _load_cached(path: Path, shape) -> np.ndarray | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            ao = z["ao"]
    except (OSError, KeyError, ValueError):
        return None  # a missing or damaged entry is recomputed
    return ao if ao.shape == shape and ao.dtype == np.float32 else None


def _store(path: Path, ao: np.ndarray) -> None:
    """Write to a temporary name and rename, so a killed run never leaves a half-written entry."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, ao=ao)
        tmp.replace(path)
    except OSError as exc:
        print(f"psao: warning: RTAO cache not written ({exc})", file=sys.stderr)


def _progress(enabled: bool, total: int, label: str):
    if not enabled:
        return nullcontext(None)
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
    return Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
                    transient=True, console=Console(stderr=True))


def trace_pixels(scene, world: np.ndarray, normal: np.ndarray, pixel_ids: np.ndarray, transforms,
                 settings: ReferenceSettings, show_progress: bool = False, label: str = "RTAO") -> np.ndarray:
    """Visibility of world-space points (P, 3) with unit normals (P, 3) against the frame's geometry."""
    from psao.server.geometry import scene_center
    from psao.server.settings import TraceSettings
    from psao.server.tracer import make_tracer

    verts, faces = frame_geometry(scene, transforms, settings.skin_time)
    trace = TraceSettings(rays=settings.spp, ao_distance=float(scene.ao_distance), seed=settings.seed,
                          chunk_points=max(1, settings.chunk_pixels))
    # Re-centre on the scene's bounds as the server does (float32 detail far from the origin).
    with make_tracer("embree", scene_center(scene), workers=settings.workers) as tracer:
        tracer.set_static(verts, faces)
        with _progress(show_progress, len(world), label) as bar:
            task = bar.add_task(label, total=len(world)) if bar else None
            return tracer.visibility(world, normal, pixel_ids, trace,
                                     progress=(lambda k: bar.advance(task, k)) if bar else None)


def reference_ao(scene, gbuffer, transforms, settings: ReferenceSettings | None = None, key: FrameKey | None = None,
                 show_progress: bool | None = None) -> np.ndarray:
    """(H, W) float32 RTAO visibility, 1 on background pixels. `gbuffer` is a GBufferArrays (world,
    normal, mask); `key` enables the on-disk cache."""
    settings = settings or ReferenceSettings()
    settings.check()
    mask = np.asarray(gbuffer.mask, bool)
    h, w = mask.shape
    path = None
    if key is not None and settings.cache_dir is not None:
        path = Path(settings.cache_dir) / f"{cache_key(scene, transforms, key, (w, h), settings)}.npz"
        cached = _load_cached(path, (h, w)) if path.is_file() else None
        if cached is not None:
            return cached
    ao = np.ones((h, w), np.float32)
    pixel_ids = np.flatnonzero(mask.reshape(-1))
    if len(pixel_ids):
        world = np.asarray(gbuffer.world, np.float64).reshape(-1, 3)[pixel_ids]
        normal = np.asarray(gbuffer.normal, np.float64).reshape(-1, 3)[pixel_ids]
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        if show_progress is None:
            show_progress = sys.stderr.isatty()
        vis = trace_pixels(scene, world, normal.astype(np.float32), pixel_ids, transforms, settings, show_progress,
                           label=f"RTAO {settings.spp} spp")
        ao.reshape(-1)[pixel_ids] = vis
    if path is not None:
        _store(path, ao)
    return ao
