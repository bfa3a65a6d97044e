"""The bridge's live /tf and /tf_static: what it sends, when, and what happens without tf2_msgs.

A real bridge node (default ``ros`` source), a probe node playing the tracker
driver, and the bridge's /endoscope/pose as the reference. Two halves:

* What the bridge sends. Where tf2_msgs is importable the bridge's
  :class:`endo_io.tf_broadcast.TfBroadcaster` publishes ``TFMessage``; the
  pip-only install has no tf2_msgs, so here the broadcaster is replaced by a
  recorder at that seam (the node is otherwise real). Every edge it is given
  is turned into the ``geometry_msgs/TransformStamped`` that would go out
  (:func:`endo_io.tf.transform_stamped`, the broadcaster's own conversion)
  and checked against the published camera pose, T_world_tracker and the
  hand–eye file to 1e-12, with its stamp and frames.
* The real broadcaster: pip-only it logs exactly one info line and sends
  nothing, and the diagnostics say so; on a full ROS install (tf2_msgs
  importable) a listener receives the same transforms over DDS. Only one of
  these two can run on a given install; the other is skipped with its reason.
"""

from __future__ import annotations

import importlib.util
import time
from typing import Any

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TransformStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from endo_io import topics
from endo_io.pose import invert_transform, matrix_to_pose, pose_to_matrix, rigid_transform
from endo_io.tf import StampedTransform, tf_qos, transform_stamped
from endo_io.tf_broadcast import NO_TF2_MSGS, TfBroadcaster, tf_message_class
from endo_tracker_bridge import node as bridge_node
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.node import TrackerBridgeNode

pytestmark = pytest.mark.ros

X = rigid_transform([0.1, 2.9, -0.2], [0.004, 0.010, -0.230])  # T_marker_camera
WORLD_TRACKER = rigid_transform([0.3, 0.0, -1.2], [1.0, 2.0, 3.0])
OFFSET_NS = 7_000_000
START_NS = 1_750_000_000_000_000_000
STEP_NS = 20_000_000  # 50 Hz
HAVE_TF2_MSGS = importlib.util.find_spec("tf2_msgs") is not None


def _marker(k: int) -> np.ndarray:
    """Marker pose k in metres, 1 mm per step (0.05 m/s at 50 Hz)."""
    return rigid_transform([0.4, -0.3, 0.2 + 1e-3 * k], [0.035 + 1e-3 * k, -0.12, -1.5])


def _message_matrix(msg: TransformStamped) -> tuple[np.ndarray, int, str, str]:
    """(4, 4) transform, stamp ns, parent and child frame of a TransformStamped."""
    pose = PoseStamped()
    pose.header = msg.header
    t, q = msg.transform.translation, msg.transform.rotation
    pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = t.x, t.y, t.z
    pose.pose.orientation.x, pose.pose.orientation.y = q.x, q.y
    pose.pose.orientation.z, pose.pose.orientation.w = q.z, q.w
    T, stamp = pose_to_matrix(pose)
    return T, stamp, msg.header.frame_id, msg.child_frame_id


class RecordingBroadcaster:
    """Stands in for TfBroadcaster where tf2_msgs is importable: keeps what it is given."""

    available = True

    def __init__(self, node: Any) -> None:
        self.sent: list[list[StampedTransform]] = []
        self.static: list[list[StampedTransform]] = []
        self.closed = False

    def send(self, edges: list[StampedTransform]) -> None:
        self.sent.append(list(edges))

    def send_static(self, edges: list[StampedTransform]) -> None:
        self.static.append(list(edges))

    def close(self) -> None:
        self.closed = True


