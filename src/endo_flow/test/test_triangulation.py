"""Multi-view midpoint triangulation and its gates, against known points."""

from __future__ import annotations

import numpy as np

from endo_flow.keyframes import Keyframe, KeyframeWindow, TrackViews
from endo_flow.pipeline import geometric_parallax
from endo_flow.triangulation import TriangulationGates, midpoint, triangulate
from endo_io.pose import rigid_transform

from .conftest import synthetic_track_views


def _views(points: np.ndarray, centres: np.ndarray, angle_noise: float = 0.0,
           seed: int = 0) -> TrackViews:
    return synthetic_track_views(points, centres, angle_noise=angle_noise, seed=seed)


def test_midpoint_recovers_points_exactly_without_noise():
    rng = np.random.default_rng(1)
    points = rng.uniform([-0.02, -0.02, 0.03], [0.02, 0.02, 0.06], (50, 3))
    centres = np.array([[0.0, 0.0, 0.0], [0.004, 0.001, 0.0], [0.008, -0.001, 0.002]])
    estimate, smallest = midpoint(_views(points, centres))
    np.testing.assert_allclose(estimate, points, atol=1e-12)
    assert np.all(smallest > 0.0)


def test_noise_averages_over_views():
    """0.3 mrad ray noise (0.1 px at f = 320): depth error falls with the view count."""
    rng = np.random.default_rng(2)
    points = rng.uniform([-0.01, -0.01, 0.035], [0.01, 0.01, 0.045], (400, 3))
    errors = []
    for v in (3, 12):
        centres = np.stack([np.linspace(0.0, 0.01, v), np.zeros(v), np.zeros(v)], axis=1)
        estimate, _ = midpoint(_views(points, centres, angle_noise=3e-4, seed=v))
        errors.append(np.sqrt(np.mean((estimate[:, 2] - points[:, 2]) ** 2)))
    assert errors[0] < 0.25e-3  # 10 mm baseline at 40 mm: ~0.1 mm
    assert errors[1] < 0.7 * errors[0]


def test_gates_reject_two_views_small_parallax_behind_and_outliers():
    points = np.array([[0.0, 0.0, 0.04]] * 4)
    centres = np.array([[0.0, 0.0, 0.0], [0.005, 0.0, 0.0], [0.01, 0.0, 0.0]])
    views = _views(points, centres)
    views.valid[1, 0] = False  # track 1: two views only
    views.directions[2] *= -1.0  # track 2: point behind every camera
    views.directions[3, 0] = [0.3, 0.0, 0.954]  # track 3: one ray 0.3 rad off
    views.directions[3, 0] /= np.linalg.norm(views.directions[3, 0])
    result = triangulate(views, TriangulationGates(), optical_axis=np.array([0.0, 0.0, 1.0]))
    assert result.accepted.tolist() == [True, False, False, False]
    assert abs(result.depth_m[0] - 0.04) < 1e-12
    np.testing.assert_allclose(result.parallax_rad[0], np.arctan2(0.01, 0.04), rtol=1e-9)
    # the same geometry with a 1 mm baseline fails the parallax and baseline gates
    short = _views(points[:1], centres * 0.1)
    assert not triangulate(short, TriangulationGates()).accepted[0]


def test_keyframe_window_gathers_views_by_track_id():
    window = KeyframeWindow(capacity=3, min_step_m=1e-3)
    point = np.array([0.001, -0.002, 0.05])
    for k in range(5):
        T = rigid_transform(np.array([0.0, 0.02 * k, 0.0]), np.array([0.003 * k, 0.0, 0.0]))
        ray = T[:3, :3].T @ (point - T[:3, 3])
        ids = np.array([7, 3]) if k % 2 else np.array([3, 7, 9])
        rays = np.tile(ray / np.linalg.norm(ray), (len(ids), 1))
        assert window.wants(T)
        window.add(Keyframe(k, T, ids, rays))
    assert len(window) == 3
    views = window.views(np.array([7, 9]))
    assert views.valid.tolist() == [[True, True, True], [True, False, True]]
    estimate, _ = midpoint(TrackViews(views.centres[:1], views.directions[:1], views.valid[:1]))
    np.testing.assert_allclose(estimate[0], point, atol=1e-12)


def test_predicted_parallax_gate_does_not_select_near_biased_tracks():
    """Short baselines, 3 mrad ray noise: gating the rays' own parallax at 4° biases depth low.

    Points 30–50 mm away seen over a 2.8 mm baseline (parallax 3–5°): the
    tracks whose noise widened their rays' angle pass a 4° gate on it and
    triangulate too near; the same gate on the angle predicted from the
    baseline and the (noise-free) relative depth keeps as many tracks
    without choosing them by their error.
    """
    rng = np.random.default_rng(3)
    n = 2000
    points = rng.uniform([-0.02, -0.02, 0.03], [0.02, 0.02, 0.05], (n, 3))
    centres = np.array([[0.0, 0.0, 0.0], [1.4e-3, 0.0, 0.0], [2.8e-3, 0.0, 0.0]])
    views = _views(points, centres, angle_noise=3e-3, seed=3)
    axis = np.array([0.0, 0.0, 1.0])
    result = triangulate(views, TriangulationGates(min_parallax_rad=np.radians(1.0)),
                         optical_axis=axis)
    ok = result.accepted
    log_error = np.log(result.depth_m / points[:, 2])
    relative = points[:, 2] / 0.04  # a perfect SFS, 0.04 m per unit
    predicted = np.zeros(n)
    predicted[ok] = geometric_parallax(views, ok, np.log(result.depth_m[ok] / relative[ok]),
                                       relative[ok], axis)
    to_first, to_last = points - centres[0], points - centres[-1]
    true_angle = np.arccos(np.sum(to_first * to_last, axis=1) / np.linalg.norm(to_first, axis=1)
                           / np.linalg.norm(to_last, axis=1))
    np.testing.assert_allclose(predicted[ok], true_angle[ok], rtol=0.08)
    # every track at the frame's median distance: the angle follows the baseline only
    flat = geometric_parallax(views, ok, np.log(result.depth_m[ok] / relative[ok]),
                              relative[ok], axis, one_distance=True)
    assert np.ptp(flat) < 0.35 * np.ptp(predicted[ok]), (np.ptp(flat), np.ptp(predicted[ok]))
    by_rays = ok & (result.parallax_rad >= np.radians(4.0))
    by_prediction = ok & (predicted >= np.radians(4.0))
    assert abs(by_rays.sum() - by_prediction.sum()) < 0.1 * by_rays.sum()
    bias_rays = np.median(log_error[by_rays])
    bias_predicted = np.median(log_error[by_prediction])
    assert bias_rays < -0.02  # measured -3.1 to -3.8 % over seeds 1-3
    assert bias_predicted > 0.5 * bias_rays  # measured -0.9 %: the midpoint's own
