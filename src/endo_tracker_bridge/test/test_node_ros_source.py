"""The bridge node with source=ros: a driver's millimetre poses in, both outputs checked."""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from endo_io import topics
from endo_io.errors import ParameterValidationError
from endo_io.pose import matrix_to_pose, pose_to_matrix, rigid_transform
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.node import TrackerBridgeNode

pytestmark = pytest.mark.ros

OFFSET_NS = -4_000_000  # a tracker whose clock runs 4 ms ahead of the camera's



X = rigid_transform([0.1, 2.9, -0.2], [0.004, 0.010, -0.230])
WORLD_TRACKER = rigid_transform([0.3, 0.0, -1.2], [1.0, 2.0, 3.0])


def test_ros_source_in_millimetres(tmp_path):
    calibration = tmp_path / "handeye.yaml"
    HandEyeCalibration(T_marker_camera=X, time_offset_ns=OFFSET_NS).save(calibration)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        bridge = TrackerBridgeNode(
            context=context,
            parameter_overrides=[
                Parameter("source", value="ros"),
                Parameter("ros_topic", value="/driver/pose"),
                Parameter("ros_unit", value="mm"),
                Parameter("ros_frame_id", value="polaris"),
                Parameter("handeye_file", value=str(calibration)),
                Parameter("T_world_tracker", value=[float(v) for v in WORLD_TRACKER.ravel()]),
            ],
        )
        probe = rclpy.create_node("probe", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(bridge)
        executor.add_node(probe)
        driver = probe.create_publisher(PoseStamped, "/driver/pose", 10)
        received: dict[str, list[PoseStamped]] = {topics.MARKER_POSE: [], topics.CAMERA_POSE: []}
        diagnostics: list[DiagnosticArray] = []
        for topic, bucket in received.items():
            probe.create_subscription(PoseStamped, topic, bucket.append, 10)
        probe.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)

        def spin(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.02)

        marker_mm = rigid_transform([0.4, -0.3, 0.2], [35.0, -120.0, -1500.0])
        stamp_ns = 1_750_000_000_000_000_000
        end = time.monotonic() + 10.0
        k = 0
        while not received[topics.CAMERA_POSE] and time.monotonic() < end:
            msg = matrix_to_pose(marker_mm, stamp_ns + k * 16_000_000, "polaris")
            driver.publish(msg)
            k += 1
            spin(0.1)
        # bad inputs: wrong frame, backwards stamp, NaN, non-unit quaternion
        driver.publish(matrix_to_pose(marker_mm, stamp_ns + (k + 1) * 16_000_000, "camera"))
        driver.publish(matrix_to_pose(marker_mm, stamp_ns, "polaris"))
        nan_msg = matrix_to_pose(marker_mm, stamp_ns + (k + 2) * 16_000_000, "polaris")
        nan_msg.pose.position.y = float("nan")
        driver.publish(nan_msg)
        long_q = matrix_to_pose(marker_mm, stamp_ns + (k + 3) * 16_000_000, "polaris")
        long_q.pose.orientation.w *= 1.2
        driver.publish(long_q)
        spin(1.5)
        bridge.close()
    finally:
        rclpy.shutdown(context=context)

    marker = received[topics.MARKER_POSE][0]
    T_marker, marker_stamp = pose_to_matrix(marker)
    assert marker.header.frame_id == "tracker"
    np.testing.assert_allclose(T_marker[:3, 3], marker_mm[:3, 3] / 1000.0, atol=1e-12)
    np.testing.assert_allclose(T_marker[:3, :3], marker_mm[:3, :3], atol=1e-12)

    camera = received[topics.CAMERA_POSE][0]
    T_camera, camera_stamp = pose_to_matrix(camera)
    assert camera.header.frame_id == "world"
    assert camera_stamp == marker_stamp - OFFSET_NS
    T_tracker_marker = marker_mm.copy()
    T_tracker_marker[:3, 3] /= 1000.0
    np.testing.assert_allclose(T_camera, WORLD_TRACKER @ T_tracker_marker @ X, atol=1e-12)

    values = {kv.key: kv.value for kv in diagnostics[-1].status[0].values}
    for cause in (
        "UnexpectedFrameError",
        "TimeWentBackwardsError",
        "NonFinitePoseError",
        "NonUnitQuaternionError",
    ):
        assert values[f"dropped.{cause}"] == "1", values


def test_bad_configuration_is_refused_with_a_named_error(tmp_path):
    from endo_tracker_bridge.errors import HandEyeFileError, TrackerSourceError

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        with pytest.raises(ParameterValidationError, match="'serial' is not one of ros, igtl"):
            TrackerBridgeNode(
                context=context, parameter_overrides=[Parameter("source", value="serial")]
            )
        with pytest.raises(TrackerSourceError, match="16 row-major"):
            TrackerBridgeNode(
                context=context,
                parameter_overrides=[Parameter("T_world_tracker", value=[1.0, 0.0])],
            )
        with pytest.raises(HandEyeFileError):
            TrackerBridgeNode(
                context=context,
                parameter_overrides=[Parameter("handeye_file", value=str(tmp_path / "none.yaml"))],
            )
        for output in (topics.MARKER_POSE, topics.CAMERA_POSE, "marker_pose"):
            with pytest.raises(ParameterValidationError, match="the bridge's own output"):
                TrackerBridgeNode(
                    context=context, namespace="/tracker",
                    parameter_overrides=[Parameter("ros_topic", value=output)],
                )
    finally:
        rclpy.shutdown(context=context)
