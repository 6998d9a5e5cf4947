"""Errors of the client package.

    ClientError              base
    ├── ConnectError         server unreachable, refused, or closed with an error
    ├── MirrorError          an update that does not fit the mirror (slot or bucket out of range)
    └── RenderError          no EGL, a GLSL compile error, a bad size, a grid from another scene
"""
from __future__ import annotations


class ClientError(Exception):
    pass


class ConnectError(ClientError):
    pass


class MirrorError(ClientError):
    pass


class RenderError(ClientError):
    pass
