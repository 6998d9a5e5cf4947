"""Weights files of the learned AO methods: one .npz of named float32 arrays plus a JSON header.

    arrays = load_weights(path, "mlp", expected_shapes)   # RenderError (one line) on anything wrong

Checked before anything reaches the GPU: the file exists and is an .npz, its header names the method,
every expected array is there with the expected shape, and no value is NaN or infinite.
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from psao.client.errors import RenderError


def save_weights(path, method: str, arrays: dict[str, np.ndarray], header: dict) -> int:
    """Write the arrays as float32 (atomically: temporary name, then rename); returns the weight bytes."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {k: np.asarray(v, np.float32) for k, v in arrays.items()}
    tmp = path.with_name(path.name + ".partial.npz")
    np.savez_compressed(tmp, header_json=np.array(json.dumps({**header, "method": method})), **out)
    tmp.replace(path)
    return int(sum(v.nbytes for v in out.values()))


def load_weights(path, method: str, shapes: dict[str, tuple] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, header). `shapes` maps array name -> expected shape (None in a shape: any length)."""
    path = Path(path)
    if not path.is_file():
        raise RenderError(f"{method} weights file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(str(z["header_json"]))
            arrays = {k: np.asarray(z[k]) for k in z.files if k != "header_json"}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise RenderError(f"{path}: not a {method} weights file ({' '.join(str(exc).split())[:120]})") from None
    if header.get("method") != method:
        raise RenderError(f"{path}: holds {header.get('method')!r} weights, not {method}")
    for name, shape in (shapes or {}).items():
        if name not in arrays:
            raise RenderError(f"{path}: {method} weights lack the array {name}")
        got = arrays[name].shape
        if len(got) != len(shape) or any(want is not None and g != want for g, want in zip(got, shape)):
            want_text = "x".join("N" if s is None else str(s) for s in shape)
            raise RenderError(f"{path}: {method} array {name} has shape {'x'.join(map(str, got))}, expected {want_text}")
    for name, a in arrays.items():
        if not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all():
            raise RenderError(f"{path}: {method} array {name} holds NaN, infinite or non-float values")
    return {k: v.astype(np.float32) for k, v in arrays.items()}, header


def weight_bytes(arrays: dict[str, np.ndarray]) -> int:
    return int(sum(np.asarray(v, np.float32).nbytes for v in arrays.values()))
