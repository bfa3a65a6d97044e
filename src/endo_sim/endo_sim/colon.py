"""Colon phantom: a bending tube with haustral folds, ray cast exactly.

Geometry (world frame, metres; the lumen runs along +z)
--------------------------------------------------------
The lumen is the set of points whose distance ρ from a smooth centreline
``c(z) = (cx(z), cy(z), z)`` (measured in the z = const plane) is below the wall
radius ``r(z, φ)``; the wall is the zero set of the implicit function

    F(x, y, z) = r(z, φ) − ρ,      F > 0 inside the lumen,

    r(z, φ) = R0·(1 + a·cos 3φ) − H(φ)·fold(z − w·cos(φ − φw))
    H(φ)    = h·(1 − m·(1 + cos 3φ)/2)
    fold(s) = (1 − q²)⁴ for |q| < 1, q = (s mod P, centred) / half_width, else 0.

``cos 3φ`` gives the rounded-triangular cross-section of the three taeniae
coli; the folds (haustra) are ridges of height ``h`` every ``P`` metres, lower
at the taeniae (``m``) and slightly oblique (``w``). The centreline is a
periodic cubic B-spline with random control points (seeded), so the lumen
bends gently and hides the far folds. Every term is a polynomial except one
square root and one division, which keeps the ray caster fast.

Ray casting
-----------
Each ray solves F(o + t·d) = 0 for its first root t > 0. A sparse grid (every
``COARSE_STEP``-th pixel in x and y) is found robustly by sphere tracing with a
Lipschitz bound of F (measured on the surface at construction) and
over-relaxation (Keinert et al. 2014), then polished by Newton's method. Every
other pixel starts Newton from the bilinear interpolation of its four grid
neighbours when they agree within ``SMOOTH_SPREAD``; where they do not (a fold
silhouette) or Newton leaves the neighbours' range, the pixel is sphere traced
on its own. Newton stops when the step is below 1e-11 m, so depth is exact to
far better than a micrometre. A ridge thinner than the grid step lying wholly
between grid rays could be missed; with the default geometry ridges are many
pixels wide.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from endo_sim.bands import run_in_bands
from endo_sim.bspline import curve_pair, random_control, wrap_pair
from endo_sim.errors import SimulationParameterError
from endo_sim.surface import SurfaceHits
from endo_sim.surface import no_hit as _no_hit
from endo_sim.texture import Texture

#: Grid steps (pixels, powers of two) of the sparse levels: the coarsest is
#: sphere traced, each finer one starts Newton from the level above.
LEVEL_STEPS = (8, 4)
#: Largest relative spread of the four neighbour depths that still counts as
#: one smooth surface (interpolate, then Newton).
SMOOTH_SPREAD = 0.15
#: Newton stops when the error left after its last step, bounded by
#: step²·max|F''|/(2|F'|) (quadratic convergence), is below this (metres).
ACCURACY_M = 1e-7
#: ... and only once steps are below this (metres), where the quadratic
#: model of F along the ray holds (folds are millimetres wide).
NEWTON_LOCAL_M = 1e-4
#: Sphere tracing hands over to Newton below this gap (metres).
HANDOVER_GAP_M = 3e-4
#: Smallest sphere-tracing step (metres), so grazing rays terminate.
MIN_STEP_M = 1e-4
#: Where a pixel's neighbours disagree, its own trace starts at this fraction
#: of the nearest neighbour depth (anything nearer would be a ridge thinner
#: than the grid step).
RESTART_FRACTION = 0.85

# Layout of the packed parameter vector passed to the kernels.
(
    _R0,
    _TAENIA,
    _FOLD_H,
    _FOLD_DROP,
    _PERIOD,
    _INV_PERIOD,
    _INV_HALF_WIDTH,
    _TILT,
    _COS_W,
    _SIN_W,
    _INV_BEND_SPACING,
    _LIPSCHITZ,
    _LIPSCHITZ_OPEN,
    _T_MAX,
    _HALF_HESSIAN,
) = range(15)
_N_PARAMETERS = 15


@dataclass(frozen=True)
class ColonGeometry:
    """Shape parameters of the colon phantom (metres, radians).

    Defaults follow the adult transverse colon: 44 mm lumen diameter,
    semilunar folds 5 mm high every 24 mm, the 3-fold taeniae modulation
    and a centreline that wanders ±6 mm over 4 cm.
    """

    radius_m: float = 0.022
    taenia_modulation: float = 0.06
    fold_height_m: float = 0.005
    fold_spacing_m: float = 0.024
    fold_half_width_m: float = 0.0065
    fold_drop_at_taenia: float = 0.5
    fold_tilt_m: float = 0.002
    fold_tilt_azimuth_rad: float = 0.7
    bend_amplitude_m: float = 0.006
    bend_knot_spacing_m: float = 0.04
    bend_knots: int = 32

    def __post_init__(self) -> None:
        if not 0.005 <= self.radius_m <= 0.1:
            raise SimulationParameterError(f"colon radius {self.radius_m} m is outside 5..100 mm")
        if not 0.0 <= self.taenia_modulation < 0.3:
            raise SimulationParameterError("taenia_modulation must be in [0, 0.3)")
        if not 0.0 <= self.fold_height_m < 0.5 * self.radius_m:
            raise SimulationParameterError("fold height must be in [0, radius/2)")
        if not 0.0 < self.fold_half_width_m <= 0.5 * self.fold_spacing_m:
            raise SimulationParameterError("fold half width must be in (0, spacing/2]")
        if not 0.0 <= self.fold_drop_at_taenia <= 1.0:
            raise SimulationParameterError("fold_drop_at_taenia must be in [0, 1]")
        if not 0.0 <= self.bend_amplitude_m < 0.3 * self.radius_m:
            raise SimulationParameterError("bend amplitude must be in [0, 0.3·radius)")
        if self.bend_knots < 4 or self.bend_knot_spacing_m <= 0.0:
            raise SimulationParameterError("the centreline needs >= 4 knots and a positive spacing")

    @property
    def min_radius_m(self) -> float:
        """Smallest wall radius (at a fold crest between taeniae), metres."""
        return self.radius_m * (1.0 - self.taenia_modulation) - self.fold_height_m


@nb.njit(cache=True, nogil=True, inline="always")
def colon_field(
    x: float, y: float, z: float, prm: np.ndarray, bend: np.ndarray
) -> tuple[float, float, float, float, float]:
    """F(x, y, z) = r − ρ (metres, > 0 inside), its gradient, and F without folds.

    prm: packed parameters (:meth:`ColonScene.parameters`); bend: (M + 3, 2)
    wrapped centreline control points (:func:`~endo_sim.bspline.wrap_pair`).
    Returns (F, dF/dx, dF/dy, dF/dz, F_open) where F_open = F with the folds
    removed (F ≥ F_open − fold height, which gives the tracer a longer safe step).
    """
    xc, xcp, yc, ycp = curve_pair(bend, prm[_INV_BEND_SPACING], z)
    dx = x - xc
    dy = y - yc
    rho = math.sqrt(dx * dx + dy * dy) + 1e-300
    inv = 1.0 / rho
    c1 = dx * inv
    s1 = dy * inv
    c3 = 4.0 * c1 * c1 * c1 - 3.0 * c1
    s3 = 3.0 * s1 - 4.0 * s1 * s1 * s1
    r0 = prm[_R0]
    h0 = prm[_FOLD_H]
    drop = prm[_FOLD_DROP]
    height = h0 * (1.0 - drop * 0.5 * (1.0 + c3))
    height_phi = h0 * drop * 1.5 * s3
    cos_pw = c1 * prm[_COS_W] + s1 * prm[_SIN_W]
    sin_pw = s1 * prm[_COS_W] - c1 * prm[_SIN_W]
    tilt = prm[_TILT]
    s = z - tilt * cos_pw
    centred = s - prm[_PERIOD] * math.floor(s * prm[_INV_PERIOD] + 0.5)
    q = centred * prm[_INV_HALF_WIDTH]
    fold = 0.0
    fold_slope = 0.0
    if q * q < 1.0:
        base = 1.0 - q * q
        base3 = base * base * base
        fold = base3 * base
        fold_slope = -8.0 * base3 * q * prm[_INV_HALF_WIDTH]
    r_open = r0 * (1.0 + prm[_TAENIA] * c3)
    r = r_open - height * fold
    r_phi = -3.0 * r0 * prm[_TAENIA] * s3 - height_phi * fold - height * fold_slope * tilt * sin_pw
    r_z = -height * fold_slope
    grad_x = -r_phi * s1 * inv - c1
    grad_y = r_phi * c1 * inv - s1
    grad_z = r_z + r_phi * (s1 * xcp - c1 * ycp) * inv + (c1 * xcp + s1 * ycp)
    return r - rho, grad_x, grad_y, grad_z, r_open - rho


@nb.njit(cache=True, nogil=True, inline="always")
def _fast_atan2(y: float, x: float) -> float:
    """atan2 to within 1e-5 rad (odd minimax polynomial after octant reduction).

    Only used for the texture coordinate, where 1e-5 rad is 0.2 µm of arc.
    """
    ax = abs(x)
    ay = abs(y)
    if ax == 0.0 and ay == 0.0:
        return 0.0
    swap = ay > ax
    a = ax / ay if swap else ay / ax
    a2 = a * a
    r = a * (
        0.99997726
        + a2
        * (
            -0.33262347
            + a2 * (0.19354346 + a2 * (-0.11643287 + a2 * (0.05265332 - a2 * 0.01172120)))
        )
    )
    if swap:
        r = 0.5 * math.pi - r
    if x < 0.0:
        r = math.pi - r
    return -r if y < 0.0 else r


#: The same function compiled without forced inlining, for cold helpers
#: (bounds at construction, bisection) whose compile time would otherwise grow.
_colon_field_outlined = nb.njit(cache=True, nogil=True)(colon_field.py_func)


@nb.njit(cache=True, nogil=True, inline="always")
def colon_arc(x: float, y: float, z: float, prm: np.ndarray, bend: np.ndarray) -> float:
    """Arc length φ·R0 (metres) of a point's azimuth around the centreline."""
    xc, _xcp, yc, _ycp = curve_pair(bend, prm[_INV_BEND_SPACING], z)
    return _fast_atan2(y - yc, x - xc) * prm[_R0]


