"""Which rays of a static point's ray set the static scene occludes, kept from the bake's trace.

A point that never moves keeps its ray set (directions from its id, normal and the seed), and the static
scene never changes under it, so whether the static scene occludes each of its rays holds for good. The
bake's tracer answers every ray from the static scene first and asks the moving instances only about the
rays it lets through (bake.load_bake_geometry), so keeping those answers costs no ray
(EmbreeTracer.visibility_and_static_hits). Near a mover, a point's AO then needs only the rays the static
scene lets through, traced against the moving parts alone (TracePart.static_hit): the full trace's answer
at a fraction of its cost (BudgetSettings.exact_cost says how much). A scene edit that makes a static
instance a mover voids every answer (forget); the tick keeps them again for a few points a tick as it
traces them whole (ServerTick._whole_static). Kept bit-packed per point id (ceil(rays / 8) bytes each,
np.packbits order).
"""
from __future__ import annotations

import numpy as np


class StaticHits:
    def __init__(self, n: int, rays: int, seed: int, static_ids: np.ndarray | None):
        """`n` point ids, of whose `static_ids` (points of static instances; None: none) answers may be kept,
        for ray sets of `rays` rays under `seed`."""
        self.rays, self.seed = int(rays), int(seed)
        self.bits = np.zeros((n, (self.rays + 7) // 8), np.uint8)
        self.static = np.zeros(n, bool)
        if static_ids is not None:
            self.static[static_ids] = True
        self.known = np.zeros(n, bool)

    @property
    def nbytes(self) -> int:
        return int(self.bits.nbytes + self.static.nbytes + self.known.nbytes)

    def keep(self, ids: np.ndarray, bits: np.ndarray) -> None:
        """The static scene's packed answers (len(ids), ceil(rays / 8)) for static points `ids`."""
        if not self.static[ids].all():
            raise ValueError("static hits are kept for points of static instances only")
        self.bits[ids] = bits
        self.known[ids] = True

    def fits(self, rays: int, seed: int) -> bool:
        """Whether these answers are for ray sets of `rays` rays under `seed`."""
        return self.rays == int(rays) and self.seed == int(seed)

    def forget(self, static_ids: np.ndarray) -> None:
        """The static scene changed (an edit made some of its instances movers): every kept answer is void,
        and answers may be kept for `static_ids` only (the points of the instances still static)."""
        self.known[:] = False
        self.static[:] = False
        self.static[static_ids] = True

    def packed(self, ids: np.ndarray) -> np.ndarray:
        """(P, ceil(rays / 8)) uint8 answers of known `ids`."""
        return self.bits[ids]

    def of(self, ids: np.ndarray) -> np.ndarray:
        """(P, rays) bool answers of known `ids` (the form the tests compare with
        EmbreeTracer.static_occluded; the tick hands the packed form to the tracer)."""
        return np.unpackbits(self.bits[ids], axis=1, count=self.rays).astype(bool)
