"""The served scene as psao.protocol.scenefile bytes (what SceneData sends), compressed once per scene hash.

Skins are sampled: the skinning matrices of every skinned mesh at `samples_per_second` over one period
of its animator (its `duration`: a glTF animation's length, a walk cycle; 0 or none: static, one sample).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import zstandard

from psao.protocol.scenefile import CameraPathData, InstanceData, MeshData, SceneFile, SkinData


@dataclass(frozen=True)
class SceneExportSettings:
    samples_per_second: float = 120.0  # skin poses per second of animation (robots: poses within 5 mm)
    max_samples: int = 2048  # per skin; longer animations are sampled more sparsely
    zstd_level: int = 19  # sent once per client, compressed once per server: worth the strongest level
    # what clients that ask while the strongest level is still compressing get (psao serve): Sponza's 3.8 MB
    # file is 17% larger than at level 19 but compressed 20x faster
    first_zstd_level: int = 3


def skin_data(skin, settings: SceneExportSettings) -> SkinData:
    period = float(getattr(skin.animator, "duration", 0.0) or 0.0)
    k = 1 if period <= 0 else int(min(settings.max_samples, max(2, np.ceil(period * settings.samples_per_second))))
    times = np.arange(k) * (period / k)
    mats = np.stack([skin.skinning_matrices(t)[:, :3, :] for t in times]).astype(np.float32)
    return SkinData(np.asarray(skin.joints, np.uint8), np.asarray(skin.weights, np.float32), period, mats)


def scene_file(scene, settings: SceneExportSettings = SceneExportSettings()) -> SceneFile:
    """A psao.scene Scene as the wire format's plain arrays."""
    meshes = [MeshData(m.name, np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32), bool(m.double_sided),
                       tuple(float(c) for c in m.color), None if m.skin is None else skin_data(m.skin, settings))
              for m in scene.meshes]
    instances = [InstanceData(i.name, int(i.mesh), np.asarray(i.transform, np.float32)) for i in scene.instances]
    paths = [CameraPathData(p.name, float(p.fov_y), bool(p.loop),
                            np.array([[k.time, *k.eye, *k.target] for k in p.keys], np.float32))
             for p in scene.camera_paths.values()]
    return SceneFile(scene.name, float(scene.ao_distance), meshes, instances, paths)


_BLOBS: dict[tuple[str, int], bytes] = {}  # (scene content hash, zstd level) -> compressed scene file
_FILES: dict[str, bytes] = {}  # scene content hash -> the scene file


def scene_blob(scene, settings: SceneExportSettings = SceneExportSettings(), level: int | None = None) -> bytes:
    """The zstd-compressed scene file SceneData carries, at zstd `level` (default: settings.zstd_level);
    built once per scene content hash and level. Every level decompresses to the same file."""
    key = (scene.content_hash(), settings.zstd_level if level is None else level)
    if key not in _BLOBS:
        _BLOBS[key] = zstandard.ZstdCompressor(level=key[1]).compress(_scene_bytes(scene, settings))
    return _BLOBS[key]


def _scene_bytes(scene, settings: SceneExportSettings) -> bytes:
    key = scene.content_hash()
    if key not in _FILES:
        _FILES[key] = scene_file(scene, settings).serialize()
    return _FILES[key]