class Rig:
    """The bridge, a driver on /tracker/pose, the bridge's outputs."""

    def __init__(self, context: rclpy.Context) -> None:
        self.bridge = TrackerBridgeNode(context=context)
        self.probe = rclpy.create_node("driver_probe", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.bridge)
        self.executor.add_node(self.probe)
        self.cameras: list[PoseStamped] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.probe.create_subscription(PoseStamped, topics.CAMERA_POSE, self.cameras.append, 50)
        self.probe.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self.diagnostics.append, 10
        )
        self.driver = self.probe.create_publisher(PoseStamped, topics.TRACKER_POSE, 10)
        self.k = 0

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def send(self) -> PoseStamped:
        """Publish the next driver sample; the camera pose the bridge published for it."""
        deadline = time.monotonic() + 5.0
        while self.driver.get_subscription_count() == 0 and time.monotonic() < deadline:
            self.spin(0.05)
        self.k += 1
        count = len(self.cameras)
        self.driver.publish(matrix_to_pose(_marker(self.k), START_NS + self.k * STEP_NS, "tracker"))
        deadline = time.monotonic() + 5.0
        while len(self.cameras) == count and time.monotonic() < deadline:
            self.spin(0.02)
        assert len(self.cameras) == count + 1, "the bridge published no camera pose"
        return self.cameras[-1]

    def set(self, name: str, value: object) -> bool:
        return self.bridge.set_parameters([Parameter(name, value=value)])[0].successful

    def status_value(self, key: str) -> str:
        self.spin(1.2)  # diagnostics are published once a second
        values = {kv.key: kv.value for kv in self.diagnostics[-1].status[0].values}
        return values[key]


@pytest.fixture
def context():
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.shutdown(context=context)


@pytest.fixture
def recording_rig(context, monkeypatch):
    monkeypatch.setattr(bridge_node, "TfBroadcaster", RecordingBroadcaster)
    rig = Rig(context)
    yield rig
    rig.bridge.close()


def _static_matrices(edges: list[StampedTransform]) -> dict[tuple[str, str], np.ndarray]:
    found = {}
    for edge in edges:
        T, _, parent, child = _message_matrix(transform_stamped(edge))
        found[(parent, child)] = T
    return found


def test_camera_and_static_transforms_equal_the_poses(recording_rig, tmp_path):
    rig = recording_rig
    tf = rig.bridge.tf_broadcaster
    assert isinstance(tf, RecordingBroadcaster)
    # At start: the identity transform and hand-eye the bridge composes with.
    (start,) = tf.static
    assert set(_static_matrices(start)) == {
        ("world", "tracker"), ("endoscope_optical_frame", "endoscope_marker")
    }
    for T in _static_matrices(start).values():
        np.testing.assert_allclose(T, np.eye(4), atol=1e-12)

    calibration = tmp_path / "handeye.yaml"
    HandEyeCalibration(T_marker_camera=X, time_offset_ns=OFFSET_NS).save(calibration)
    assert rig.set("T_world_tracker", [float(v) for v in WORLD_TRACKER.ravel()])
    assert rig.set("handeye_file", str(calibration))
    assert len(tf.static) == 3  # re-sent after each change, complete each time
    static = _static_matrices(tf.static[-1])
    np.testing.assert_allclose(static[("world", "tracker")], WORLD_TRACKER, atol=1e-12)
    np.testing.assert_allclose(
        static[("endoscope_optical_frame", "endoscope_marker")], invert_transform(X), atol=1e-12
    )

    for _ in range(3):
        before = len(tf.sent)
        camera = rig.send()
        assert len(tf.sent) == before + 1
        (edge,) = tf.sent[-1]
        T, stamp, parent, child = _message_matrix(transform_stamped(edge))
        T_camera, camera_stamp = pose_to_matrix(camera)
        assert (parent, child) == ("world", "endoscope_optical_frame")
        assert stamp == camera_stamp == START_NS + rig.k * STEP_NS - OFFSET_NS
        np.testing.assert_allclose(T, T_camera, atol=1e-12)
        np.testing.assert_allclose(T, WORLD_TRACKER @ _marker(rig.k) @ X, atol=1e-12)
        # The composed static chain gives the same camera: world→tracker→marker→camera.
        np.testing.assert_allclose(
            static[("world", "tracker")] @ _marker(rig.k)
            @ invert_transform(static[("endoscope_optical_frame", "endoscope_marker")]),
            T, atol=1e-12,
        )


