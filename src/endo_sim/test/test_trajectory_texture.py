"""Trajectories at surgical speeds; the tissue texture."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_sim.abdomen import AbdomenGeometry
from endo_sim.colon import ColonGeometry, ColonScene
from endo_sim.handeye import centred_board, handeye_stations, handeye_trajectory
from endo_sim.texture import Texture, tissue_texture
from endo_sim.trajectory import NS_PER_S, AbdomenTrajectory, ColonTrajectory


def speeds(trajectory, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0, round(seconds * NS_PER_S), 10_000_000, dtype=np.int64)
    poses = trajectory.poses_at(t)
    linear = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=-1) / 0.01
    rotation = Rotation.from_matrix(poses[:, :3, :3])
    angular = (rotation[:-1].inv() * rotation[1:]).magnitude() / 0.01
    return linear, angular


def test_colon_motion_is_smooth_at_surgical_speed_and_inside_the_lumen() -> None:
    geometry = ColonGeometry()
    scene = ColonScene(
        geometry, Texture(np.full((8, 8, 1), 0.4, np.float32), (0.2, 2 * math.pi * 0.022)), 1
    )
    trajectory = ColonTrajectory(scene, seed=1, duration_ns=30 * NS_PER_S)
    linear, angular = speeds(trajectory, 30.0)
    assert linear.min() >= 0.004 and linear.max() <= 0.020
    assert math.degrees(angular.max()) < 25.0
    # Smooth: speed changes by less than 1 mm/s per 10 ms step.
    assert np.max(np.abs(np.diff(linear))) < 1e-3
    positions = trajectory.poses_at(np.arange(0, 30 * NS_PER_S, 50_000_000))[:, :3, 3]
    assert scene.field(positions).min() > 0.008  # >= 8 mm from the wall


def test_abdomen_motion_speed() -> None:
    trajectory = AbdomenTrajectory(
        AbdomenGeometry().curvature_radius_m, seed=3, duration_ns=60 * NS_PER_S
    )
    linear, angular = speeds(trajectory, 60.0)
    # A sweep slows down when its components turn round together; rarely.
    assert np.percentile(linear, 5) >= 0.004 and linear.max() <= 0.020
    assert 0.007 <= np.median(linear) <= 0.015
    assert math.degrees(angular.max()) < 25.0


def test_handeye_stations_see_the_board_and_rotate_about_several_axes() -> None:
    from endo_io.camera import CameraModel

    camera = CameraModel.pinhole(640, 480, 320.0, 320.0, 319.5, 239.5)
    board = centred_board()
    stations = handeye_stations(board, camera, seed=5, count=15, fov_radius_px=240.0)
    assert stations.shape == (15, 4, 4)
    axes = []
    for a, b in itertools.pairwise(stations):
        relative = Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).as_rotvec()
        axes.append(relative / np.linalg.norm(relative))
    # Relative rotation axes span 3-D (needed by AX = XB solvers).
    singular = np.linalg.svd(np.array(axes), compute_uv=False)
    assert singular[-1] > 0.1 * singular[0]
    trajectory = handeye_trajectory(stations)
    dwell = trajectory.station_times_ns()
    for k in (0, 7, 14):
        np.testing.assert_allclose(
            trajectory.pose_at(int(dwell[k, 0] + 1000)), stations[k], atol=1e-9
        )


def test_texture_is_deterministic_periodic_and_low_contrast() -> None:
    a = tissue_texture(4, (0.04, 0.03), channels=1)
    b = tissue_texture(4, (0.04, 0.03), channels=1)
    c = tissue_texture(5, (0.04, 0.03), channels=1)
    assert np.array_equal(a.albedo, b.albedo)
    assert not np.array_equal(a.albedo, c.albedo)
    grey = a.albedo[..., 0]
    assert 0.3 < grey.mean() < 0.5
    # Low contrast: most of the field within ±25 % of its median.
    assert np.mean(np.abs(grey / np.median(grey) - 1.0) < 0.25) > 0.95
    uv = np.random.default_rng(0).uniform(0, 0.05, (20, 30, 2))
    valid = np.ones((20, 30), bool)
    shifted = uv + np.array([0.04, -0.03])
    np.testing.assert_allclose(a.sample(uv, valid), a.sample(shifted, valid), atol=1e-6)
    rgb = tissue_texture(4, (0.04, 0.03), channels=3).albedo
    # Vessels absorb green more than red: green has more relative contrast.
    assert np.std(rgb[..., 1]) / rgb[..., 1].mean() > np.std(rgb[..., 0]) / rgb[..., 0].mean()


def test_texture_rejects_bad_shapes() -> None:
    from endo_sim.errors import SimulationParameterError

    with pytest.raises(SimulationParameterError):
        Texture(np.zeros((4, 4), np.float32), (0.1, 0.1))
