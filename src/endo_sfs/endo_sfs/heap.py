"""A binary min-heap on preallocated numba arrays.

Keys (float64) and items (int64) live in two arrays of a fixed capacity;
the caller keeps the size and grows the arrays when they fill. Used by the
near-light solver to repair misordered nodes lowest first.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def heap_push(keys: np.ndarray, items: np.ndarray, size: int, key: float, item: int) -> int:
    """Push onto the binary min-heap keys[:size]/items[:size] (capacity permitting); new size."""
    k = size
    while k > 0:
        parent = (k - 1) >> 1
        if keys[parent] <= key:
            break
        keys[k] = keys[parent]
        items[k] = items[parent]
        k = parent
    keys[k] = key
    items[k] = item
    return size + 1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def heap_pop(keys: np.ndarray, items: np.ndarray, size: int) -> tuple[int, int]:
    """Pop the smallest item of the heap keys[:size]/items[:size]; (item, new size)."""
    top = items[0]
    size -= 1
    key = keys[size]
    item = items[size]
    k = 0
    while True:
        child = 2 * k + 1
        if child >= size:
            break
        if child + 1 < size and keys[child + 1] < keys[child]:
            child += 1
        if keys[child] >= key:
            break
        keys[k] = keys[child]
        items[k] = items[child]
        k = child
    keys[k] = key
    items[k] = item
    return top, size
