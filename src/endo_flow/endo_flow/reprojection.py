"""The scale observed by a scale-only reprojection fit of a frame's tracks over their views.

The triangulation route (:func:`endo_flow.triangulation.triangulate`, then
ln(z / d_rel) per track) needs a parallax gate: a track whose rays barely
diverge triangulates to noise. A gate on the rays' own angle selects the
tracks whose noise widened it, which triangulate too near, so ln s is biased
low while the baselines are short (docs/flow.md). This fit needs no gate.
Each track's point in a reference view r is where SFS puts it, scaled by the
one unknown s,

    X_r(s) = c_r + s · d_rel,r / (d_r · a_r) · d_r

(c_r the view's centre, d_r the track's unit ray, a_r the optical axis:
depth_relative is depth along z), and it is projected with the known poses
into every other view k of the track. The residual is the tangent-plane
error of view k's observed ray d_k,

    e_rk = (v − (v·d_k) d_k) / (v·d_k),  v = X_r(s) − c_k,

a 2-vector in radians (1 px ≈ 1/f). One parameter, ln s, minimises the
robust (Cauchy) sum Σ w_i ρ(|e_rk|) over every track i, reference r and
other view k of the window at once, by iteratively reweighted Gauss–Newton
from the triangulation's median. A view pair with little parallax moves its
projection little as s changes: its Jacobian is small and it has little
leverage, naturally (no selection by the track's own error), and since every
view's pose enters, the views' independent pose errors average down.

The observation's variance is the track-clustered sandwich (every residual
of a track shares its LK and SFS errors) of the Gauss–Newton step; the
caller adds the pose error that every track of the frame shares.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from endo_flow.keyframes import TrackViews

#: Cauchy constant in robust standard deviations of a residual component (95 % efficiency).
CAUCHY_C = 2.385
#: Median of a 2-D isotropic Gaussian vector's norm, in per-component standard deviations.
RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
#: ``reference`` values of :func:`fit_log_scale`.
REFERENCES = ("all", "newest")


@dataclass(frozen=True)
class ReprojectionFit:
    """The scale-only reprojection fit of one frame.

    Attributes:
        log_scale: ln s minimising the robust reprojection error.
        std: its standard error (ln units): the track-clustered sandwich of
            the Gauss–Newton step, without the frames' shared pose error.
        sigma_rad: robust standard deviation of one residual component, rad.
        tracks: tracks with at least one residual.
        pairs: (reference, view) pairs used.
        leverage: (N,) float64 each track's share of the Gauss–Newton
            Hessian (its weight times Σ |∂e/∂ln s|²), summing to 1 over the
            tracks used (0 elsewhere).
        iterations: Gauss–Newton steps taken.
    """

    log_scale: float
    std: float
    sigma_rad: float
    tracks: int
    pairs: int
    leverage: np.ndarray
    iterations: int


@numba.njit(cache=True, nogil=True)
def _pair_terms(log_scale: float, centres: np.ndarray, directions: np.ndarray,
                valid: np.ndarray, axes: np.ndarray, relative: np.ndarray, use: np.ndarray,
                newest_only: bool, norm: np.ndarray, score: np.ndarray, curvature: np.ndarray,
                track: np.ndarray, share: np.ndarray) -> int:
    """Residual norm, Jᵀe and JᵀJ of every (track, reference, view) pair at ``log_scale``.

    Fills the first P entries of the output arrays (P returned); ``share`` is
    1 / (the track's reference count), so every track weighs alike whatever
    its number of references.
    """
    n, v = valid.shape
    s = np.exp(log_scale)
    p = 0
    for i in range(n):
        if not use[i]:
            continue
        newest = -1
        for k in range(v):
            if valid[i, k]:
                newest = k
        refs = 0
        first = p
        for r in range(v):
            if not valid[i, r] or not (relative[i, r] > 0.0):
                continue
            if newest_only and r != newest:
                continue
            drx, dry, drz = directions[i, r, 0], directions[i, r, 1], directions[i, r, 2]
            cos_axis = drx * axes[i, r, 0] + dry * axes[i, r, 1] + drz * axes[i, r, 2]
            if cos_axis <= 1e-3:
                continue
            t = s * relative[i, r] / cos_axis
            mx, my, mz = t * drx, t * dry, t * drz  # dX / d ln s
            px, py, pz = centres[i, r, 0] + mx, centres[i, r, 1] + my, centres[i, r, 2] + mz
            used = False
            for k in range(v):
                if k == r or not valid[i, k]:
                    continue
                dx, dy, dz = directions[i, k, 0], directions[i, k, 1], directions[i, k, 2]
                vx, vy, vz = px - centres[i, k, 0], py - centres[i, k, 1], pz - centres[i, k, 2]
                along = vx * dx + vy * dy + vz * dz
                if along <= 1e-9:
                    continue
                ex = (vx - along * dx) / along
                ey = (vy - along * dy) / along
                ez = (vz - along * dz) / along
                m_along = mx * dx + my * dy + mz * dz
                jx = (mx - m_along * dx - ex * m_along) / along
                jy = (my - m_along * dy - ey * m_along) / along
                jz = (mz - m_along * dz - ez * m_along) / along
                norm[p] = np.sqrt(ex * ex + ey * ey + ez * ez)
                score[p] = jx * ex + jy * ey + jz * ez
                curvature[p] = jx * jx + jy * jy + jz * jz
                track[p] = i
                p += 1
                used = True
            refs += used
        for q in range(first, p):
            share[q] = 1.0 / refs
    return p


_Arrays6 = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
_Arrays5 = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _kernel_arrays(views: TrackViews, use: np.ndarray) -> _Arrays6:
    """The kernel's contiguous inputs: centres, directions, valid, axes, relative, use."""
    assert views.axes is not None and views.relative is not None
    n, v = views.valid.shape
    return (np.ascontiguousarray(np.broadcast_to(views.centres, (n, v, 3)), np.float64),
            np.ascontiguousarray(views.directions, np.float64),
            np.ascontiguousarray(views.valid, np.bool_),
            np.ascontiguousarray(np.broadcast_to(views.axes, (n, v, 3)), np.float64),
            np.ascontiguousarray(views.relative, np.float64), np.ascontiguousarray(use))


def _buffers(use: np.ndarray, views: int, newest_only: bool) -> _Arrays5:
    """The kernel's outputs, large enough for every pair: norm, score, curvature, track, share."""
    capacity = int(np.count_nonzero(use)) * (views - 1) * (1 if newest_only else views)
    return (np.empty(capacity), np.empty(capacity), np.empty(capacity),
            np.empty(capacity, np.int64), np.empty(capacity))


def track_leverage(views: TrackViews, use: np.ndarray, log_scale: float, *,
                   reference: str = "all") -> np.ndarray:
    """Each track's leverage on ln s: Σ |∂e/∂ln s|² over its pairs (each reference's share).

    Args:
        views, use, reference: as in :func:`fit_log_scale`.
        log_scale: ln s at which the Jacobians are taken.

    Returns:
        (N,) float64, rad² per unit ln s², 0 for tracks not used or without pairs.
    """
    n, v = views.valid.shape
    use = np.asarray(use, bool)
    if n == 0 or v < 2 or not use.any():
        return np.zeros(n)
    norm, score, curvature, track, share = _buffers(use, v, reference == "newest")
    pairs = _pair_terms(float(log_scale), *_kernel_arrays(views, use), reference == "newest",
                        norm, score, curvature, track, share)
    return np.bincount(track[:pairs], weights=curvature[:pairs] * share[:pairs], minlength=n)


def fit_log_scale(
    views: TrackViews,
    use: np.ndarray,
    weights: np.ndarray,
    start: float,
    *,
    reference: str = "all",
    iterations: int = 8,
    min_sigma_rad: float = 1e-4,
) -> ReprojectionFit | None:
    """Fit ln s to the reprojection of SFS's points (see the module docstring).

    Args:
        views: (N, V) views of N tracks with ``axes`` and ``relative``
            (depth_relative of the track in each view), oldest first.
        use: (N,) bool, the tracks to fit.
        weights: (N,) float >= 0 per-track weights (e.g. balanced over the
            field of view), relative.
        start: initial ln s (e.g. the median of the triangulated ratios).
        reference: ``all``: every view of a track with depth_relative is a
            reference in turn; ``newest``: its newest view only.
        iterations: Gauss–Newton steps at most (stops when the step is
            below 1e-5).
        min_sigma_rad: least robust residual standard deviation, rad.

    Returns:
        The fit, or None without any residual or Hessian.
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {REFERENCES}, got {reference!r}")
    n, v = views.valid.shape
    use = np.asarray(use, bool) & (np.asarray(weights) > 0.0)
    if n == 0 or v < 2 or not use.any() or not np.isfinite(start):
        return None
    newest_only = reference == "newest"
    norm, score, curvature, track, share = _buffers(use, v, newest_only)
    arrays = _kernel_arrays(views, use)
    w_track = np.asarray(weights, np.float64)
    log_scale = float(start)
    sigma = min_sigma_rad
    steps = 0
    pairs = 0
    for steps in range(1, iterations + 1):  # noqa: B007 (steps is reported)
        pairs = _pair_terms(log_scale, *arrays, newest_only, norm, score, curvature, track, share)
        if pairs == 0:
            return None
        r, g, h, t, a = (x[:pairs] for x in (norm, score, curvature, track, share))
        sigma = max(float(np.median(r)) / RAYLEIGH_MEDIAN, min_sigma_rad)
        robust = 1.0 / (1.0 + (r / (CAUCHY_C * sigma)) ** 2)
        w = w_track[t] * a * robust
        hessian = float(np.sum(w * h))
        if not hessian > 0.0:
            return None
        step = float(np.sum(w * g)) / hessian
        log_scale -= float(np.clip(step, -0.5, 0.5))
        if abs(step) < 1e-5:
            break
    # the spread at the solution: scores clustered by track (a track's residuals
    # share its LK and SFS errors)
    pairs = _pair_terms(log_scale, *arrays, newest_only, norm, score, curvature, track, share)
    r, g, h, t, a = (x[:pairs] for x in (norm, score, curvature, track, share))
    robust = 1.0 / (1.0 + (r / (CAUCHY_C * sigma)) ** 2)
    w = w_track[t] * a * robust
    hessian = float(np.sum(w * h))
    if not hessian > 0.0:
        return None
    per_track_score = np.bincount(t, weights=w * g, minlength=n)
    per_track_h = np.bincount(t, weights=w * h, minlength=n)
    tracks = int(np.count_nonzero(per_track_h))
    # Σ score² / H² is 0 at one track: the per-pair noise σ² Σ w² |J|² / H² is its floor
    clustered = float(np.sum(per_track_score**2))
    independent = sigma**2 * float(np.sum(w * w * h))
    std = float(np.sqrt(max(clustered, independent))) / hessian
    if tracks > 1:
        std *= np.sqrt(tracks / (tracks - 1.0))  # the sandwich's small-sample correction
    return ReprojectionFit(log_scale, std, sigma, tracks, int(pairs), per_track_h / hessian,
                           steps)


__all__ = ["CAUCHY_C", "REFERENCES", "ReprojectionFit", "fit_log_scale", "track_leverage"]
