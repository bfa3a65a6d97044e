"""The numba triangulation against the numpy version it replaced, figure by figure."""

from __future__ import annotations

import numpy as np

from endo_flow.keyframes import TrackViews
from endo_flow.triangulation import Triangulation, TriangulationGates, midpoint, triangulate


def numpy_midpoint(views: TrackViews) -> tuple[np.ndarray, np.ndarray]:
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


def numpy_triangulate(
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
    points, _ = numpy_midpoint(views)
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


def test_numba_triangulation_equals_the_numpy_version():
    rng = np.random.default_rng(0)
    n, v = 500, 12
    truth = rng.uniform([-0.02, -0.02, 0.02], [0.02, 0.02, 0.06], (n, 3))
    centres = np.zeros((n, v, 3))
    centres[:] = np.stack([np.linspace(0.0, 0.01, v), rng.normal(0.0, 1e-3, v), np.zeros(v)], 1)
    directions = truth[:, None] - centres + rng.normal(0.0, 2e-5, (n, v, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    valid = rng.random((n, v)) < 0.6
    directions[~valid] = 0.0
    directions[:20] *= -1.0  # behind every view
    directions[20:25] = directions[20:25, :1]  # parallel rays: no point
    valid[25:30] = False  # no view at all
    valid[30:35, 2:] = False  # two views at most
    views = TrackViews(centres, directions, valid)
    axis = np.array([0.0, 0.1, 0.995])
    for optical_axis in (axis / np.linalg.norm(axis), None):
        got = triangulate(views, TriangulationGates(), optical_axis=optical_axis)
        want = numpy_triangulate(views, TriangulationGates(), optical_axis=optical_axis)
        assert 400 < got.accepted.sum() <= n - 35
        np.testing.assert_array_equal(got.accepted, want.accepted)
        np.testing.assert_array_equal(got.views, want.views)
        np.testing.assert_allclose(got.points, want.points, rtol=0, atol=1e-13)
        np.testing.assert_allclose(got.depth_m, want.depth_m, rtol=0, atol=1e-13)
        np.testing.assert_allclose(got.parallax_rad, want.parallax_rad, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.baseline_m, want.baseline_m, rtol=0, atol=1e-15)
        # arccos near 1 amplifies rounding: 1e-10 rad against a 0.02 rad gate
        np.testing.assert_allclose(got.residual_rad, want.residual_rad, rtol=0, atol=1e-10)
    points, smallest = midpoint(views)
    ref_points, ref_smallest = numpy_midpoint(views)
    np.testing.assert_allclose(points, ref_points, rtol=0, atol=1e-13)
    np.testing.assert_allclose(smallest, ref_smallest, rtol=0, atol=1e-14)
