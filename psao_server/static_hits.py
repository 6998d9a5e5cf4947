"""Which rays of a static point's ray set the static scene occludes, traced once and kept.

A point that never moves keeps its ray set (directions from its id, normal and the seed), and the static
scene never changes under it, so whether the static scene occludes each of its rays holds for good. Near
a mover, the point's AO then needs only the rays the static scene lets through, traced against the
moving parts alone (EmbreeTracer.visibility_given_static): the full trace's answer for a fraction of its
cost. Kept bit-packed per point id (rays / 8 bytes each), filled on first need.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np


class StaticHits:
    def __init__(self, n: int, rays: int):
        self.rays = int(rays)
        self.bits = np.zeros((n, (self.rays + 7) // 8), np.uint8)
        self.known = np.zeros(n, bool)

    def forget(self) -> None:
        """The static scene changed: every kept answer is void."""
        self.known[:] = False

    def of(self, ids: np.ndarray, trace: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(P, rays) bool for `ids`; `trace(new_ids)` gives the (len(new_ids), rays) answers not kept yet."""
        new = ids[~self.known[ids]]
        if len(new):
            self.bits[new] = np.packbits(np.asarray(trace(new), bool), axis=1)
            self.known[new] = True
        return np.unpackbits(self.bits[ids], axis=1, count=self.rays).astype(bool)
