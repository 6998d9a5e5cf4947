"""Weighted sample elimination (Yuksel 2015) as a compiled Warp kernel.

The elimination is inherently sequential: remove the sample with the highest weight, lower the weight of
its neighbours, repeat. It runs as one Warp thread (`wp.launch(dim=1)`) on the CPU (LLVM), with an
array-based binary max-heap over a CSR neighbour graph built beforehand (psao.server.points.generate).

Heap order is a strict total order: higher weight first, equal weights broken towards the lower sample
index, so the result is fully determined by the graph and equals a brute-force "argmax, remove, update"
loop with the same tie-breaking (tests/test_points.py checks exactly that).
"""
from __future__ import annotations

import numpy as np
import warp as wp

wp.config.quiet = True
if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.19 prints its banner by log level, not `quiet`
    wp.config.log_level = wp.LOG_WARNING

_DEVICE = "cpu"


@wp.func
def _above(key: wp.array(dtype=wp.float64), ident: wp.array(dtype=wp.int32), a: wp.int32, b: wp.int32) -> wp.bool:
    # True when heap entry a belongs nearer the top than heap entry b
    ka = key[a]
    kb = key[b]
    if ka > kb:
        return True
    if ka == kb and ident[a] < ident[b]:
        return True
    return False


@wp.func
def _sift_down(
    key: wp.array(dtype=wp.float64),
    ident: wp.array(dtype=wp.int32),
    slot: wp.array(dtype=wp.int32),
    start: wp.int32,
    size: wp.int32,
):
    # keys live in heap order next to the sample ids, so comparisons read contiguous memory
    i = start
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        right = child + 1
        if right < size:
            if _above(key, ident, right, child):
                child = right
        if not _above(key, ident, child, i):
            break
        ki = key[i]
        key[i] = key[child]
        key[child] = ki
        a = ident[i]
        b = ident[child]
        ident[i] = b
        ident[child] = a
        slot[b] = i
        slot[a] = child
        i = child


@wp.kernel
def eliminate_kernel(
    offsets: wp.array(dtype=wp.int32),
    neighbours: wp.array(dtype=wp.int32),
    edge_weight: wp.array(dtype=wp.float64),
    keep_count: wp.int32,
    key: wp.array(dtype=wp.float64),
    ident: wp.array(dtype=wp.int32),
    slot: wp.array(dtype=wp.int32),
    out_removed: wp.array(dtype=wp.int32),
):
    n = key.shape[0]
    # weight of a sample: sum of its edge weights, summed in CSR order (the reference sums the same way)
    for i in range(n):
        s = wp.float64(0.0)
        for e in range(offsets[i], offsets[i + 1]):
            s = s + edge_weight[e]
        key[i] = s
        ident[i] = i
        slot[i] = i
    k = n / 2 - 1
    while k >= 0:
        _sift_down(key, ident, slot, k, n)
        k = k - 1
    size = n
    while size > keep_count:
        top = ident[0]
        size = size - 1
        key[0] = key[size]
        last = ident[size]
        ident[0] = last
        slot[last] = 0
        slot[top] = -1
        out_removed[top] = 1
        _sift_down(key, ident, slot, 0, size)
        for e in range(offsets[top], offsets[top + 1]):
            j = neighbours[e]
            h = slot[j]
            if h >= 0:
                # weights only decrease, so a max-heap needs only a sift down
                key[h] = key[h] - edge_weight[e]
                _sift_down(key, ident, slot, h, size)


def eliminate_csr(offsets: np.ndarray, neighbours: np.ndarray, edge_weight: np.ndarray, keep_count: int) -> np.ndarray:
    """Run the elimination on a symmetric CSR graph; returns the bool mask of kept samples.

    offsets (n+1,) int32, neighbours (E,) int32 sorted by row then column, edge_weight (E,) float64.
    """
    n = len(offsets) - 1
    if keep_count >= n:
        return np.ones(n, dtype=bool)
    wp.init()
    d = _DEVICE
    removed = wp.zeros(n, dtype=wp.int32, device=d)
    wp.launch(
        eliminate_kernel,
        dim=1,
        inputs=[
            wp.array(np.ascontiguousarray(offsets, dtype=np.int32), dtype=wp.int32, device=d),
            wp.array(np.ascontiguousarray(neighbours, dtype=np.int32), dtype=wp.int32, device=d),
            wp.array(np.ascontiguousarray(edge_weight, dtype=np.float64), dtype=wp.float64, device=d),
            int(keep_count),
            wp.empty(n, dtype=wp.float64, device=d),
            wp.empty(n, dtype=wp.int32, device=d),
            wp.empty(n, dtype=wp.int32, device=d),
        ],
        outputs=[removed],
        device=d,
    )
    return removed.numpy() == 0
