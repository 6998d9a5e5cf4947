"""PSAO: point-based split rendering of ray-traced ambient occlusion.

The Python API for embedding (imported on first use, so `import psao` stays light):

    psao.Server, psao.ServerSettings   psao.server.embed: a server in this process, moved by the application
    psao.Client                        psao.client.embed: a headless client in this process
"""
from __future__ import annotations

_HOMES = {"Server": "psao.server.embed", "ServerSettings": "psao.server.embed", "Client": "psao.client.embed"}


def __getattr__(name: str):
    if name in _HOMES:
        import importlib

        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module 'psao' has no attribute {name!r}")


__all__ = sorted(_HOMES)
