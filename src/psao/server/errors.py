"""Errors of the server package.

    ServerError              base
    ├── ConfigError          a setting out of range (density <= 0, rays < 1, tick rate out of 5..60)
    ├── GridError            a grid that cannot be built (dimensions beyond the key range, bad grid file)
    └── TracerError          a tracer back-end that cannot run (Embree missing, Warp without CUDA)
"""
from __future__ import annotations


class ServerError(Exception):
    pass


class ConfigError(ServerError):
    pass


class GridError(ServerError):
    pass


class TracerError(ServerError):
    pass