@nb.njit(cache=True, nogil=True, inline="always")
def _safe_radius(f: float, f_open: float, prm: np.ndarray) -> float:
    """Radius of a ball around the point that the wall does not enter (metres)."""
    return max(f / prm[_LIPSCHITZ], (f_open - prm[_FOLD_H]) / prm[_LIPSCHITZ_OPEN])


@nb.njit(cache=True, nogil=True, inline="always")
def _newton(
    o: np.ndarray, d: tuple[float, float, float], t: float, prm: np.ndarray, bend: np.ndarray
) -> tuple[float, float, float, float]:
    """Newton's method on F along the ray o + t·d from ``t``.

    Returns (t, ∇F at the last evaluation); t is NaN if Newton does not converge.
    """
    dx, dy, dz = d
    gx = gy = gz = 0.0
    for _ in range(12):
        f, gx, gy, gz, _f_open = colon_field(o[0] + t * dx, o[1] + t * dy, o[2] + t * dz, prm, bend)
        slope = gx * dx + gy * dy + gz * dz
        if slope > -1e-3:
            break
        step = -f / slope
        t += step
        if abs(step) < NEWTON_LOCAL_M and step * step * prm[_HALF_HESSIAN] < -ACCURACY_M * slope:
            return t, gx, gy, gz
    return math.nan, gx, gy, gz


