"""The seed paper's orthographic model: an Eikonal equation for the height.

With the light at the viewer and an orthographic camera, equation (1) of the
seed paper, I = A·cos θ + B·sin² θ with cos θ = 1/√(1 + |∇z|²), inverts per
pixel to c = cos θ (:func:`endo_sfs.reflectance.colocated_cosine`), and the
height obeys equation (2),

    |∇z| = F,  F = √(1/c² − 1),

solved by fast sweeping with the first-order Godunov update (Zhao 2005) or
the third-order WENO-Godunov update (Zhang, Zhao & Qian 2006), the latter
started from the former.

Sources. The Eikonal determines z only from given values. Without boundary
data the singular points (the brightest nodes, c ≈ 1, where the surface faces
the viewer) are sources at depth 1: with ``concave=False`` they are taken as
the nearest points (a dome, a bump), with ``concave=True`` as the farthest
(a trough, the inside of a tube). With ``boundary_depth`` given (the paper's
z = φ on ∂Ω) its finite values are the sources instead. Either way the
viscosity solution is the min over sources of source value + geodesic
distance, which is exact for surfaces whose depth has no other interior
minimum (maximum when concave).

Units: lateral coordinates are normalised image coordinates (x/z, y/z), so
depth is relative to the (unknown) working distance, which is 1 at the
singular points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from endo_sfs import kernels
from endo_sfs.errors import NoValidPixelsError, SfsInputError
from endo_sfs.reflectance import colocated_cosine, oren_nayar_coefficients

#: WENO smoothness regulariser, relative to the squared node spacing.
_WENO_EPS_REL = 0.1


@dataclass(frozen=True)
class SolveInfo:
    """How a fast-sweeping solve ended.

    iterations: full iterations (four sweeps each) in the last phase run
    (0 when the near-light first pass and repair left no node to sweep);
    change: the largest node change of the last iteration (solution units);
    converged: change ≤ tolerance; updates: node updates computed over all
    phases (the work done; a warm start needs fewer).
    """

    iterations: int
    change: float
    converged: bool
    updates: int = 0


def pad(array: np.ndarray, value: float | int) -> np.ndarray:
    """Surround a 2-D array with two layers of ``value`` (the kernels' layout)."""
    return np.pad(array, 2, mode="constant", constant_values=value)


def eikonal_speed(intensity: np.ndarray, roughness: float) -> np.ndarray:
    """Right-hand side F = √(1/c² − 1) of |∇z| = F from irradiance.

    intensity: (...) float, irradiance per unit albedo × light. Returns (...)
    float64, +inf where c = 0 (grazing), NaN where the intensity is NaN.
    """
    c = colocated_cosine(intensity, roughness)
    with np.errstate(divide="ignore"):
        return np.sqrt(np.maximum(1.0 / (c * c) - 1.0, 0.0))


def solve_eikonal(
    speed: np.ndarray,
    valid: np.ndarray,
    sources: np.ndarray,
    spacing: tuple[float, float],
    order: int = 3,
    tolerance: float = 1e-10,
    max_iterations: int = 200,
) -> tuple[np.ndarray, SolveInfo]:
    """Viscosity solution of |∇T| = F with T fixed at the sources.

    speed: (ny, nx) float F ≥ 0 per node. valid: (ny, nx) bool. sources:
    (ny, nx) float, the fixed value at source nodes, NaN elsewhere. spacing:
    (hx, hy) chart units. order: 1 (Godunov), 2 (second-order upwind) or
    3 (WENO3 Godunov).
    Returns ((ny, nx) float64 T, +inf where unreachable or invalid; info).
    """
    if order not in (1, 2, 3):
        raise SfsInputError(f"order must be 1, 2 or 3, got {order}")
    valid = np.asarray(valid, dtype=bool)
    fixed = valid & np.isfinite(sources)
    if not fixed.any():
        raise NoValidPixelsError("the Eikonal has no source node (no singular point or data)")
    t = pad(np.where(fixed, sources, np.inf).astype(np.float64), np.inf)
    f = pad(np.where(valid, speed, np.inf).astype(np.float64), np.inf)
    fixed_p = pad(fixed.astype(np.uint8), 0)
    valid_p = pad(valid.astype(np.uint8), 0)
    info = _sweep(t, f, fixed_p, valid_p, spacing, order, tolerance, max_iterations)
    return t[2:-2, 2:-2], info


def _sweep(
    t: np.ndarray,
    speed: np.ndarray,
    fixed: np.ndarray,
    valid: np.ndarray,
    spacing: tuple[float, float],
    order: int,
    tolerance: float,
    max_iterations: int,
) -> SolveInfo:
    """Run the sweeps on padded arrays; WENO starts from second order."""
    hx, hy = spacing
    eps = _WENO_EPS_REL * hx * hy
    iterations, change, updates = kernels.eikonal_sweep(
        t, speed, fixed, valid, hx, hy, min(order, 2), tolerance, max_iterations, eps
    )
    if order == 3:
        iterations, change, more = kernels.eikonal_sweep(
            t, speed, fixed, valid, hx, hy, 3, tolerance, max_iterations, eps
        )
        updates += more
    return SolveInfo(int(iterations), float(change), bool(change <= tolerance), int(updates))


def solve_orthographic(
    intensity: np.ndarray,
    valid: np.ndarray,
    spacing: tuple[float, float],
    *,
    roughness: float = 0.0,
    order: int = 3,
    singular_tolerance: float = 1e-3,
    boundary_depth: np.ndarray | None = None,
    concave: bool = False,
    tolerance: float = 1e-10,
    max_iterations: int = 200,
) -> tuple[np.ndarray, SolveInfo]:
    """Depth from an orthographic image by the seed paper's Eikonal model.

    intensity: (ny, nx) float irradiance per unit albedo × light on a uniform
    grid of normalised image coordinates with spacing (hx, hy). valid:
    (ny, nx) bool. singular_tolerance: nodes with c ≥ max(c) − tolerance are
    singular points (used only without ``boundary_depth``). boundary_depth:
    optional (ny, nx) float relative depth at the nodes where it is known
    (NaN elsewhere). concave: the singular points are depth maxima.
    Returns ((ny, nx) float64 relative depth, NaN where invalid or
    unreachable; info).
    """
    if order not in (1, 2, 3):
        raise SfsInputError(f"order must be 1, 2 or 3, got {order}")
    intensity = np.ascontiguousarray(intensity, dtype=np.float64)
    valid = np.ascontiguousarray(valid, dtype=bool)
    if boundary_depth is None:
        boundary = np.empty((0, 0))
    else:
        if boundary_depth.shape != intensity.shape:
            raise SfsInputError(
                f"boundary_depth has shape {boundary_depth.shape}, expected {intensity.shape}"
            )
        boundary = np.ascontiguousarray(boundary_depth, dtype=np.float64)
    sign = -1.0 if concave else 1.0
    coef_a, coef_b = oren_nayar_coefficients(roughness)
    t, speed, fixed, valid_p = kernels.orthographic_inputs(
        intensity, valid, coef_a, coef_b, singular_tolerance, boundary, sign
    )
    if not valid_p.any():
        raise NoValidPixelsError("no valid node to solve on")
    if not fixed.any():
        raise NoValidPixelsError("the Eikonal has no source node (no singular point or data)")
    info = _sweep(t, speed, fixed, valid_p, spacing, order, tolerance, max_iterations)
    t = t[2:-2, 2:-2]
    depth = np.where(np.isfinite(t), sign * t, np.nan)
    return depth, info
