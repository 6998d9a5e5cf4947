"""Errors of scene loading.

    SceneError               base: a scene that cannot be loaded; the message names the file and element
    ├── SceneNotFound        a missing file or an unknown builtin: name
    ├── SceneFormatError     malformed TOML, an unsupported mesh format, a bad field
    └── GeometryError        NaN vertices, no usable triangles, a transform with NaN or zero scale
"""
from __future__ import annotations


class SceneError(Exception):
    pass


class SceneNotFound(SceneError):
    pass


class SceneFormatError(SceneError):
    pass


class GeometryError(SceneError):
    pass
