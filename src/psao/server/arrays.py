"""Array helpers for the per-tick paths."""
from __future__ import annotations

import numpy as np


def rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """a[index] for an index array along the first axis: np.take, which costs several times less than
    numpy's fancy indexing of the rows of a 2-D array."""
    return np.take(a, index, axis=0)
