"""endo-tracker-bridge as an OpenIGTLink client of a real pyigtl server, over loopback.

The test process runs a pyigtl ``OpenIGTLinkServer`` on 127.0.0.1 that
streams TRANSFORM messages in millimetres, as PLUS does. The bridge runs as
its own OS process (the console script) and publishes ``/endoscope/pose``
over DDS; the test receives it and checks every number: the unit
conversion, T_world_tracker · T_tracker_marker · T_marker_camera, and the
stamp corrected by the calibrated offset. Then the server goes away and a
new one comes up on the same port: the same bridge process reconnects and
carries on. A NaN transform on the way is dropped and counted on
/diagnostics without stopping anything.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyigtl
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor

from endo_io.pose import pose_to_matrix, rigid_transform
from endo_tracker_bridge.handeye_file import HandEyeCalibration

pytestmark = pytest.mark.ros

BRIDGE = Path(sys.executable).with_name("endo-tracker-bridge")
DEVICE = "ScopeToTracker"
OFFSET_NS = 17_250_000  # tracker stamps 17.25 ms late
EPOCH_S = 1_800_000_000



T_MARKER_CAMERA = rigid_transform([0.2, -2.6, 0.3], [0.011, -0.007, -0.245])
T_WORLD_TRACKER = rigid_transform([0.0, 0.0, np.pi / 2], [0.5, -0.25, 1.0])


def _marker_pose_mm(k: int) -> np.ndarray:
    """Marker pose k in millimetres, moving slowly (well inside the speed limits)."""
    T = rigid_transform([0.3 + 0.002 * k, -0.1, 0.05], [100.0 + 0.2 * k, -50.0, -1400.0 + 0.1 * k])
    return T


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class _Listener:
    """Subscribes to /endoscope/pose and /diagnostics in its own rclpy context."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("igtl_bridge_test", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.poses: dict[int, np.ndarray] = {}
        self.frames: set[str] = set()
        self.diagnostics: dict[str, str] = {}
        self.level = b"\x00"
        self.message = ""
        self.node.create_subscription(PoseStamped, "/endoscope/pose", self._on_pose, 50)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_pose(self, msg: PoseStamped) -> None:
        T, stamp_ns = pose_to_matrix(msg)
        self.poses[stamp_ns] = T
        self.frames.add(msg.header.frame_id)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if "tracker_bridge" in status.name:
                self.diagnostics = {kv.key: kv.value for kv in status.values}
                self.level, self.message = status.level, status.message

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def _expected_camera_pose(k: int) -> np.ndarray:
    T_tracker_marker = _marker_pose_mm(k)
    T_tracker_marker[:3, 3] *= 1e-3
    return T_WORLD_TRACKER @ T_tracker_marker @ T_MARKER_CAMERA


def _stream(server, listener, first_k, count, bad_k=None):
    """Send TRANSFORMs first_k..first_k+count-1 at ~100 Hz while spinning the listener."""
    sent = {}
    for k in range(first_k, first_k + count):
        # multiples of 1/64 s are exact in the float seconds pyigtl packs
        stamp_s = EPOCH_S + k / 64
        matrix = np.full((4, 4), np.nan) if k == bad_k else _marker_pose_mm(k)
        server.send_message(
            pyigtl.TransformMessage(matrix, timestamp=stamp_s, device_name=DEVICE), wait=False
        )
        if k != bad_k:
            sent[EPOCH_S * 1_000_000_000 + k * 15_625_000 - OFFSET_NS] = k
        listener.spin(0.01)
    return sent


def _received(listener, stamp_ns):
    """The pose received at ``stamp_ns``; the 2^-32 s wire format allows ±1 ns."""
    for candidate in (stamp_ns, stamp_ns - 1, stamp_ns + 1):
        if candidate in listener.poses:
            return listener.poses[candidate]
    return None


