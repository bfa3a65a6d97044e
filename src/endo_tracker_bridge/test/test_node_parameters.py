"""Run-time parameter changes of the bridge: each one takes effect, or is refused with a reason.

A real bridge node with its default ``ros`` source on ``/tracker/pose``, a
probe node playing a tracker driver, and the outputs checked number by number
after every ``set_parameters`` (the same callbacks ``ros2 param set`` reaches).
"""

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
from endo_io.pose import matrix_to_pose, pose_to_matrix, rigid_transform
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.node import PARAMETERS, TrackerBridgeNode

pytestmark = pytest.mark.ros

X = rigid_transform([0.1, 2.9, -0.2], [0.004, 0.010, -0.230])
WORLD_TRACKER = rigid_transform([0.3, 0.0, -1.2], [1.0, 2.0, 3.0])
OFFSET_NS = 7_000_000
START_NS = 1_750_000_000_000_000_000
STEP_NS = 20_000_000  # 50 Hz


def _marker(k: int) -> np.ndarray:
    """Marker pose k in metres, 1 mm per step (0.05 m/s at 50 Hz)."""
    return rigid_transform([0.4, -0.3, 0.2 + 1e-3 * k], [0.035 + 1e-3 * k, -0.12, -1.5])


class Rig:
    """The bridge, a driver publishing on any topic, and the bridge's outputs."""

    def __init__(self, context: rclpy.Context) -> None:
        self.bridge = TrackerBridgeNode(context=context)
        self.probe = rclpy.create_node("driver_probe", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.bridge)
        self.executor.add_node(self.probe)
        self.cameras: list[PoseStamped] = []
        self.markers: list[PoseStamped] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.probe.create_subscription(PoseStamped, topics.CAMERA_POSE, self.cameras.append, 50)
        self.probe.create_subscription(PoseStamped, topics.MARKER_POSE, self.markers.append, 50)
        self.probe.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self.diagnostics.append, 10
        )
        self.drivers = {}
        self.k = 0

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def send(self, topic: str = topics.TRACKER_POSE, pose: np.ndarray | None = None) -> int:
        """Publish the next driver sample on ``topic`` until it has been handled; its stamp."""
        if topic not in self.drivers:
            self.drivers[topic] = self.probe.create_publisher(PoseStamped, topic, 10)
        driver = self.drivers[topic]
        deadline = time.monotonic() + 5.0
        while driver.get_subscription_count() == 0 and time.monotonic() < deadline:
            self.spin(0.05)
        self.k += 1
        stamp = START_NS + self.k * STEP_NS
        driver.publish(matrix_to_pose(_marker(self.k) if pose is None else pose, stamp, "tracker"))
        self.spin(0.3)
        return stamp

    def camera_at(self, stamp_ns: int) -> tuple[np.ndarray, PoseStamped] | None:
        """The camera pose published for the driver sample of ``stamp_ns`` (any offset)."""
        for msg in self.markers:
            if pose_to_matrix(msg)[1] == stamp_ns:
                index = self.markers.index(msg)
                return pose_to_matrix(self.cameras[index])[0], self.cameras[index]
        return None

    def dropped(self, cause: str) -> int:
        self.spin(1.2)  # diagnostics are published once a second
        values = {kv.key: kv.value for kv in self.diagnostics[-1].status[0].values}
        return int(values.get(f"dropped.{cause}", 0))


@pytest.fixture
def rig():
    context = rclpy.Context()
    rclpy.init(context=context)
    rig = Rig(context)
    yield rig
    rig.bridge.close()
    rclpy.shutdown(context=context)


def _set(rig: Rig, name: str, value: object):
    return rig.bridge.set_parameters([Parameter(name, value=value)])[0]


def test_defaults_listen_on_the_drivers_topic_and_publish_on_their_own(rig):
    stamp = rig.send()
    found = rig.camera_at(stamp)
    assert found is not None, "no camera pose for a driver pose on /tracker/pose"
    T, msg = found
    np.testing.assert_allclose(T, _marker(rig.k), atol=1e-12)  # identity hand-eye and world
    assert msg.header.frame_id == "world" and rig.markers[-1].header.frame_id == "tracker"
    # Every parameter of the table can change at run time (none is read-only).
    assert not any(spec.read_only for spec in PARAMETERS)