#: Newton compiled once (no forced inlining) for the rarely taken paths.
_newton_outlined = nb.njit(cache=True, nogil=True)(_newton.py_func)


@nb.njit(cache=True, nogil=True)
def _bracketed(
    o: np.ndarray,
    d: tuple[float, float, float],
    lo: float,
    hi: float,
    prm: np.ndarray,
    bend: np.ndarray,
) -> tuple[float, float, float, float]:
    """Root of F in [lo, hi] (F(lo) > 0 ≥ F(hi)): Newton safeguarded by bisection."""
    dx, dy, dz = d
    t = 0.5 * (lo + hi)
    gx = gy = gz = 0.0
    for _ in range(100):
        f, gx, gy, gz, _f_open = _colon_field_outlined(
            o[0] + t * dx, o[1] + t * dy, o[2] + t * dz, prm, bend
        )
        if f > 0.0:
            lo = t
        else:
            hi = t
        slope = gx * dx + gy * dy + gz * dz
        candidate = t - f / slope if slope < 0.0 else 0.5 * (lo + hi)
        if not lo < candidate < hi:
            candidate = 0.5 * (lo + hi)
        if abs(candidate - t) < ACCURACY_M:
            return candidate, gx, gy, gz
        t = candidate
    return t, gx, gy, gz


