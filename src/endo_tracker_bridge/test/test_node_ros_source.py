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


def _values(diagnostics: DiagnosticArray) -> dict[str, str]:
    return {kv.key: kv.value for kv in diagnostics.status[0].values}


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

        def spin_until(condition, seconds):
            end = time.monotonic() + seconds
            while not condition() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.02)

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
        # bad inputs: wrong frame, NaN, non-unit quaternion, a repeated stamp; a
        # stamp back to the start is a restart of the stream (a clock jump), not a drop
        # (in two bursts: the bridge's sensor-data subscription keeps the last 5)
        health = bridge._health
        driver.publish(matrix_to_pose(marker_mm, stamp_ns + (k + 1) * 16_000_000, "polaris"))
        driver.publish(matrix_to_pose(marker_mm, stamp_ns + (k + 2) * 16_000_000, "camera"))
        driver.publish(matrix_to_pose(marker_mm, stamp_ns, "polaris"))
        spin_until(lambda: health.clock_jumps == 1, 10.0)
        nan_msg = matrix_to_pose(marker_mm, stamp_ns + (k + 3) * 16_000_000, "polaris")
        nan_msg.pose.position.y = float("nan")
        driver.publish(nan_msg)
        long_q = matrix_to_pose(marker_mm, stamp_ns + (k + 4) * 16_000_000, "polaris")
        long_q.pose.orientation.w *= 1.2
        driver.publish(long_q)
        for _ in range(2):
            driver.publish(matrix_to_pose(marker_mm, stamp_ns + (k + 5) * 16_000_000, "polaris"))
        spin_until(lambda: sum(health.dropped.values()) >= 4, 10.0)
        spin_until(lambda: diagnostics and _values(diagnostics[-1])["dropped"] == "4", 10.0)
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

    values = _values(diagnostics[-1])
    for cause in (
        "UnexpectedFrameError",
        "TimeWentBackwardsError",
        "NonFinitePoseError",
        "NonUnitQuaternionError",
    ):
        assert values[f"dropped.{cause}"] == "1", values
    assert values["clock_jumps"] == "1" and values["dropped"] == "4", values


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


def test_a_loop_seen_as_a_0_7_s_step_back_is_one_warning_and_no_pose_is_lost(capfd):
    # issue 16: a bridge respawned under load saw a looped bag as a 0.7 s step back and
    # logged [ERROR] TimeWentBackwardsError, dropping that pose, until the next confirmed it
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        bridge = TrackerBridgeNode(context=context, parameter_overrides=[
            Parameter("ros_topic", value="/driver/pose")])
        probe = rclpy.create_node("probe", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(bridge)
        executor.add_node(probe)
        driver = probe.create_publisher(PoseStamped, "/driver/pose", 10)
        published: list[PoseStamped] = []
        diagnostics: list[DiagnosticArray] = []
        probe.create_subscription(PoseStamped, topics.CAMERA_POSE, published.append, 200)
        probe.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)

        def spin_until(condition, seconds=10.0):
            end = time.monotonic() + seconds
            while not condition() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.02)
            return condition()

        assert spin_until(lambda: driver.get_subscription_count() > 0
                          and probe.count_publishers(topics.CAMERA_POSE) > 0)
        stamps = [1_800_000_000_000_000_000 + k * 16_666_667 for k in range(60)]
        stamps += [stamps[-1] - 700_000_000 + k * 16_666_667 for k in range(30)]
        health = bridge._health
        for k, stamp in enumerate(stamps):
            T = rigid_transform([0.0, 0.0, 0.0], [0.0005 * (k % 60), 0.0, 1.0])
            driver.publish(matrix_to_pose(T, stamp, "tracker"))
            assert spin_until(lambda k=k: health.processed + sum(health.dropped.values()) > k)
        assert spin_until(lambda: len(published) == len(stamps))
        assert spin_until(lambda: bool(diagnostics)
                          and _values(diagnostics[-1])["processed"] == str(len(stamps)))
        bridge.close()
    finally:
        rclpy.shutdown(context=context)
    values = _values(diagnostics[-1])
    assert values["clock_jumps"] == "1" and values["dropped"] == "0", values
    assert [pose_to_matrix(msg)[1] for msg in published] == stamps  # every pose, in order
    err = capfd.readouterr().err
    assert "[ERROR]" not in err, err[-2000:]
    jumps = [line for line in err.splitlines() if "clock jump" in line]
    assert len(jumps) == 1 and jumps[0].startswith("[WARN]"), err[-2000:]
    assert "time jumped back 0.700 s" in jumps[0] and "its history was reset" in jumps[0]
