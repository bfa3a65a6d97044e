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


def midpoint(views: TrackViews) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares nearest point to each track's rays.

    Args:
        views: (N, V) views of N tracks.

    Returns:
        ((N, 3) float64 points, NaN where the rays are (nearly) parallel or
        fewer than two; (N,) float64 smallest eigenvalue of the normal
        matrix divided by the view count, 0 for parallel rays, in [0, 1)).
    """
    d = views.directions
    w = views.valid.astype(np.float64)
    # Σ_k w (I − d dᵀ) and Σ_k w (I − d dᵀ) c, without forming (N, V, 3, 3)
    count = w.sum(axis=1)
    outer = np.einsum("nv,nvi,nvj->nij", w, d, d)
    A = count[:, None, None] * np.eye(3) - outer
    proj_c = views.centres - d * np.einsum("nvi,nvi->nv", d, views.centres)[..., None]
    b = np.einsum("nv,nvi->ni", w, proj_c)
    smallest = np.linalg.eigvalsh(A)[:, 0] / np.maximum(count, 1.0)
    solvable = (count >= 2) & (smallest > 1e-9)
    points = np.full((len(d), 3), np.nan)
    if np.any(solvable):
        points[solvable] = np.linalg.solve(A[solvable], b[solvable][..., None])[..., 0]
    return points, np.where(solvable, smallest, 0.0)


def triangulate(
    views: TrackViews,
    gates: TriangulationGates | None = None,
    *,
    optical_axis: np.ndarray | None = None,
) -> Triangulation:
    """Triangulate tracks and apply the gates (see the module docstring).

    The newest view of a track is its last valid one.

    Args:
        views: (N, V) views, oldest first.
        gates: acceptance tests (defaults if None).
        optical_axis: (3,) world direction of the optical axis of the view
            the depth is measured in (the current frame), or None.

    Returns:
        The points and the per-track gate figures.
    """
    g = gates or TriangulationGates()
    points, _ = midpoint(views)
    n, v = views.valid.shape
    n_views = views.valid.sum(axis=1)
    last = v - 1 - np.argmax(views.valid[:, ::-1], axis=1)
    rows = np.arange(n)
    ref_dir = views.directions[rows, last]
    ref_centre = views.centres[rows, last]

    cos_par = np.einsum("nvi,ni->nv", views.directions, ref_dir)
    cos_par = np.where(views.valid, cos_par, 1.0)
    parallax = np.arccos(np.clip(cos_par.min(axis=1), -1.0, 1.0))
    spread = np.linalg.norm(views.centres - ref_centre[:, None, :], axis=2)
    baseline = np.where(views.valid, spread, 0.0).max(axis=1)

    with np.errstate(invalid="ignore"):
        to_point = points[:, None, :] - views.centres
        along = np.einsum("nvi,nvi->nv", to_point, views.directions)
        dist = np.linalg.norm(to_point, axis=2)
        cos_res = along / np.maximum(dist, 1e-12)
        residual = np.arccos(np.clip(np.where(views.valid, cos_res, 1.0), -1.0, 1.0)).max(axis=1)
        in_front = np.where(views.valid, along > 0.0, True).all(axis=1)
        offset = points - ref_centre
        depth = offset @ optical_axis if optical_axis is not None else np.linalg.norm(offset,
                                                                                     axis=1)
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
