"""The order in which the near-light solver visits its nodes.

Causal upwind schemes are solved in one pass when every node comes after
its upwind neighbours, i.e. in increasing order of the solution; a predicted
value per node (the previous frame's solution, or v* cold) gives that order
up to its errors (:func:`value_order`), and :func:`split_first_pass` cuts it
into two halves that two threads can visit at once.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Buckets per node of the counting sort of the first pass.
FIRST_PASS_BUCKETS = 0.25
_NO_NODES = np.empty(0, dtype=np.int64)


@njit(cache=True, nogil=True, error_model="numpy")
def value_order(v: np.ndarray, valid: np.ndarray, buckets_per_node: float) -> np.ndarray:
    """Flat indices of the valid nodes of ``v``, roughly in increasing order of value.

    A counting sort into about ``buckets_per_node`` × (number of nodes)
    equal-width buckets between the smallest and largest finite value: O(N),
    exact up to the order inside a bucket (which the sweeps that follow
    repair). v: (ny, nx) float64; valid: (ny, nx) uint8. Returns (n,) int64.
    """
    ny, nx = v.shape
    count = 0
    low = np.inf
    high = -np.inf
    for i in range(ny):
        for j in range(nx):
            if valid[i, j] and np.isfinite(v[i, j]):
                count += 1
                if v[i, j] < low:
                    low = v[i, j]
                if v[i, j] > high:
                    high = v[i, j]
    out = np.empty(count, dtype=np.int64)
    if count == 0:
        return out
    buckets = max(1, int(count * buckets_per_node))
    scale = buckets / (high - low) if high > low else 0.0
    start = np.zeros(buckets + 1, dtype=np.int64)
    for i in range(ny):
        for j in range(nx):
            if valid[i, j] and np.isfinite(v[i, j]):
                k = min(int((v[i, j] - low) * scale), buckets - 1)
                start[k + 1] += 1
    for k in range(buckets):
        start[k + 1] += start[k]
    for i in range(ny):
        for j in range(nx):
            if valid[i, j] and np.isfinite(v[i, j]):
                k = min(int((v[i, j] - low) * scale), buckets - 1)
                out[start[k]] = i * nx + j
                start[k] += 1
    return out


#: A half of the first pass must hold at least this share of the nodes;
#: otherwise the pass runs on one thread.
MIN_SPLIT_SHARE = 0.25


@njit(cache=True, nogil=True, error_model="numpy")
def split_first_pass(
    ordered: np.ndarray, nx: int, reach: int
) -> tuple[np.ndarray, int, np.ndarray]:
    """Split a value-ordered first pass into two regions for :func:`near_light_sweep`.

    ordered: (n,) int64 flat indices in increasing order of the predicted
    value; nx: padded grid width; reach: stencil reach (1 or 2).
    Information flows from low to high values, from the predicted nearest
    point (ordered[0]) towards the farthest (ordered[-1]). The seam is the
    grid line through the nearest point along that flow (a row when the flow
    is mostly horizontal, else a column), so that few characteristics cross
    it; the other orientation is tried when a side would hold less than
    MIN_SPLIT_SHARE of the nodes. Returns (the two regions' nodes, each in
    its value order, concatenated; the length of the first, 0 when no
    balanced split exists; (m,) flat indices of the nodes within ``reach``
    of the seam).
    """
    n = ordered.size
    if n < 2:
        return ordered, 0, _NO_NODES
    rows = ordered // nx
    columns = ordered - rows * nx
    flow_is_horizontal = abs(columns[n - 1] - columns[0]) >= abs(rows[n - 1] - rows[0])
    for attempt in range(2):
        by_row = flow_is_horizontal if attempt == 0 else not flow_is_horizontal
        coordinate = rows if by_row else columns
        line = coordinate[0]
        first = 0
        seam_count = 0
        for k in range(n):
            if coordinate[k] < line:
                first += 1
            if line - reach <= coordinate[k] < line + reach:
                seam_count += 1
        if not MIN_SPLIT_SHARE * n <= first <= (1.0 - MIN_SPLIT_SHARE) * n:
            continue
        out = np.empty(n, dtype=np.int64)
        seam = np.empty(seam_count, dtype=np.int64)
        a = 0
        b = first
        m = 0
        for k in range(n):
            if coordinate[k] < line:
                out[a] = ordered[k]
                a += 1
            else:
                out[b] = ordered[k]
                b += 1
            if line - reach <= coordinate[k] < line + reach:
                seam[m] = ordered[k]
                m += 1
        return out, first, seam
    return ordered, 0, _NO_NODES
