"""Scene loading shared by the server and the client: `load_scene(spec)` returns a psao.scene.model.Scene.

The names below are imported on first use (PEP 562), so a module that needs only a light part of the
package (psao.scene.limits, psao.scene.errors) does not pay for the loaders and trimesh.
"""
from __future__ import annotations

import importlib

_HOMES = {  # exported name -> the module that defines it
    "camera_at": "camera", "default_orbit": "camera", "look_at": "camera", "perspective": "camera",
    "scene_camera": "camera",
    "GeometryError": "errors", "SceneError": "errors", "SceneFormatError": "errors", "SceneNotFound": "errors",
    "load_scene": "loader",
    "CameraKey": "model", "CameraPath": "model", "Instance": "model", "Mesh": "model", "Scene": "model",
    "animation_hash": "model",
    "RigidAnimation": "rigid", "instance_transform": "rigid", "is_dynamic": "rigid",
    "Skin": "skin",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'psao.scene' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"psao.scene.{home}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_HOMES})
