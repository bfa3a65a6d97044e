"""Tracker simulation: noise RMS, latency, dropouts, units, the hand–eye chain."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_io.pose import invert_transform, rigid_transform
from endo_sim.errors import SimulationParameterError
from endo_sim.tracker import TrackerModel, simulate_tracker
from endo_sim.trajectory import NS_PER_S, StationTrajectory


def static_trajectory(seconds: float) -> StationTrajectory:
    pose = rigid_transform([0.2, -0.4, 1.0], [0.01, -0.02, 0.05])
    return StationTrajectory(pose[None], round(seconds * NS_PER_S), 1)


@pytest.mark.parametrize(("position_mm", "rotation_deg"), [(0.25, 0.1), (0.5, 0.3)])
def test_noise_has_the_configured_rms(position_mm: float, rotation_deg: float) -> None:
    model = TrackerModel(
        position_noise_rms_m=position_mm * 1e-3,
        rotation_noise_rms_rad=math.radians(rotation_deg),
        dropout_rate_hz=0.0,
    )
    samples = simulate_tracker(model, static_trajectory(400.0), np.random.default_rng(4))
    n = len(samples.stamp_ns)
    assert n == 24000
    translation = samples.poses[:, :3, 3] - samples.true_poses[:, :3, 3]
    rms_t = math.sqrt(float(np.mean(np.sum(translation**2, axis=-1))))
    relative = np.swapaxes(samples.true_poses[:, :3, :3], 1, 2) @ samples.poses[:, :3, :3]
    angle = Rotation.from_matrix(relative).magnitude()
    rms_r = math.degrees(math.sqrt(float(np.mean(angle**2))))
    # 24000 samples: the RMS estimate is within ±1.5 % (4 standard errors).
    assert rms_t == pytest.approx(position_mm * 1e-3, rel=0.015)
    assert rms_r == pytest.approx(rotation_deg, rel=0.015)
    # Isotropic: each axis carries a third of the variance.
    per_axis = np.sqrt(np.mean(translation**2, axis=0))
    np.testing.assert_allclose(per_axis, position_mm * 1e-3 / math.sqrt(3), rtol=0.03)


def test_latency_rate_and_the_hand_eye_chain() -> None:
    model = TrackerModel(
        latency_s=0.031, dropout_rate_hz=0.0, position_noise_rms_m=0.0, rotation_noise_rms_rad=0.0
    )
    trajectory = static_trajectory(2.0)
    samples = simulate_tracker(model, trajectory, np.random.default_rng(0))
    assert np.all(samples.stamp_ns - samples.sample_ns == 31_000_000)
    periods = np.diff(samples.sample_ns)
    assert np.all(np.abs(periods - NS_PER_S / 60) <= 1)
    # Marker pose composed back with the hand–eye gives the camera in the world.
    camera = invert_transform(model.T_tracker_world) @ samples.poses[0] @ model.T_marker_camera
    np.testing.assert_allclose(camera, trajectory.pose_at(0), atol=1e-12)


def test_dropouts_remove_the_expected_fraction() -> None:
    model = TrackerModel(dropout_rate_hz=0.5, dropout_mean_s=0.2)
    samples = simulate_tracker(model, static_trajectory(600.0), np.random.default_rng(9))
    missing = 1.0 - samples.visible.mean()
    # Alternating exponential spells: occluded fraction = r·m / (1 + r·m) = 0.0909.
    assert missing == pytest.approx(0.1 / 1.1, abs=0.015)
    # Dropouts come in runs, not isolated samples.
    starts = np.count_nonzero(np.diff(samples.visible.astype(int)) == -1)
    assert starts == pytest.approx(0.5 * 600 / 1.1, rel=0.15)


def test_units_and_validation() -> None:
    assert TrackerModel(units="mm").unit_scale == 1000.0
    with pytest.raises(SimulationParameterError):
        TrackerModel(units="cm")
    with pytest.raises(SimulationParameterError):
        TrackerModel(T_marker_camera=np.eye(3))