@nb.njit(cache=True, nogil=True)
def _march(
    o: np.ndarray,
    d: tuple[float, float, float],
    t_start: float,
    prm: np.ndarray,
    bend: np.ndarray,
) -> tuple[float, float, float, float]:
    """First root of F beyond ``t_start`` by over-relaxed sphere tracing, then Newton.

    Returns (t, ∇F at t); t is NaN when the ray travels prm[_T_MAX] without a
    hit. If ``t_start`` turns out to be inside the wall, tracing restarts at 0.
    (F is evaluated at one place in the loop: each inlined copy of the field
    costs a second of compilation.)
    """
    dx, dy, dz = d
    omega = 1.6
    t_max = prm[_T_MAX]
    t = t_start
    t_safe = -1.0  # no safe point yet
    radius = 0.0
    step = 0.0
    gx = gy = gz = 0.0
    for _ in range(4000):
        f, hx, hy, hz, f_open = colon_field(o[0] + t * dx, o[1] + t * dy, o[2] + t * dz, prm, bend)
        new_radius = _safe_radius(f, f_open, prm)
        if t_safe < 0.0:
            if f <= 0.0:
                if t > 0.0:
                    t = 0.0
                    continue
                return math.nan, hx, hy, hz
        elif omega > 1.0 and step > radius and (f <= 0.0 or new_radius + radius < step):
            # The over-relaxed step left the ball known to be empty: redo it
            # as a plain step and stop over-relaxing.
            omega = 1.0
            step = max(radius, MIN_STEP_M)
            t = t_safe + step
            continue
        elif f <= 0.0:
            return _bracketed(o, d, t_safe, t, prm, bend)
        t_safe = t
        radius = new_radius
        gx, gy, gz = hx, hy, hz
        if f < HANDOVER_GAP_M and gx * dx + gy * dy + gz * dz < -0.2:
            tn, nx, ny, nz = _newton_outlined(o, d, t_safe, prm, bend)
            if tn >= t_safe:
                return tn, nx, ny, nz
        step = max(omega * radius, MIN_STEP_M)
        t = t_safe + step
        if t > t_max:
            return math.nan, gx, gy, gz
    return math.nan, gx, gy, gz


