"""Read a baked grid file (psao.server's Grid.save npz) without importing the server.

Keys used: instances (INSTANCE_DTYPE), buckets (uint32 (n, 8, 2)), cells (uint32 (capacity, 8)),
scene_hash (str), meta_json (str). Everything else in the file is server-side and ignored.
"""
from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psao.protocol.gridformat import BUCKET_ENTRIES, CELL_WORDS, INSTANCE_DTYPE
from psao.client.errors import RenderError


@dataclass
class GridFile:
    instances: np.ndarray
    buckets: np.ndarray
    cells: np.ndarray
    scene_hash: str
    meta: dict


def load_grid_file(path) -> GridFile:
    path = Path(path)
    if not path.is_file():
        raise RenderError(f"grid file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            grid = GridFile(
                instances=z["instances"], buckets=z["buckets"], cells=z["cells"],
                scene_hash=str(z["scene_hash"]), meta=json.loads(str(z["meta_json"])) if "meta_json" in z else {},
            )
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise RenderError(f"{path}: not a PSAO grid file ({' '.join(str(exc).split())})") from None
    _check_layout(path, grid)
    return grid


def _check_layout(path: Path, g: GridFile) -> None:
    if g.instances.dtype != INSTANCE_DTYPE or g.instances.ndim != 1:
        raise RenderError(f"{path}: instance table has dtype {g.instances.dtype}, not the PSAO instance record")
    if g.buckets.dtype != np.uint32 or g.buckets.shape[1:] != (BUCKET_ENTRIES, 2):
        raise RenderError(f"{path}: buckets have shape {g.buckets.shape} {g.buckets.dtype}, expected (n, 8, 2) uint32")
    if g.cells.dtype != np.uint32 or g.cells.ndim != 2 or g.cells.shape[1] != CELL_WORDS:
        raise RenderError(f"{path}: cells have shape {g.cells.shape} {g.cells.dtype}, expected (n, 8) uint32")
    end = g.instances["bucket_offset"].astype(np.int64) + g.instances["bucket_count"].astype(np.int64)
    if len(end) and int(end.max()) > len(g.buckets):
        raise RenderError(f"{path}: instance table refers to bucket {int(end.max()) - 1} of {len(g.buckets)}")


def check_scene(grid: GridFile, scene, path) -> None:
    """The grid must have been baked from this very scene (same content hash, same instance count)."""
    want = scene.content_hash()
    if grid.scene_hash != want:
        raise RenderError(
            f"{path} was baked from another scene (grid scene hash {grid.scene_hash[:12] or 'missing'}, "
            f"{scene.source or scene.name} has {want[:12]})")
    if len(grid.instances) != len(scene.instances):
        raise RenderError(f"{path} has {len(grid.instances)} instance records, the scene has {len(scene.instances)}")
