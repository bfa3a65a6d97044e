"""The Cramér–Rao bound on ln s from the tracker's samples, and the fit that attains it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from endo_flow.errors import FlowInputError
from endo_flow.scale_information import (
    camera_centre_covariances,
    cumulative_scale_fit,
    known_rotation_translation,
    lever_arms,
    scale_information_bound,
    segmented_scale_fit,
)
from endo_io.pose import rigid_transform
from endo_sim.tracker import DEFAULT_T_MARKER_CAMERA, TrackerModel
from endo_tracker_bridge.composition import compose_camera_pose


def _line(n: int, length_m: float) -> np.ndarray:
    centres = np.zeros((n, 3))
    centres[:, 0] = np.linspace(0.0, length_m, n)
    centres += np.array([0.01, -0.02, 0.05])  # any origin
    return centres


def test_straight_line_matches_the_closed_form():
    sigma, length, n = 0.2e-3, 5e-3, 600  # per-axis noise, displacement, samples
    centres = _line(n, length)
    cov = np.repeat((sigma**2 * np.eye(3))[None], n, axis=0)
    bound = scale_information_bound(centres, cov)
    assert bound.shape == (n,) and np.isinf(bound[0])
    # exactly σ / √Σ(x_i − x̄)² for every prefix of two samples or more
    for k in (1, 2, 59, 299, n - 1):
        x = centres[: k + 1, 0]
        assert bound[k] == pytest.approx(sigma / np.sqrt(np.sum((x - x.mean()) ** 2)), rel=1e-9)
    # and σ√12 / (D√N) for many samples: 0.566 % here
    closed = sigma * math.sqrt(12.0) / (length * math.sqrt(n))
    assert closed == pytest.approx(0.00566, abs=1e-5)
    assert bound[-1] == pytest.approx(closed, rel=2e-3)
    # noise along the line is what counts: across it, none
    across = np.repeat(np.diag([sigma**2, (10 * sigma) ** 2, (10 * sigma) ** 2])[None], n, axis=0)
    assert scale_information_bound(centres, across)[-1] == pytest.approx(bound[-1], rel=1e-9)
    assert np.all(np.diff(bound[1:]) <= 0.0)  # more samples never lose information


def test_covariance_matches_the_simulated_tracker():
    """The first-order Σ against endo_sim's noise carried through the bridge's chain."""
    model = TrackerModel()
    rng = np.random.default_rng(3)
    T_world_camera = rigid_transform((0.3, -0.5, 0.2), (0.02, 0.01, 0.04))
    T_world_tracker = np.linalg.inv(model.T_tracker_world)
    marker = model.true_marker_poses(T_world_camera[None])[0]
    draws = model.add_noise(np.repeat(marker[None], 40_000, axis=0), rng)
    centres = compose_camera_pose(T_world_tracker, draws, model.T_marker_camera)[:, :3, 3]
    empirical = np.cov(centres.T)
    lever = lever_arms(T_world_camera[None], DEFAULT_T_MARKER_CAMERA)
    assert np.linalg.norm(lever) == pytest.approx(0.3022, abs=1e-4)
    predicted = camera_centre_covariances(
        lever, model.position_noise_rms_m, model.rotation_noise_rms_rad
    )[0]
    # per-axis RMS across the lever: √(0.25²/3 + (0.1° · 0.302 m)²/3) = 0.337 mm, along it 0.144 mm
    along = lever[0] / np.linalg.norm(lever[0])
    assert math.sqrt(along @ predicted @ along) == pytest.approx(0.25e-3 / math.sqrt(3), rel=1e-6)
    assert math.sqrt(np.trace(predicted) - along @ predicted @ along) / math.sqrt(2) == (
        pytest.approx(0.337e-3, abs=1e-6)
    )
    assert np.abs(empirical - predicted).max() < 0.03 * np.abs(predicted).max()
    assert math.sqrt(along @ empirical @ along) == pytest.approx(0.144e-3, rel=0.03)


def test_the_fit_attains_the_bound():
    """Weighted least squares of (s, t0) over a curved path: unbiased, std = the bound."""
    n = 120  # 2 s at 60 Hz
    t = np.linspace(0.0, 1.0, n)
    true = np.stack([6e-3 * t, 3e-3 * np.sin(3.0 * t), 8e-3 * t**2], axis=1) + 0.05
    R = rigid_transform((0.4, 0.2, -0.3), (0.0, 0.0, 0.0))[:3, :3]
    lever = (R @ np.array([0.0, 0.0, -0.3]))[None].repeat(n, axis=0)  # the scope along R's z
    cov = camera_centre_covariances(lever, 0.25e-3, math.radians(0.1))
    bound = scale_information_bound(true, cov)
    rng = np.random.default_rng(7)
    scale = 0.037  # vision's unit: relative = true / scale
    chol = np.linalg.cholesky(cov)
    fits = []
    for _ in range(800):
        measured = true + np.einsum("nij,nj->ni", chol, rng.normal(size=(n, 3)))
        fits.append(cumulative_scale_fit(true / scale, measured, cov))
    errors = np.array(fits) - math.log(scale)
    for k in (20, 60, n - 1):
        assert abs(errors[:, k].mean()) < 3.5 * bound[k] / math.sqrt(len(fits))
        assert errors[:, k].std() == pytest.approx(bound[k], rel=0.08)
    assert 0.005 < bound[-1] < 0.02  # 0.25 mm / 0.1° over ~1 cm in 2 s: ~1 %
    assert np.isnan(fits[0][0])


def test_known_orientation_leaves_the_position_noise():
    n = 60
    centres = _line(n, 4e-3)
    lever = np.tile([0.0, 0.3, 0.0], (n, 1))  # lever across the motion: rotation noise counts
    with_rotation = scale_information_bound(
        centres, camera_centre_covariances(lever, 0.25e-3, math.radians(0.1))
    )[-1]
    position_only = scale_information_bound(
        centres, camera_centre_covariances(lever, 0.25e-3, 0.0)
    )[-1]
    # per-axis σ along the line √(σ_p²/3 + (σ_r · 0.3 m)²/3) = 0.335 mm against σ_p/√3 = 0.144 mm
    across = math.sqrt(0.25e-3**2 / 3 + (math.radians(0.1) * 0.3) ** 2 / 3)
    assert across == pytest.approx(0.335e-3, abs=1e-6)
    assert with_rotation / position_only == pytest.approx(across / (0.25e-3 / math.sqrt(3)),
                                                          rel=1e-9)


def test_bad_input_is_named():
    with pytest.raises(FlowInputError, match=r"centres must be \(N, 3\)"):
        scale_information_bound(np.zeros((4, 2)), np.zeros((4, 3, 3)))
    with pytest.raises(FlowInputError, match="positive definite"):
        scale_information_bound(np.zeros((2, 3)), np.zeros((2, 3, 3)))
    with pytest.raises(FlowInputError, match="position noise must be > 0"):
        camera_centre_covariances(np.zeros((1, 3)), 0.0, 0.001)
    with pytest.raises(FlowInputError, match="differ in shape"):
        cumulative_scale_fit(np.zeros((3, 3)), np.zeros((2, 3)), np.tile(np.eye(3), (3, 1, 1)))


def test_known_rotation_translation_recovers_the_motion():
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(-0.02, 0.02, (80, 2)), rng.uniform(0.03, 0.06, 80)])
    T = rigid_transform((0.05, -0.03, 0.08), (1.5e-3, -0.7e-3, 2.0e-3))  # T_view_reference
    seen = points @ T[:3, :3].T + T[:3, 3]
    rays = seen / np.linalg.norm(seen, axis=1, keepdims=True)
    rays[:8] = rays[::-1][:8]  # 10 % of the tracks on the wrong point
    t, inliers = known_rotation_translation(points, rays, T[:3, :3])
    assert np.abs(t - T[:3, 3]).max() < 2e-6  # 2 µm of 2.6 mm
    assert 70 <= inliers <= 74
    # the same in another unit (SFS's): the translation scales with the points
    t_unit, _ = known_rotation_translation(points / 0.02, rays, T[:3, :3])
    assert np.abs(t_unit * 0.02 - T[:3, 3]).max() < 2e-6
    with pytest.raises(FlowInputError, match="at least 3"):
        known_rotation_translation(points[:2], rays[:2], T[:3, :3])


def test_segmented_fit_shares_one_scale():
    """Two segments with their own offsets: the fit = the one-segment fit on each, combined."""
    rng = np.random.default_rng(5)
    scale, sigma = 0.02, 0.3e-3
    segments = []
    for start in (np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.03, -0.01])):
        true = start + np.cumsum(rng.normal(0.0, 4e-4, (90, 3)), axis=0)
        cov = np.repeat((sigma**2 * np.eye(3))[None], 90, axis=0)
        measured = true + rng.normal(0.0, sigma, true.shape)
        segments.append((true / scale + 7.0, measured, cov))  # vision: another unit and origin
    log_s, std = segmented_scale_fit(segments)
    bounds = [scale_information_bound(m * 0 + r * scale, c)[-1] for r, m, c in segments]
    assert std == pytest.approx(1.0 / math.sqrt(sum(b**-2 for b in bounds)), rel=0.02)
    assert abs(log_s - math.log(scale)) < 3.0 * std
    assert math.isnan(segmented_scale_fit([(np.zeros((3, 3)), np.zeros((3, 3)),
                                            np.tile(np.eye(3), (3, 1, 1)))])[0])


def test_segmented_fit_and_translation_name_bad_input():
    eye = np.tile(np.eye(3), (3, 1, 1))
    with pytest.raises(FlowInputError, match="segment 0 holds 0 relative"):
        segmented_scale_fit([(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)))])
    with pytest.raises(FlowInputError, match="segment 1 holds 3 relative and 2 measured"):
        segmented_scale_fit([(np.ones((3, 3)), np.ones((3, 3)), eye),
                             (np.ones((3, 3)), np.ones((2, 3)), eye)])
    with pytest.raises(FlowInputError, match="NaN"):
        segmented_scale_fit([(np.full((3, 3), np.nan), np.ones((3, 3)), eye)])
    # three points on the reference centre have no direction: too few are left
    points = np.vstack([np.zeros((3, 3)), [[0.0, 0.0, 0.05]]])
    with pytest.raises(FlowInputError, match="off the centre"):
        known_rotation_translation(points, np.tile([0.0, 0.0, 1.0], (4, 1)), np.eye(3))
