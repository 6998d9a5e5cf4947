"""The AO points of a baked grid, per instance, decoded with src/psao/protocol/'s formats (what MLP baking trains on)."""
from __future__ import annotations

import numpy as np

from psao.protocol.gridformat import EMPTY, KEY_MASK, POINTS_PER_CELL, decode_point_local, key_to_cell
from psao.protocol.pointword import dequantise_ao, oct_decode, unpack_point


def instance_points(instances, buckets, cells, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(local positions (P, 3), local normals (P, 3), AO visibility (P,)) of instance `index`."""
    rec = instances[index]
    b0, nb = int(rec["bucket_offset"]), int(rec["bucket_count"])
    entries = np.asarray(buckets[b0:b0 + nb]).reshape(-1, 2)
    used = entries[:, 0] != EMPTY
    keys, slots = entries[used, 0], entries[used, 1].astype(np.int64)
    words = np.asarray(cells)[slots, :POINTS_PER_CELL]
    allocated, qpos, ncode, aocode = unpack_point(words)
    cell_xyz = np.repeat(key_to_cell(keys & KEY_MASK, rec["dims"])[:, None, :], POINTS_PER_CELL, axis=1)
    pos = decode_point_local(cell_xyz[allocated], qpos[allocated], rec["origin"], float(rec["cell_size"]))
    return pos.astype(np.float64), oct_decode(ncode[allocated]).astype(np.float64), dequantise_ao(aocode[allocated])