@nb.njit(cache=True, nogil=True, inline="always")
def _world_ray(rotation: np.ndarray, r: np.ndarray) -> tuple[float, float, float]:
    """Rotate a camera-frame ray into the world frame."""
    return (
        rotation[0, 0] * r[0] + rotation[0, 1] * r[1] + rotation[0, 2] * r[2],
        rotation[1, 0] * r[0] + rotation[1, 1] * r[1] + rotation[1, 2] * r[2],
        rotation[2, 0] * r[0] + rotation[2, 1] * r[1] + rotation[2, 2] * r[2],
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _trace_from_grid(
    o: np.ndarray,
    d: tuple[float, float, float],
    i: int,
    j: int,
    grid: np.ndarray,
    step: int,
    prm: np.ndarray,
    bend: np.ndarray,
) -> tuple[float, float, float, float]:
    """Trace pixel (i, j) starting from the depths of a sparser grid (step pixels).

    Smooth neighbourhood: Newton from the bilinear interpolation. Otherwise
    (a silhouette) Newton from each neighbour depth, nearest first, keeping the
    first root that lands near the depth it started from. All neighbours
    without a hit: no hit. Anything else: sphere tracing.
    """
    # Steps are powers of two, so these float products are exact (and avoid
    # slow integer divisions in the per-pixel loop).
    inv_step = 1.0 / step
    ci = int(i * inv_step)
    cj = int(j * inv_step)
    if ci + 1 >= grid.shape[0] or cj + 1 >= grid.shape[1]:
        return _march(o, d, 0.0, prm, bend)
    fi = (i - ci * step) * inv_step
    fj = (j - cj * step) * inv_step
    t00 = grid[ci, cj]
    t01 = grid[ci, cj + 1]
    t10 = grid[ci + 1, cj]
    t11 = grid[ci + 1, cj + 1]
    # NaN (no hit) as +inf: sorts last.
    a = t00 if t00 == t00 else math.inf
    b = t01 if t01 == t01 else math.inf
    c = t10 if t10 == t10 else math.inf
    e = t11 if t11 == t11 else math.inf
    lo = min(min(a, b), min(c, e))
    hi = max(max(a, b), max(c, e))
    if lo == math.inf:
        return math.nan, 0.0, 0.0, 0.0
    smooth = hi - lo <= SMOOTH_SPREAD * lo
    if smooth:
        # One start: the bilinear interpolation, accepted within the neighbours' range.
        a = (t00 * (1.0 - fj) + t01 * fj) * (1.0 - fi) + (t10 * (1.0 - fj) + t11 * fj) * fi
        b = c = e = math.inf
    else:
        # Silhouette: the neighbour depths in increasing order (sorting network).
        a, b = min(a, b), max(a, b)
        c, e = min(c, e), max(c, e)
        a, c = min(a, c), max(a, c)
        b, e = min(b, e), max(b, e)
        b, c = min(b, c), max(b, c)
    tried = -1.0
    for k in range(4):
        start = a if k == 0 else (b if k == 1 else (c if k == 2 else e))
        if start == math.inf:
            break
        if start <= tried * (1.0 + SMOOTH_SPREAD):
            continue
        tried = start
        t, gx, gy, gz = _newton(o, d, start, prm, bend)
        low = lo if smooth else start
        high = hi if smooth else start
        if t >= low * (1.0 - SMOOTH_SPREAD) and t <= high * (1.0 + SMOOTH_SPREAD):
            return t, gx, gy, gz
    return _march(o, d, RESTART_FRACTION * lo, prm, bend)


@nb.njit(cache=True, nogil=True)
def _trace_grid(
    origin: np.ndarray,
    rotation: np.ndarray,
    rays: np.ndarray,
    needed: np.ndarray,
    step: int,
    parent: np.ndarray,
    parent_step: int,
    prm: np.ndarray,
    bend: np.ndarray,
    out: np.ndarray,
    row_start: int,
    row_stop: int,
) -> None:
    """Depths of the grid of every ``step``-th pixel where ``needed``, into out (NaN elsewhere).

    parent: the grid of the level above (every ``parent_step``-th pixel) or an
    empty (0, 0) array for the coarsest level, which is sphere traced.
    Grid rows [row_start, row_stop) only.
    """
    cols = needed.shape[1]
    for gi in range(row_start, row_stop):
        for gj in range(cols):
            if not needed[gi, gj]:
                out[gi, gj] = math.nan
                continue
            d = _world_ray(rotation, rays[gi * step, gj * step])
            if parent.shape[0] == 0:
                t = _march(origin, d, 0.0, prm, bend)[0]
            else:
                t = _trace_from_grid(
                    origin, d, gi * step, gj * step, parent, parent_step, prm, bend
                )[0]
            out[gi, gj] = t


@nb.njit(cache=True, nogil=True)
def _trace_pixels(
    origin: np.ndarray,
    rotation: np.ndarray,
    rays: np.ndarray,
    mask: np.ndarray,
    grid: np.ndarray,
    grid_step: int,
    prm: np.ndarray,
    bend: np.ndarray,
    out_distance: np.ndarray,
    out_normal: np.ndarray,
    out_uv: np.ndarray,
    row_start: int,
    row_stop: int,
) -> None:
    """Pixels of ``mask`` in rows [row_start, row_stop) from the finest grid.

    Writes distance, camera-frame normal and uv (see :meth:`ColonScene.trace_geometry`).
    """
    width = mask.shape[1]
    for i in range(row_start, row_stop):
        for j in range(width):
            if not mask[i, j]:
                _no_hit(out_distance, out_normal, out_uv, i, j)
                continue
            d = _world_ray(rotation, rays[i, j])
            t, gx, gy, gz = _trace_from_grid(origin, d, i, j, grid, grid_step, prm, bend)
            if t != t:
                _no_hit(out_distance, out_normal, out_uv, i, j)
                continue
            out_distance[i, j] = t
            norm = math.sqrt(gx * gx + gy * gy + gz * gz)
            gx /= norm
            gy /= norm
            gz /= norm
            # Camera-frame normal R^T n; ∇F points into the lumen, i.e. at the camera.
            out_normal[i, j, 0] = rotation[0, 0] * gx + rotation[1, 0] * gy + rotation[2, 0] * gz
            out_normal[i, j, 1] = rotation[0, 1] * gx + rotation[1, 1] * gy + rotation[2, 1] * gz
            out_normal[i, j, 2] = rotation[0, 2] * gx + rotation[1, 2] * gy + rotation[2, 2] * gz
            x = origin[0] + t * d[0]
            y = origin[1] + t * d[1]
            z = origin[2] + t * d[2]
            out_uv[i, j, 0] = z
            out_uv[i, j, 1] = colon_arc(x, y, z, prm, bend)


@nb.njit(cache=True, nogil=True)
def _max_derivatives(
    prm: np.ndarray, bend: np.ndarray, z: np.ndarray, phi: np.ndarray
) -> tuple[float, float, float]:
    """Largest |∇F|, |∇F_open| and Frobenius norm of ∇²F over points sampled near the wall."""
    largest = 0.0
    largest_open = 0.0
    largest_hessian = 0.0
    eps = 1e-7
    for k in range(z.shape[0]):
        xc, _xcp, yc, _ycp = curve_pair(bend, prm[_INV_BEND_SPACING], z[k])
        for m in range(phi.shape[0]):
            for scale in (0.3, 0.6, 0.8, 0.9, 1.0, 1.1):
                x = xc + scale * prm[_R0] * math.cos(phi[m])
                y = yc + scale * prm[_R0] * math.sin(phi[m])
                _f, gx, gy, gz, _f_open = _colon_field_outlined(x, y, z[k], prm, bend)
                largest = max(largest, math.sqrt(gx * gx + gy * gy + gz * gz))
                # F_open has no closed-form gradient here; central differences.
                ax = (
                    _colon_field_outlined(x + eps, y, z[k], prm, bend)[4]
                    - _colon_field_outlined(x - eps, y, z[k], prm, bend)[4]
                )
                ay = (
                    _colon_field_outlined(x, y + eps, z[k], prm, bend)[4]
                    - _colon_field_outlined(x, y - eps, z[k], prm, bend)[4]
                )
                az = (
                    _colon_field_outlined(x, y, z[k] + eps, prm, bend)[4]
                    - _colon_field_outlined(x, y, z[k] - eps, prm, bend)[4]
                )
                largest_open = max(largest_open, math.sqrt(ax * ax + ay * ay + az * az) / (2 * eps))
                hessian = 0.0
                for axis in range(3):
                    ex = eps if axis == 0 else 0.0
                    ey = eps if axis == 1 else 0.0
                    ez = eps if axis == 2 else 0.0
                    _a, px, py, pz, _b = _colon_field_outlined(x + ex, y + ey, z[k] + ez, prm, bend)
                    _c, mx, my, mz, _d = _colon_field_outlined(x - ex, y - ey, z[k] - ez, prm, bend)
                    hessian += ((px - mx) ** 2 + (py - my) ** 2 + (pz - mz) ** 2) / (4 * eps * eps)
                largest_hessian = max(largest_hessian, math.sqrt(hessian))
    return largest, largest_open, largest_hessian


@nb.njit(cache=True, nogil=True)
def _centreline(prm: np.ndarray, bend: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """Centreline x, y and their z-derivatives at each z (N,) into out (N, 4)."""
    for k in range(z.shape[0]):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = curve_pair(bend, prm[_INV_BEND_SPACING], z[k])


@nb.njit(cache=True, nogil=True)
def _field_at(prm: np.ndarray, bend: np.ndarray, points: np.ndarray, out: np.ndarray) -> None:
    """F at each point (N, 3) into out (N,)."""
    for k in range(points.shape[0]):
        out[k] = _colon_field_outlined(points[k, 0], points[k, 1], points[k, 2], prm, bend)[0]


class ColonScene:
    """The colon phantom: :class:`ColonGeometry` plus a tissue texture.

    The texture is indexed by (z, φ·R0) (metres): its period along the second
    axis must be the circumference 2π·R0 so that it closes around the lumen.
    Rays that travel ``max_distance_m`` without meeting the wall return no
    light (the far lumen is dark in a real colonoscope too).
    """

    name = "colon"
    #: Wet mucosa: full specular highlights.
    specular_weight = 1.0

    def __init__(
        self, geometry: ColonGeometry, texture: Texture, seed: int, max_distance_m: float = 0.3
    ) -> None:
        circumference = 2.0 * math.pi * geometry.radius_m
        if abs(texture.period_m[1] - circumference) > 1e-9:
            raise SimulationParameterError(
                f"colon texture period along the azimuth must be 2π·R0 = {circumference:.6f} m"
            )
        if max_distance_m <= 0.0:
            raise SimulationParameterError("max_distance_m must be positive")
        self.geometry = geometry
        self.texture = texture
        self.max_distance_m = float(max_distance_m)
        rng = np.random.default_rng([int(seed), 0xC0105])
        bend_x = random_control(rng, geometry.bend_knots, geometry.bend_amplitude_m)
        bend_y = random_control(rng, geometry.bend_knots, geometry.bend_amplitude_m)
        self.bend = wrap_pair(bend_x, bend_y)
        g = geometry
        prm = np.zeros(_N_PARAMETERS)
        prm[_R0] = g.radius_m
        prm[_TAENIA] = g.taenia_modulation
        prm[_FOLD_H] = g.fold_height_m
        prm[_FOLD_DROP] = g.fold_drop_at_taenia
        prm[_PERIOD] = g.fold_spacing_m
        prm[_INV_PERIOD] = 1.0 / g.fold_spacing_m
        prm[_INV_HALF_WIDTH] = 1.0 / g.fold_half_width_m
        prm[_TILT] = g.fold_tilt_m
        prm[_COS_W] = math.cos(g.fold_tilt_azimuth_rad)
        prm[_SIN_W] = math.sin(g.fold_tilt_azimuth_rad)
        prm[_INV_BEND_SPACING] = 1.0 / g.bend_knot_spacing_m
        prm[_T_MAX] = self.max_distance_m
        z = np.linspace(0.0, self.length_m, 40 * g.bend_knots + 1)
        phi = np.linspace(-math.pi, math.pi, 73)
        largest, largest_open, largest_hessian = _max_derivatives(prm, self.bend, z, phi)
        # Margins over the sampled maxima: the bounds only have to hold near
        # the wall, where the samples are dense.
        prm[_LIPSCHITZ] = 1.1 * largest
        prm[_LIPSCHITZ_OPEN] = 1.1 * largest_open
        prm[_HALF_HESSIAN] = 0.5 * 1.5 * largest_hessian
        #: Packed parameter vector read by the numba kernels.
        self.parameters = prm
        self._needed_cache: tuple[np.ndarray, list[np.ndarray]] | None = None

    @property
    def length_m(self) -> float:
        """Period of the centreline along z (the phantom repeats after it), metres."""
        return self.geometry.bend_knots * self.geometry.bend_knot_spacing_m

    def centreline(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centreline points and unit tangents at axial positions ``z`` (N,) metres.

        Returns ((N, 3) points, (N, 3) unit tangents), world frame.
        """
        z = np.ascontiguousarray(np.asarray(z, dtype=np.float64).ravel())
        values = np.empty((z.shape[0], 4))
        _centreline(self.parameters, self.bend, z, values)
        points = np.stack([values[:, 0], values[:, 2], z], axis=-1)
        tangents = np.stack([values[:, 1], values[:, 3], np.ones_like(z)], axis=-1)
        tangents /= np.linalg.norm(tangents, axis=-1, keepdims=True)
        return points, tangents

    def field(self, points: np.ndarray) -> np.ndarray:
        """F at world points (N, 3) metres: the radial gap to the wall (> 0 inside), (N,)."""
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        out = np.empty(points.shape[0])
        _field_at(self.parameters, self.bend, points, out)
        return out

    def _needed_grids(self, mask: np.ndarray) -> list[np.ndarray]:
        """Per level, the grid points within one cell of a masked pixel (cached per mask)."""
        cached = self._needed_cache
        if cached is not None and cached[0] is mask:
            return cached[1]
        mask_u8 = mask.astype(np.uint8)
        grids = []
        for step in LEVEL_STEPS:
            near = cv2.dilate(mask_u8, np.ones((2 * step + 1, 2 * step + 1), np.uint8))
            grids.append(np.ascontiguousarray(near[::step, ::step] > 0))
        self._needed_cache = (mask, grids)
        return grids

    def trace_geometry(
        self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ray cast the wall.

        pose: (4, 4) T_world_camera; rays: (H, W, 3) unit rays (camera frame);
        mask: (H, W) bool. Returns distance (H, W) metres (NaN: masked or no
        hit), camera-frame unit normal (H, W, 3), texture uv (H, W, 2) metres.
        """
        height, width = mask.shape
        origin = np.ascontiguousarray(pose[:3, 3], dtype=np.float64)
        rotation = np.ascontiguousarray(pose[:3, :3], dtype=np.float64)
        grid: np.ndarray = np.zeros((0, 0))
        grid_step = 0
        for step, needed in zip(LEVEL_STEPS, self._needed_grids(mask), strict=True):
            level = np.empty(needed.shape)
            run_in_bands(
                _trace_grid, needed.shape[0], origin, rotation, rays, needed, step, grid,
                grid_step, self.parameters, self.bend, level,
            )  # fmt: skip
            grid = level
            grid_step = step
        distance = np.empty((height, width))
        normal = np.empty((height, width, 3))
        uv = np.empty((height, width, 2))
        run_in_bands(
            _trace_pixels,
            height,
            origin,
            rotation,
            rays,
            mask,
            grid,
            grid_step,
            self.parameters,
            self.bend,
            distance,
            normal,
            uv,
        )
        return distance, normal, uv

    def trace(self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray) -> SurfaceHits:
        """First hits of the unit rays (H, W, 3, camera frame) from the camera at pose (4, 4)."""
        distance, normal, uv = self.trace_geometry(pose, rays, mask)
        albedo = self.texture.sample(uv, np.isfinite(distance))
        return SurfaceHits(distance, normal, albedo, self.specular_weight)
