"""Multi-view triangulation of tracks on unit rays with known camera poses.

Each track has V views: camera centres c_k and world unit rays d_k
(:class:`endo_flow.keyframes.TrackViews`). The midpoint estimate is the point
nearest to all rays in the least-squares sense,

    X = argmin Σ_k |(I − d_k d_kᵀ)(X − c_k)|²,

a 3×3 linear system per track, solved for all tracks at once. It is exact
for exact rays and, unlike two-view DLT, averages the tracker's pose noise
over every view. A track is accepted only if:

* it has at least ``min_views`` views (more than two: two rays always
  "meet" at their midpoint, a third is the first check that they agree);
* the largest angle between its rays and the newest ray (the parallax) is at
  least ``min_parallax_rad``, and the camera centres are at least
  ``min_baseline_m`` apart: without baseline the depth is noise;
* every ray passes within ``max_residual_rad`` of the point (the
  reprojection error, as an angle so that lens distortion does not matter:
  1 px is 1/f rad at the image centre);
* the point is in front of every view, and its depth along the newest
  view's optical axis is within [``min_depth_m``, ``max_depth_m``].
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from endo_flow.keyframes import TrackViews


@dataclass(frozen=True)
class TriangulationGates:
    """Acceptance tests of a triangulated track (see the module docstring).

    Attributes:
        min_views: least number of views (>= 3).
        min_parallax_rad: least angle between the newest ray and another.
        min_baseline_m: least distance between the newest camera centre and
            another, metres.
        max_residual_rad: largest angle between a ray and the direction to
            the point.
        min_depth_m, max_depth_m: depth range along the newest optical axis.
    """

    min_views: int = 3
    min_parallax_rad: float = float(np.radians(4.0))
    min_baseline_m: float = 2.0e-3
    max_residual_rad: float = 0.02
    min_depth_m: float = 2.0e-3
    max_depth_m: float = 0.3

    def __post_init__(self) -> None:
        if self.min_views < 3:
            raise ValueError(f"min_views must be >= 3, got {self.min_views}")
        if self.min_parallax_rad < 0.0 or self.min_baseline_m < 0.0:
            raise ValueError("min_parallax_rad and min_baseline_m must be >= 0")
        if not self.max_residual_rad > 0.0:
            raise ValueError("max_residual_rad must be > 0")
        if not 0.0 <= self.min_depth_m < self.max_depth_m:
            raise ValueError("need 0 <= min_depth_m < max_depth_m")


@dataclass(frozen=True)
class Triangulation:
    """Triangulated tracks.

    Attributes:
        points: (N, 3) float64 world points, metres (NaN where unsolvable).
        accepted: (N,) bool, passed every gate.
        views: (N,) int, number of views used.
        parallax_rad: (N,) float64 largest angle to the newest ray.
        baseline_m: (N,) float64 largest distance to the newest centre.
        residual_rad: (N,) float64 largest ray-to-point angle.
        depth_m: (N,) float64 depth along the newest view's optical axis
            (needs ``optical_axis`` in :func:`triangulate`; else the
            distance from the newest centre).
    """

    points: np.ndarray
    accepted: np.ndarray
    views: np.ndarray
    parallax_rad: np.ndarray
    baseline_m: np.ndarray
    residual_rad: np.ndarray
    depth_m: np.ndarray


@numba.njit(cache=True, nogil=True)
def _smallest_eigenvalue(a00: float, a01: float, a02: float, a11: float, a12: float,
                         a22: float) -> float:
    """Smallest eigenvalue of a symmetric 3×3 matrix (the trigonometric closed form)."""
    off = a01 * a01 + a02 * a02 + a12 * a12
    if off == 0.0:
        return min(a00, a11, a22)
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    # det((A − qI) / p) / 2, clamped to acos's domain against rounding
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
           + a02 * (a01 * a12 - b11 * a02))
    r = min(1.0, max(-1.0, det / (2.0 * p * p * p)))
    return q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)


@numba.njit(cache=True, nogil=True)
def _triangulate(
    centres: np.ndarray, directions: np.ndarray, valid: np.ndarray, axis: np.ndarray,
    has_axis: bool, points: np.ndarray, smallest: np.ndarray, n_views: np.ndarray,
    parallax: np.ndarray, baseline: np.ndarray, residual: np.ndarray, depth: np.ndarray,
    in_front: np.ndarray,
) -> None:
    """Midpoint and gate figures of every track, one pass per track (see :func:`triangulate`)."""
    n, v = valid.shape
    for i in range(n):
        # Σ_k (I − d dᵀ) and Σ_k (I − d dᵀ) c over the valid views
        count = 0
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        b0 = b1 = b2 = 0.0
        last = v - 1
        for k in range(v):
            if not valid[i, k]:
                continue
            count += 1
            last = k
            dx, dy, dz = directions[i, k, 0], directions[i, k, 1], directions[i, k, 2]
            cx, cy, cz = centres[i, k, 0], centres[i, k, 1], centres[i, k, 2]
            a00 += 1.0 - dx * dx
            a01 -= dx * dy
            a02 -= dx * dz
            a11 += 1.0 - dy * dy
            a12 -= dy * dz
            a22 += 1.0 - dz * dz
            along = dx * cx + dy * cy + dz * cz
            b0 += cx - dx * along
            b1 += cy - dy * along
            b2 += cz - dz * along
        n_views[i] = count
        low = _smallest_eigenvalue(a00, a01, a02, a11, a12, a22) / max(count, 1)
        x = y = z = np.nan
        if count >= 2 and low > 1e-9:
            smallest[i] = low
            # Cramer's rule on the symmetric positive definite 3×3 system
            c00 = a11 * a22 - a12 * a12
            c01 = a02 * a12 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            det = a00 * c00 + a01 * c01 + a02 * c02
            x = (c00 * b0 + c01 * b1 + c02 * b2) / det
            y = (c01 * b0 + (a00 * a22 - a02 * a02) * b1 + (a01 * a02 - a00 * a12) * b2) / det
            z = (c02 * b0 + (a01 * a02 - a00 * a12) * b1 + (a00 * a11 - a01 * a01) * b2) / det
        else:
            smallest[i] = 0.0
        points[i, 0], points[i, 1], points[i, 2] = x, y, z
        # the gates' figures against the newest valid view
        rdx, rdy, rdz = directions[i, last, 0], directions[i, last, 1], directions[i, last, 2]
        rcx, rcy, rcz = centres[i, last, 0], centres[i, last, 1], centres[i, last, 2]
        min_cos = 1.0
        widest = 0.0
        worst = 0.0
        front = True
        for k in range(v):
            if not valid[i, k]:
                continue
            dx, dy, dz = directions[i, k, 0], directions[i, k, 1], directions[i, k, 2]
            min_cos = min(min_cos, dx * rdx + dy * rdy + dz * rdz)
            ex = centres[i, k, 0] - rcx
            ey = centres[i, k, 1] - rcy
            ez = centres[i, k, 2] - rcz
            widest = max(widest, np.sqrt(ex * ex + ey * ey + ez * ez))
            tx = x - centres[i, k, 0]
            ty = y - centres[i, k, 1]
            tz = z - centres[i, k, 2]
            along = tx * dx + ty * dy + tz * dz
            dist = np.sqrt(tx * tx + ty * ty + tz * tz)
            if np.isnan(along):  # no point: no residual, and not in front
                worst = np.nan
            elif not np.isnan(worst):
                worst = max(worst, np.arccos(min(1.0, max(-1.0, along / max(dist, 1e-12)))))
            front = front and along > 0.0
        parallax[i] = np.arccos(max(-1.0, min(1.0, min_cos)))
        baseline[i] = widest
        residual[i] = worst
        in_front[i] = front
        ox, oy, oz = x - rcx, y - rcy, z - rcz
        if has_axis:
            depth[i] = ox * axis[0] + oy * axis[1] + oz * axis[2]
        else:
            depth[i] = np.sqrt(ox * ox + oy * oy + oz * oz)


def _solve(views: TrackViews, optical_axis: np.ndarray | None) -> tuple[np.ndarray, ...]:
    n, v = views.valid.shape
    points = np.empty((n, 3))
    smallest, parallax, baseline, residual, depth = (np.empty(n) for _ in range(5))
    n_views = np.empty(n, np.int64)
    in_front = np.empty(n, bool)
    axis = np.zeros(3) if optical_axis is None else np.asarray(optical_axis, np.float64)
    _triangulate(np.ascontiguousarray(np.broadcast_to(views.centres, (n, v, 3)), np.float64),
                 np.ascontiguousarray(views.directions, np.float64),
                 np.ascontiguousarray(views.valid, np.bool_), axis, optical_axis is not None,
                 points, smallest, n_views, parallax, baseline, residual, depth, in_front)
    return points, smallest, n_views, parallax, baseline, residual, depth, in_front


def midpoint(views: TrackViews) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares nearest point to each track's rays.

    Args:
        views: (N, V) views of N tracks.

    Returns:
        ((N, 3) float64 points, NaN where the rays are (nearly) parallel or
        fewer than two; (N,) float64 smallest eigenvalue of the normal
        matrix divided by the view count, 0 for parallel rays, in [0, 1)).
    """
    points, smallest, *_ = _solve(views, None)
    return points, smallest


