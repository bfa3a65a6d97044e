"""Periodic uniform cubic B-splines: smooth random curves and height fields.

The scenes need smooth random shapes (the colon's bending centreline, the
abdominal wall's undulations) that are cheap to evaluate inside a ray-casting
loop, exactly C², and reproducible from a seed. A uniform cubic B-spline over
periodic control values is all of that: 4 (1-D) or 16 (2-D) multiply-adds per
value, no transcendental functions, and its derivatives come in closed form.

Knot ``j`` sits at ``x = j·spacing``; the control values wrap around, so the
curve has period ``len(control)·spacing``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True, inline="always")
def _basis(f: float) -> tuple[float, float, float, float, float, float, float, float]:
    """Cubic B-spline weights and their derivatives at fraction ``f`` in [0, 1)."""
    g = 1.0 - f
    f2 = f * f
    f3 = f2 * f
    b0 = g * g * g / 6.0
    b1 = (3.0 * f3 - 6.0 * f2 + 4.0) / 6.0
    b2 = (-3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0) / 6.0
    b3 = f3 / 6.0
    d0 = -0.5 * g * g
    d1 = 1.5 * f2 - 2.0 * f
    d2 = -1.5 * f2 + f + 0.5
    d3 = 0.5 * f2
    return b0, b1, b2, b3, d0, d1, d2, d3


@nb.njit(cache=True, nogil=True)
def curve_value(control: np.ndarray, spacing: float, x: float) -> tuple[float, float]:
    """Value and derivative d/dx of a periodic cubic B-spline at ``x``.

    control: (M,) float64 control values; spacing: knot spacing (units of x).
    Returns (value, derivative) in units of control and control/x.
    """
    m = control.shape[0]
    u = x / spacing
    j = math.floor(u)
    f = u - j
    b0, b1, b2, b3, d0, d1, d2, d3 = _basis(f)
    i = int(j) % m
    c0 = control[(i - 1) % m]
    c1 = control[i]
    c2 = control[(i + 1) % m]
    c3 = control[(i + 2) % m]
    value = b0 * c0 + b1 * c1 + b2 * c2 + b3 * c3
    slope = (d0 * c0 + d1 * c1 + d2 * c2 + d3 * c3) / spacing
    return value, slope


@nb.njit(cache=True, nogil=True, inline="always")
def _row(control: np.ndarray, r: int, c: int, b: tuple, d: tuple) -> tuple[float, float]:
    """Weighted sums of four consecutive control values of row r (value, slope)."""
    c0 = control[r, c]
    c1 = control[r, c + 1]
    c2 = control[r, c + 2]
    c3 = control[r, c + 3]
    return (
        b[0] * c0 + b[1] * c1 + b[2] * c2 + b[3] * c3,
        d[0] * c0 + d[1] * c1 + d[2] * c2 + d[3] * c3,
    )


@nb.njit(cache=True, nogil=True, inline="always")
def surface_value(
    control: np.ndarray, inv_spacing: float, x: float, y: float
) -> tuple[float, float, float]:
    """Value and gradient of a periodic bicubic B-spline height field at (x, y).

    control: (My + 3, Mx + 3) wrapped control heights from :func:`wrap_grid`
    (row index along y); inv_spacing: 1 / knot spacing (both axes).
    Returns (h, dh/dx, dh/dy).
    """
    my = control.shape[0] - 3
    mx = control.shape[1] - 3
    ux = x * inv_spacing
    uy = y * inv_spacing
    ux -= mx * math.floor(ux * (1.0 / mx))
    uy -= my * math.floor(uy * (1.0 / my))
    jx = math.floor(ux)
    jy = math.floor(uy)
    bx0, bx1, bx2, bx3, dx0, dx1, dx2, dx3 = _basis(ux - jx)
    by0, by1, by2, by3, dy0, dy1, dy2, dy3 = _basis(uy - jy)
    ix = min(int(jx), mx - 1)
    iy = min(int(jy), my - 1)
    bx = (bx0, bx1, bx2, bx3)
    dx = (dx0, dx1, dx2, dx3)
    v0, s0 = _row(control, iy, ix, bx, dx)
    v1, s1 = _row(control, iy + 1, ix, bx, dx)
    v2, s2 = _row(control, iy + 2, ix, bx, dx)
    v3, s3 = _row(control, iy + 3, ix, bx, dx)
    value = by0 * v0 + by1 * v1 + by2 * v2 + by3 * v3
    grad_x = by0 * s0 + by1 * s1 + by2 * s2 + by3 * s3
    grad_y = dy0 * v0 + dy1 * v1 + dy2 * v2 + dy3 * v3
    return value, grad_x * inv_spacing, grad_y * inv_spacing


@nb.njit(cache=True, nogil=True, inline="always")
def curve_pair(
    control: np.ndarray, inv_spacing: float, x: float
) -> tuple[float, float, float, float]:
    """Values and derivatives of two periodic cubic B-splines sharing knots, at ``x``.

    control: (M + 3, 2) float64 wrapped control values from :func:`wrap_pair`;
    inv_spacing: 1 / knot spacing (a product is cheaper than a division in
    the ray caster's inner loop). Returns (a, da/dx, b, db/dx).
    """
    m = control.shape[0] - 3
    u = x * inv_spacing
    # Wrap into [0, m) in floating point: an integer modulo is a slow
    # hardware division, and this sits in the ray caster's inner loop.
    u -= m * math.floor(u * (1.0 / m))
    j = math.floor(u)
    b0, b1, b2, b3, d0, d1, d2, d3 = _basis(u - j)
    i = min(int(j), m - 1)
    a = (
        b0 * control[i, 0]
        + b1 * control[i + 1, 0]
        + b2 * control[i + 2, 0]
        + b3 * control[i + 3, 0]
    )
    da = (
        d0 * control[i, 0]
        + d1 * control[i + 1, 0]
        + d2 * control[i + 2, 0]
        + d3 * control[i + 3, 0]
    )
    b = (
        b0 * control[i, 1]
        + b1 * control[i + 1, 1]
        + b2 * control[i + 2, 1]
        + b3 * control[i + 3, 1]
    )
    db = (
        d0 * control[i, 1]
        + d1 * control[i + 1, 1]
        + d2 * control[i + 2, 1]
        + d3 * control[i + 3, 1]
    )
    return a, da * inv_spacing, b, db * inv_spacing


def wrap_pair(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Pack two (M,) periodic control vectors as the (M + 3, 2) array :func:`curve_pair` reads.

    Row k holds control index (k − 1) mod M, so a knot interval needs no
    modulo beyond the one that finds it.
    """
    m = first.shape[0]
    index = (np.arange(m + 3) - 1) % m
    return np.ascontiguousarray(np.stack([first[index], second[index]], axis=-1), dtype=np.float64)


def wrap_grid(control: np.ndarray) -> np.ndarray:
    """Pad a periodic (My, Mx) control grid to the (My + 3, Mx + 3) one :func:`surface_value` reads.

    Row/column k holds control index (k − 1) mod M.
    """
    my, mx = control.shape
    rows = (np.arange(my + 3) - 1) % my
    cols = (np.arange(mx + 3) - 1) % mx
    return np.ascontiguousarray(control[np.ix_(rows, cols)], dtype=np.float64)


def random_control(
    rng: np.random.Generator, shape: int | tuple[int, ...], amplitude: float
) -> np.ndarray:
    """Zero-mean random control values scaled so that the largest is ``amplitude``.

    Returns float64 control values of ``shape``; ``amplitude`` in the units the
    spline should have (metres for the scenes).
    """
    values = rng.standard_normal(shape)
    values -= values.mean()
    peak = float(np.max(np.abs(values)))
    return np.ascontiguousarray(values * (amplitude / peak if peak > 0.0 else 0.0))
