"""Units, quaternion order, the transform chain and the stamp correction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_io.pose import rigid_transform
from endo_tracker_bridge.composition import (
    compose_camera_pose,
    corrected_stamp_ns,
)
from endo_tracker_bridge.conventions import (
    LengthUnit,
    quaternion_wxyz_to_xyzw,
    quaternion_xyzw_to_wxyz,
    transform_from_matrix,
    transform_from_quaternion,
)
from endo_tracker_bridge.errors import StampCorrectionError, TrackerSourceError


def test_millimetres_become_metres():
    T = transform_from_quaternion(
        np.array([0.0, 0.0, 0.0, 1.0]), np.array([12.5, -40.0, 1500.0]), LengthUnit.MILLIMETRE
    )
    np.testing.assert_allclose(T[:3, 3], [0.0125, -0.040, 1.5], atol=1e-15)
    T_m = transform_from_quaternion(
        np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.5, 0.25, 2.0]), LengthUnit.METRE
    )
    np.testing.assert_allclose(T_m[:3, 3], [0.5, 0.25, 2.0])


def test_matrix_in_millimetres_becomes_metres_and_rotation_is_kept():
    R = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = [100.0, 200.0, -300.0]
    T = transform_from_matrix(M.astype(np.float32), LengthUnit.MILLIMETRE)
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, -0.3], rtol=1e-6)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-6)
    # float32 input is projected back onto an exact rotation
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-14)


def test_length_unit_parsing():
    assert LengthUnit.parse("MM") is LengthUnit.MILLIMETRE
    assert LengthUnit.parse(" m ") is LengthUnit.METRE
    with pytest.raises(TrackerSourceError, match="unknown length unit"):
        LengthUnit.parse("cm")


def test_w_first_quaternion_is_reordered_to_xyzw():
    # 90° about z: w-first (cos45°, 0, 0, sin45°) must rotate x onto y.
    half = np.sqrt(0.5)
    q_wxyz = np.array([half, 0.0, 0.0, half])
    q_xyzw = quaternion_wxyz_to_xyzw(q_wxyz)
    np.testing.assert_allclose(q_xyzw, [0.0, 0.0, half, half])
    T = transform_from_quaternion(q_xyzw, np.zeros(3), LengthUnit.METRE)
    np.testing.assert_allclose(T[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    # and a general rotation agrees with scipy (x, y, z, w order)
    rotation = Rotation.from_euler("zyx", [33, -71, 12], degrees=True)
    q_ndi = quaternion_xyzw_to_wxyz(rotation.as_quat())
    assert q_ndi[0] == pytest.approx(rotation.as_quat()[3])
    T = transform_from_quaternion(quaternion_wxyz_to_xyzw(q_ndi), np.zeros(3), LengthUnit.METRE)
    np.testing.assert_allclose(T[:3, :3], rotation.as_matrix(), atol=1e-12)
    # reading a w-first quaternion as if it were x,y,z,w gives a different rotation
    wrong = transform_from_quaternion(q_ndi, np.zeros(3), LengthUnit.METRE)
    assert np.max(np.abs(wrong[:3, :3] - rotation.as_matrix())) > 0.1


def test_composition_order_world_tracker_marker_camera():
    T_world_tracker = rigid_transform([0.0, 0.0, np.pi / 2], [1.0, 2.0, 0.5])
    T_tracker_marker = rigid_transform([0.3, -0.2, 0.1], [0.10, -0.05, 0.90])
    T_marker_camera = rigid_transform([np.pi, 0.0, 0.0], [0.0, 0.02, -0.15])
    T_world_camera = compose_camera_pose(T_world_tracker, T_tracker_marker, T_marker_camera)

    # Follow a point on the camera's optical axis through each frame by hand.
    p_camera = np.array([0.0, 0.0, 0.05, 1.0])
    p_marker = T_marker_camera @ p_camera
    p_tracker = T_tracker_marker @ p_marker
    p_world = T_world_tracker @ p_tracker
    np.testing.assert_allclose(T_world_camera @ p_camera, p_world, atol=1e-14)
    # camera origin in the world, written out
    R_wt, t_wt = T_world_tracker[:3, :3], T_world_tracker[:3, 3]
    R_tm, t_tm = T_tracker_marker[:3, :3], T_tracker_marker[:3, 3]
    expected_origin = R_wt @ (R_tm @ T_marker_camera[:3, 3] + t_tm) + t_wt
    np.testing.assert_allclose(T_world_camera[:3, 3], expected_origin, atol=1e-14)
    # any other order is a different pose
    reversed_chain = T_marker_camera @ T_tracker_marker @ T_world_tracker
    assert np.linalg.norm(reversed_chain[:3, 3] - T_world_camera[:3, 3]) > 0.1


def test_identity_world_tracker_and_hand_eye_give_the_marker_pose():
    T_tracker_marker = rigid_transform([0.1, 0.2, 0.3], [0.01, 0.02, 0.03])
    np.testing.assert_allclose(
        compose_camera_pose(np.eye(4), T_tracker_marker, np.eye(4)), T_tracker_marker
    )


def test_stamp_correction_subtracts_the_offset():
    # tracker stamps 21.5 ms late: the camera-clock stamp is 21.5 ms earlier
    assert corrected_stamp_ns(1_700_000_000_123_456_789, 21_500_000) == 1_700_000_000_101_956_789
    # a tracker that stamps early (negative offset) moves the stamp later
    assert corrected_stamp_ns(5_000_000_000, -3_000_000) == 5_003_000_000
    assert corrected_stamp_ns(5_000_000_000, 0) == 5_000_000_000
    with pytest.raises(StampCorrectionError, match="negative"):
        corrected_stamp_ns(1_000, 2_000)
