"""CameraPoseChain: the bridge's gate → compose → restamp chain, ROS-free."""

from __future__ import annotations

import numpy as np
import pytest

from endo_io.pose import rigid_transform
from endo_tracker_bridge.chain import CameraPoseChain
from endo_tracker_bridge.errors import SpeedLimitError, TimeWentBackwardsError
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.sample import TrackerSample
from endo_tracker_bridge.validation import SpeedLimits


def _chain() -> tuple[CameraPoseChain, np.ndarray, np.ndarray]:
    T_marker_camera = rigid_transform([0.1, -0.2, 0.3], [0.01, 0.02, 0.3])
    T_world_tracker = rigid_transform([0.0, 0.5, 0.0], [0.1, 0.0, -1.0])
    calibration = HandEyeCalibration(T_marker_camera=T_marker_camera, time_offset_ns=25_000_000)
    return CameraPoseChain(calibration, T_world_tracker), T_marker_camera, T_world_tracker


def test_accepted_sample_gives_the_composed_pose_on_the_camera_clock() -> None:
    chain, T_marker_camera, T_world_tracker = _chain()
    T_tracker_marker = rigid_transform([0.3, 0.1, -0.2], [0.05, -0.02, 1.2])
    pose = chain.accept(TrackerSample(1_000_000_000, T_tracker_marker))
    # x_world = T_world_tracker · T_tracker_marker · T_marker_camera · x_camera
    point_camera = np.array([0.01, -0.02, 0.05, 1.0])
    expected = T_world_tracker @ (T_tracker_marker @ (T_marker_camera @ point_camera))
    np.testing.assert_allclose(pose.T_world_camera @ point_camera, expected, atol=1e-12)
    assert pose.stamp_ns == 1_000_000_000 - 25_000_000


def test_the_gate_rejects_time_going_backwards_and_jumps() -> None:
    chain = CameraPoseChain(HandEyeCalibration.identity(), limits=SpeedLimits(linear_m_s=1.0))
    chain.accept(TrackerSample(1_000_000_000, np.eye(4)))
    with pytest.raises(TimeWentBackwardsError):
        chain.accept(TrackerSample(1_000_000_000, np.eye(4)))
    jump = np.eye(4)
    jump[0, 3] = 0.1  # 10 cm in 10 ms: 10 m/s
    with pytest.raises(SpeedLimitError):
        chain.accept(TrackerSample(1_010_000_000, jump))
    chain.reset()
    assert chain.accept(TrackerSample(1_010_000_000, jump)).stamp_ns == 1_010_000_000