def test_frame_names_and_publish_tf_take_effect(recording_rig):
    rig = recording_rig
    tf = rig.bridge.tf_broadcaster
    assert isinstance(tf, RecordingBroadcaster)
    assert rig.set("world_frame", "map")
    assert rig.set("camera_frame", "scope_optical_frame")
    assert set(_static_matrices(tf.static[-1])) == {
        ("map", "tracker"), ("scope_optical_frame", "endoscope_marker")
    }
    rig.send()
    (edge,) = tf.sent[-1]
    assert (edge.parent_frame, edge.child_frame) == ("map", "scope_optical_frame")

    # A frame that would be its own parent is refused, and nothing changes.
    sent_static = len(tf.static)
    assert not rig.set("camera_frame", "map")
    assert rig.bridge.get_parameter("camera_frame").value == "scope_optical_frame"
    assert len(tf.static) == sent_static
    assert not rig.set("world_frame", "")

    # publish_tf off: the broadcaster is closed and poses still go out, without /tf.
    assert rig.set("publish_tf", False)
    assert tf.closed and rig.bridge.tf_broadcaster is None
    sent = len(tf.sent)
    rig.send()
    assert len(tf.sent) == sent
    assert rig.status_value("tf") == "off"
    # ... and on again: a new broadcaster with the static edges at once.
    assert rig.set("publish_tf", True)
    again = rig.bridge.tf_broadcaster
    assert isinstance(again, RecordingBroadcaster) and again is not tf
    assert set(_static_matrices(again.static[-1])) == {
        ("map", "tracker"), ("scope_optical_frame", "endoscope_marker")
    }


def test_tf_qos_is_tf2_ros_broadcasters():
    dynamic, static = tf_qos(static=False), tf_qos(static=True)
    assert (dynamic.depth, dynamic.reliability.name, dynamic.durability.name) == (
        100, "RELIABLE", "VOLATILE"
    )
    assert (static.depth, static.reliability.name, static.durability.name) == (
        1, "RELIABLE", "TRANSIENT_LOCAL"
    )


@pytest.mark.skipif(HAVE_TF2_MSGS, reason="tf2_msgs is importable: the DDS test below runs")
def test_without_tf2_msgs_one_info_line_and_nothing_sent(context, capfd):
    assert tf_message_class() is None
    rig = Rig(context)
    try:
        tf = rig.bridge.tf_broadcaster
        assert isinstance(tf, TfBroadcaster) and not tf.available
        rig.send()
        rig.send()
        assert rig.status_value("tf") == "not published (no tf2_msgs)"
        names = {name for name, _ in rig.probe.get_topic_names_and_types()}
        assert topics.TF not in names and topics.TF_STATIC not in names
    finally:
        rig.bridge.close()
    output = capfd.readouterr()
    lines = [line for line in (output.out + output.err).splitlines() if NO_TF2_MSGS in line]
    assert len(lines) == 1 and "[INFO]" in lines[0], output.err[-2000:]


@pytest.mark.skipif(not HAVE_TF2_MSGS, reason="tf2_msgs is not importable (pip-only install)")
def test_with_tf2_msgs_a_listener_receives_the_transforms(context, tmp_path):
    tf_message_type = tf_message_class()
    assert tf_message_type is not None
    rig = Rig(context)
    received: dict[str, list[Any]] = {topics.TF: [], topics.TF_STATIC: []}
    for topic in received:
        rig.probe.create_subscription(
            tf_message_type, topic, received[topic].append,
            tf_qos(static=topic == topics.TF_STATIC),
        )
    try:
        assert rig.set("T_world_tracker", [float(v) for v in WORLD_TRACKER.ravel()])
        cameras = [rig.send() for _ in range(3)]
        rig.spin(0.5)
    finally:
        rig.bridge.close()
    static = {
        (parent, child): T
        for msg in received[topics.TF_STATIC][-1:]
        for T, _, parent, child in map(_message_matrix, msg.transforms)
    }
    np.testing.assert_allclose(static[("world", "tracker")], WORLD_TRACKER, atol=1e-12)
    by_stamp = {
        stamp: T
        for msg in received[topics.TF]
        for T, stamp, parent, child in map(_message_matrix, msg.transforms)
        if (parent, child) == ("world", "endoscope_optical_frame")
    }
    for camera in cameras:
        T_camera, stamp = pose_to_matrix(camera)
        np.testing.assert_allclose(by_stamp[stamp], T_camera, atol=1e-12)