def _wait_for(listener, sent, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and any(_received(listener, s) is None for s in sent):
        listener.spin(0.05)


def _check(listener, sent):
    for stamp_ns, k in sent.items():
        pose = _received(listener, stamp_ns)
        assert pose is not None, f"no /endoscope/pose at tracker stamp - offset for message {k}"
        # float32 on the wire: 1.4 m is good to ~1e-7 m
        np.testing.assert_allclose(pose, _expected_camera_pose(k), atol=2e-6, rtol=0)


def test_igtl_client_publishes_camera_pose_and_survives_a_server_restart(tmp_path):
    port = _free_port()
    calibration = tmp_path / "handeye.yaml"
    HandEyeCalibration(T_marker_camera=T_MARKER_CAMERA, time_offset_ns=OFFSET_NS).save(calibration)
    world_tracker = "[" + ",".join(repr(float(v)) for v in T_WORLD_TRACKER.ravel()) + "]"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    previous_handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    listener = _Listener()
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    bridge = subprocess.Popen(
        [
            str(BRIDGE),
            "--ros-args",
            "-p",
            "source:=igtl",
            "-p",
            f"igtl_port:={port}",
            "-p",
            f"igtl_device:={DEVICE}",
            "-p",
            "igtl_reconnect_interval_s:=0.1",
            "-p",
            f"handeye_file:={calibration}",
            "-p",
            f"T_world_tracker:={world_tracker}",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        # first server: wait until the bridge is connected and discovered
        end, k = time.monotonic() + 20.0, 0
        while time.monotonic() < end and k < 100 and not listener.poses:
            _stream(server, listener, k, 1)
            listener.spin(0.1)
            k += 1
        assert server.is_connected(), "the bridge never connected to the OpenIGTLink server"
        sent = _stream(server, listener, 100, 30, bad_k=110)
        _wait_for(listener, sent, 5.0)
        _check(listener, sent)
        assert listener.frames == {"world"}

        # the server goes away; nothing arrives; the bridge keeps running
        server.stop()
        listener.spin(0.5)
        assert bridge.poll() is None
        before_restart = len(listener.poses)

        # a new server on the same port: the same bridge process reconnects
        server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
        end = time.monotonic() + 10.0
        while time.monotonic() < end and not server.is_connected():
            listener.spin(0.1)
        assert server.is_connected(), "the bridge did not reconnect to the restarted server"
        sent_again = _stream(server, listener, 200, 30)
        _wait_for(listener, sent_again, 5.0)
        _check(listener, sent_again)
        assert len(listener.poses) > before_restart
        assert bridge.poll() is None

        # the NaN transform was dropped and counted; the rest went through
        listener.spin(1.5)
        assert listener.diagnostics.get("dropped.NonFinitePoseError") == "1"
        assert int(listener.diagnostics["connections"]) >= 2
    finally:
        server.stop()
        bridge.send_signal(signal.SIGINT)
        try:
            output, _ = bridge.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            bridge.kill()
            output, _ = bridge.communicate()
        listener.close()
        for sig, handler in previous_handlers.items():
            signal.signal(sig, handler)
        print(output)  # shown by pytest when the test fails
    assert bridge.returncode == 0, output
    assert "connected to OpenIGTLink server" in output


def test_igtl_connection_state_on_diagnostics_follows_the_server():
    # issue 16: with no server the status said OK without a connected key, and
    # 8 s after the server stopped it still said connected: True.
    from diagnostic_msgs.msg import DiagnosticStatus

    port = _free_port()
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    previous_handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    listener = _Listener()
    bridge = subprocess.Popen(
        [str(BRIDGE), "--ros-args", "-p", "source:=igtl", "-p", f"igtl_port:={port}",
         "-p", "igtl_reconnect_interval_s:=0.1"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    server = None

    def wait_for(condition, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not condition():
            listener.spin(0.05)
        return condition()

    try:
        assert wait_for(lambda: listener.diagnostics.get("connected") == "False", 20.0)
        assert listener.level == DiagnosticStatus.WARN
        assert f"not connected to 127.0.0.1:{port}" in listener.message
        server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
        assert wait_for(lambda: listener.diagnostics.get("connected") == "True", 10.0)
        assert "not connected" not in listener.message
        server.stop()
        stopped = time.monotonic()
        assert wait_for(lambda: listener.diagnostics.get("connected") == "False", 5.0)
        assert time.monotonic() - stopped < 2.5
        assert "not connected" in listener.message and listener.level == DiagnosticStatus.WARN
        assert bridge.poll() is None
    finally:
        if server is not None:
            server.stop()
        bridge.send_signal(signal.SIGINT)
        try:
            output, _ = bridge.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            bridge.kill()
            output, _ = bridge.communicate()
        listener.close()
        for sig, handler in previous_handlers.items():
            signal.signal(sig, handler)
        print(output)
    assert bridge.returncode == 0, output