def test_transform_handeye_and_frames_take_effect(rig, tmp_path):
    rows = [float(v) for v in WORLD_TRACKER.ravel()]
    assert _set(rig, "T_world_tracker", rows).successful
    stamp = rig.send()
    np.testing.assert_allclose(rig.camera_at(stamp)[0], WORLD_TRACKER @ _marker(rig.k), atol=1e-12)

    calibration = tmp_path / "handeye.yaml"
    HandEyeCalibration(T_marker_camera=X, time_offset_ns=OFFSET_NS).save(calibration)
    assert _set(rig, "handeye_file", str(calibration)).successful
    stamp = rig.send()
    T, msg = rig.camera_at(stamp)
    np.testing.assert_allclose(T, WORLD_TRACKER @ _marker(rig.k) @ X, atol=1e-12)
    assert pose_to_matrix(msg)[1] == stamp - OFFSET_NS

    assert _set(rig, "world_frame", "map").successful
    assert _set(rig, "tracker_frame", "polaris").successful
    stamp = rig.send()
    assert rig.camera_at(stamp)[1].header.frame_id == "map"
    assert rig.markers[-1].header.frame_id == "polaris"

    # Values that cannot work are refused with the reason; nothing changes.
    result = _set(rig, "handeye_file", str(tmp_path / "missing.yaml"))
    assert not result.successful and "missing.yaml" in result.reason
    result = _set(rig, "T_world_tracker", [1.0, 0.0, 0.0])
    assert not result.successful and "16 row-major" in result.reason
    result = _set(rig, "T_world_tracker", [2.0 * v for v in rows])
    assert not result.successful and "T_world_tracker" in result.reason
    stamp = rig.send()
    T, msg = rig.camera_at(stamp)
    np.testing.assert_allclose(T, WORLD_TRACKER @ _marker(rig.k) @ X, atol=1e-12)
    assert rig.bridge.get_parameter("handeye_file").value == str(calibration)


def test_speed_limits_take_effect(rig):
    rig.send()
    # 0.05 m/s is under the default 2 m/s; a 0.01 m/s limit refuses the next step.
    assert _set(rig, "max_speed_m_s", 0.01).successful
    stamp = rig.send()
    assert rig.camera_at(stamp) is None
    assert rig.dropped("SpeedLimitError") == 1
    assert _set(rig, "max_speed_m_s", 1).successful  # an integer for the double
    assert rig.bridge.parameters["max_speed_m_s"] == 1.0
    stamp = rig.send()
    assert rig.camera_at(stamp) is not None
    result = _set(rig, "max_speed_m_s", 0.0)
    assert not result.successful and "out of range" in result.reason


def test_input_topic_and_unit_changes_take_effect(rig):
    assert _set(rig, "ros_topic", "/driver/pose").successful
    before = len(rig.cameras)
    rig.send(topics.TRACKER_POSE)  # the old topic is no longer read
    assert len(rig.cameras) == before
    stamp = rig.send("/driver/pose")
    assert rig.camera_at(stamp) is not None
    # The bridge's own outputs are refused as its input.
    for output in (topics.CAMERA_POSE, topics.MARKER_POSE):
        result = _set(rig, "ros_topic", output)
        assert not result.successful and "the bridge's own output" in result.reason
    assert rig.bridge.get_parameter("ros_topic").value == "/driver/pose"
    # Millimetres: the driver's numbers are divided by 1000.
    assert _set(rig, "ros_unit", "mm").successful
    pose_mm = _marker(rig.k + 1)
    pose_mm[:3, 3] *= 1000.0
    stamp = rig.send("/driver/pose", pose_mm)
    T, _ = rig.camera_at(stamp)
    np.testing.assert_allclose(T, _marker(rig.k), atol=1e-12)
    result = _set(rig, "ros_unit", "km")
    assert not result.successful and "'km' is not one of m, mm" in result.reason


def test_a_new_source_replaces_the_old_one(rig, tmp_path):
    rig.send()
    log = tmp_path / "track.csv"
    lines = ["time_ns,tool,x,y,z,qx,qy,qz,qw"]
    lines += [f"{2_000_000_000 + i * 10_000_000},scope,{i},0,0,0,0,0,1" for i in range(5)]
    log.write_text("\n".join(lines) + "\n")
    result = rig.bridge.set_parameters_atomically([
        Parameter("source", value="csv"), Parameter("csv_path", value=str(log)),
        Parameter("csv_unit", value="mm"), Parameter("csv_rate", value=0.0),
    ])
    assert result.successful, result.reason
    rig.spin(1.0)
    csv_stamps = [pose_to_matrix(m)[1] for m in rig.markers[-5:]]
    assert csv_stamps == [2_000_000_000 + i * 10_000_000 for i in range(5)]
    np.testing.assert_allclose(pose_to_matrix(rig.cameras[-1])[0][:3, 3], [0.004, 0.0, 0.0])
    # The ros subscription is gone with the old source.
    before = len(rig.cameras)
    rig.send(topics.TRACKER_POSE)
    assert len(rig.cameras) == before
    # A log that cannot be read is refused, and the csv source stays.
    result = _set(rig, "csv_path", str(tmp_path / "absent.csv"))
    assert not result.successful and "absent.csv" in result.reason
    assert rig.bridge.get_parameter("csv_path").value == str(log)
    # Back to ros: the driver's poses are read again (a fresh gate: no time-order clash).
    assert _set(rig, "source", "ros").successful
    stamp = rig.send()
    assert rig.camera_at(stamp) is not None
    result = _set(rig, "source", "serial")
    assert not result.successful and "'serial' is not one of ros, igtl, ndi, csv" in result.reason
