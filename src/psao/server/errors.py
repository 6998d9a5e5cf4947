"""Errors of the server package.

    ServerError              base
    ├── ConfigError          a setting out of range (density <= 0, rays < 1, tick rate out of 5..60)
    ├── GridError            a grid that cannot be built (dimensions beyond the key range, bad grid file)
    ├── InstanceError        an instance psao.Server cannot add or remove (unknown mesh or instance, a name
    │                        taken, a matrix that is not finite, singular or out of a SceneEdit's limits)
    └── TracerError          a tracer back-end that cannot run (Embree missing, Warp without CUDA)
"""
from __future__ import annotations


class ServerError(Exception):
    pass


class ConfigError(ServerError):
    pass


class GridError(ServerError):
    pass


class InstanceError(ServerError):
    pass


class TracerError(ServerError):
    pass
