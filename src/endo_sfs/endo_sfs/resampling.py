"""Bilinear resampling between the pixels and a solve grid, and the passes beside it.

Numba kernels, parallel over rows.
"""

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


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _finite_bilinear(grid: np.ndarray, x: float, y: float) -> float:
    """Bilinear value of ``grid`` at node position (x, y) over its finite nodes only.

    grid: (h, w) float64 with NaN or inf at unusable nodes. The weights of
    the finite nodes among the four are renormalised, so a position next to
    the edge of the solved region still gets a value; NaN where (x, y) is
    outside the grid or no node around it is finite.
    """
    gh, gw = grid.shape
    if not (x > -1.0 and y > -1.0 and x < gw and y < gh):
        return np.nan
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
        return total / weight
    return np.nan


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def sample_weighted(
    grid: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, wanted: np.ndarray
) -> np.ndarray:
    """Bilinear samples of ``grid`` over its finite nodes only (:func:`_finite_bilinear`).

    grid: (h, w) float64 with NaN or inf at unusable nodes. map_x, map_y:
    (H, W) node coordinates; wanted: (H, W) bool. NaN where no node is
    finite or the pixel is not wanted. Returns (H, W) float64.
    """
    out = np.full(map_x.shape, np.nan)
    for r in prange(map_x.shape[0]):
        for c in range(map_x.shape[1]):
            if wanted[r, c]:
                out[r, c] = _finite_bilinear(grid, map_x[r, c], map_y[r, c])
    return out


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def usable_pixels(
    image: np.ndarray,
    mask: np.ndarray,
    has_ray: np.ndarray,
    dark_level: float,
    saturation: float,
) -> tuple[np.ndarray, float]:
    """Data pixels and the brightest finite value of a frame, in one pass.

    image: (H, W) float; mask: (H, W) bool, or (0, 0) for none; has_ray:
    (H, W) bool pixels with a viewing direction. A pixel is data when it is
    finite, above ``dark_level``, below ``saturation`` (inf: no limit), in
    ``mask`` and has a ray (``endo_sfs.relative_depth.valid_pixels`` and the
    grid's ray table together). Returns ((H, W) bool, the largest finite
    value of the whole image, -inf when there is none).
    """
    height, width = image.shape
    masked = mask.size > 0
    out = np.zeros((height, width), dtype=np.bool_)
    peaks = np.full(height, -np.inf)
    for r in prange(height):
        peak = -np.inf
        for c in range(width):
            value = image[r, c]
            if not np.isfinite(value):
                continue
            if value > peak:
                peak = value
            out[r, c] = (value > dark_level and value < saturation and has_ray[r, c]
                         and (not masked or mask[r, c]))
        peaks[r] = peak
    return out, peaks.max() if height > 0 else -np.inf


@njit(cache=True, nogil=True, error_model="numpy")
def _depth_row(
    log_r: np.ndarray,
    map_x: np.ndarray,
    map_y: np.ndarray,
    wanted: np.ndarray,
    ray_z: np.ndarray,
    out: np.ndarray,
    r: int,
) -> int:
    """Row ``r`` of :func:`depth_from_log_distance`; returns its overflowed pixels.

    Most pixels lie between four finite nodes: those take the plain
    bilinear interpolation (no renormalised weights, the same value to
    rounding) and the exponential in float32, the output's precision (the
    depth within ~7e-8·|ln r| + 2.5e-7 relative of the float64 path's:
    2.4e-7 for |ln r| < 6; test_resampling.py); the others
    :func:`_finite_bilinear`.
    """
    bad = 0
    last_row, last_column = log_r.shape[0] - 1, log_r.shape[1] - 1
    for c in range(map_x.shape[1]):
        if not wanted[r, c]:
            continue
        x = map_x[r, c]
        y = map_y[r, c]
        if x >= 0.0 and y >= 0.0 and x < last_column and y < last_row:
            x0 = int(x)
            y0 = int(y)
            v00 = log_r[y0, x0]
            v01 = log_r[y0, x0 + 1]
            v10 = log_r[y0 + 1, x0]
            v11 = log_r[y0 + 1, x0 + 1]
            total = v00 + v01 + v10 + v11
            if total - total == 0.0:  # all four finite (NaN or inf leave NaN)
                fx = x - x0
                top = v00 + fx * (v01 - v00)
                bottom = v10 + fx * (v11 - v10)
                single = np.float32(top + (y - y0) * (bottom - top))
                near = np.exp(single) * np.float32(ray_z[r, c])
                out[r, c] = near
                if near == np.inf or near <= 0.0:
                    bad += 1
                continue
        value = _finite_bilinear(log_r, x, y)
        if value == value:  # not NaN
            depth = np.float32(np.exp(value) * ray_z[r, c])
            out[r, c] = depth
            if depth == np.inf or depth <= 0.0:
                bad += 1
    return bad


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def depth_from_log_distance(
    log_r: np.ndarray,
    map_x: np.ndarray,
    map_y: np.ndarray,
    wanted: np.ndarray,
    ray_z: np.ndarray,
) -> tuple[np.ndarray, int]:
    """Depth along the optical axis per pixel from ln r on the solve grid, in one pass.

    :func:`sample_weighted` of ``log_r`` (the bilinear interpolation over
    the finite nodes), then z = e^{ln r}·ω_z with ``ray_z`` (H, W) the
    pixels' ray z components. log_r: (h, w) float64, NaN unknown; map_x,
    map_y: (H, W) node coordinates; wanted: (H, W) bool. Returns ((H, W)
    float32 depth, NaN where not wanted or unknown; the number of pixels
    whose depth is infinite or not positive: an overflowed solve).
    """
    height, width = map_x.shape
    out = np.full((height, width), np.nan, dtype=np.float32)
    bad = np.zeros(height, dtype=np.int64)
    for r in prange(height):
        bad[r] = _depth_row(log_r, map_x, map_y, wanted, ray_z, out, r)
    return out, int(bad.sum())