def triangulate(
    views: TrackViews,
    gates: TriangulationGates | None = None,
    *,
    optical_axis: np.ndarray | None = None,
) -> Triangulation:
    """Triangulate tracks and apply the gates (see the module docstring).

    The newest view of a track is its last valid one. One numba pass per
    track (the numpy version built (N, V, 3) temporaries and ran LAPACK on
    N 3×3 systems: ~1 ms per frame).

    Args:
        views: (N, V) views, oldest first.
        gates: acceptance tests (defaults if None).
        optical_axis: (3,) world direction of the optical axis of the view
            the depth is measured in (the current frame), or None.

    Returns:
        The points and the per-track gate figures.
    """
    g = gates or TriangulationGates()
    points, _, n_views, parallax, baseline, residual, depth, in_front = _solve(views,
                                                                                optical_axis)
    with np.errstate(invalid="ignore"):
        accepted = (
            np.isfinite(points).all(axis=1)
            & (n_views >= g.min_views)
            & (parallax >= g.min_parallax_rad)
            & (baseline >= g.min_baseline_m)
            & (residual <= g.max_residual_rad)
            & in_front
            & (depth >= g.min_depth_m)
            & (depth <= g.max_depth_m)
        )
    return Triangulation(points, accepted, n_views, parallax, baseline, residual, depth)
