"""Frames to disk: numbered PNGs of the composite and the AO of each mode, and size parsing."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from psao.client.errors import RenderError


def parse_size(text: str) -> tuple[int, int]:
    """'640x360' -> (640, 360). Zero and GL limits are checked by the renderer, with its context."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not m:
        raise RenderError(f"frame size {text!r}: expected WIDTHxHEIGHT, e.g. 640x360")
    return int(m.group(1)), int(m.group(2))


def ao_to_uint8(ao: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(ao, np.float32) * 255.0), 0, 255).astype(np.uint8)


def save_frame(frame, out_dir: Path, index: int) -> list[Path]:
    """Write frame_NNNNN_composite_MODE.png and frame_NNNNN_ao_MODE.png; returns the paths."""
    from PIL import Image

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for mode, rgb in frame.composite.items():
        path = out_dir / f"frame_{index:05d}_composite_{mode}.png"
        Image.fromarray(rgb, mode="RGB").save(path)
        written.append(path)
    for mode, ao in frame.ao.items():
        path = out_dir / f"frame_{index:05d}_ao_{mode}.png"
        Image.fromarray(ao_to_uint8(ao), mode="L").save(path)
        written.append(path)
    return written
