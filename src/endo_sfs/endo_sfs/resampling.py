"""Bilinear resampling between the pixel grid and a solve grid (numba, parallel over rows)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def sample_strict(
    image: np.ndarray, valid: np.ndarray, map_x: np.ndarray, map_y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``image`` at (map_x, map_y) pixel positions.

    image: (H, W) float; valid: (H, W) bool. map_x, map_y: (h, w) float
    column/row coordinates (pixel centres at integers). A sample is valid only
    if all four pixels around it are valid; otherwise it is NaN.
    Returns (values (h, w) float64, valid (h, w) bool).
    """
    height, width = image.shape
    out = np.full(map_x.shape, np.nan)
    ok = np.zeros(map_x.shape, dtype=np.bool_)
    for r in prange(map_x.shape[0]):
        for c in range(map_x.shape[1]):
            x = map_x[r, c]
            y = map_y[r, c]
            if not (x >= 0.0 and y >= 0.0 and x <= width - 1 and y <= height - 1):
                continue
            x0 = min(int(x), width - 2) if width > 1 else 0
            y0 = min(int(y), height - 2) if height > 1 else 0
            fx = x - x0
            fy = y - y0
            x1 = min(x0 + 1, width - 1)
            y1 = min(y0 + 1, height - 1)
            if not (valid[y0, x0] and valid[y0, x1] and valid[y1, x0] and valid[y1, x1]):
                continue
            top = image[y0, x0] * (1.0 - fx) + image[y0, x1] * fx
            bottom = image[y1, x0] * (1.0 - fx) + image[y1, x1] * fx
            out[r, c] = top * (1.0 - fy) + bottom * fy
            ok[r, c] = True
    return out, ok


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def sample_weighted(
    grid: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, wanted: np.ndarray
) -> np.ndarray:
    """Bilinear samples of ``grid`` over its finite nodes only.

    grid: (h, w) float64 with NaN or inf at unusable nodes. map_x, map_y:
    (H, W) node coordinates; wanted: (H, W) bool. The weights of the finite
    nodes among the four are renormalised, so a pixel next to the edge of
    the solved region still gets a value; NaN where no node is finite or the
    pixel is not wanted. Returns (H, W) float64.
    """
    gh, gw = grid.shape
    out = np.full(map_x.shape, np.nan)
    for r in prange(map_x.shape[0]):
        for c in range(map_x.shape[1]):
            if not wanted[r, c]:
                continue
            x = map_x[r, c]
            y = map_y[r, c]
            if not (x > -1.0 and y > -1.0 and x < gw and y < gh):
                continue
            xf = np.floor(x)
            yf = np.floor(y)
            x0 = int(xf)
            y0 = int(yf)
            fx = x - xf
            fy = y - yf
            total = 0.0
            weight = 0.0
            for dy in range(2):
                yy = y0 + dy
                if yy < 0 or yy >= gh:
                    continue
                wy = fy if dy == 1 else 1.0 - fy
                for dx in range(2):
                    xx = x0 + dx
                    if xx < 0 or xx >= gw:
                        continue
                    value = grid[yy, xx]
                    if not np.isfinite(value):
                        continue
                    w = wy * (fx if dx == 1 else 1.0 - fx)
                    total += w * value
                    weight += w
            if weight > 1e-6:
                out[r, c] = total / weight
    return out
