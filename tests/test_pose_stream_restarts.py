"""The flow node at the start and the restarts of its pose stream (issue 16).

Conditions of normal operation must be a counted warning, never an ``[ERROR]``:

* the first image of a recording (and of every pass of a looped replay)
  precedes the tracker's first pose by a few milliseconds: that frame is
  processed without a pose, counted as ``dropped.PoseBeforeStreamError`` on
  ``/diagnostics`` and logged once as a warning (it was ``PoseTooOldError``,
  an ``[ERROR]`` line, at every loop);
* a pose stream that steps back by less than a second (a loop seen by a
  bridge respawned under load: 0.7 s) restarts the pose buffer, counted as a
  clock jump (it was ``PoseOrderError``, an ``[ERROR]`` and a lost pose).

The node runs in this process over DDS; frames and poses are paced on the
node's own counters (conditions, not sleeps). Its log lines are read from
the process's stderr.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from endo_flow.node import FlowNode
from endo_io import topics
from endo_io.camera import CameraModel
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose, rigid_transform
from endo_io.qos import reliable_qos
from endo_io.stamp import NS_PER_S

pytestmark = pytest.mark.ros

MS = 1_000_000
START_NS = 1_800_000_000 * NS_PER_S
FRAME_NS = NS_PER_S // 30
POSE_NS = NS_PER_S // 60
#: the first pose of each pass is this long after the first image (the phantom bag's 4 ms)
FIRST_POSE_NS = 4 * MS
FRAMES = 36  # 1.2 s: a pass longer than the frames' 1 s jump tolerance
CAMERA = CameraModel.pinhole(160, 120, 120.0, 120.0, 79.5, 59.5)


class Rig:
    """A flow node, a peer publishing its inputs, and what comes back on /diagnostics."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.flow = FlowNode(context=self.context, parameter_overrides=[
            Parameter("tracking_downsample", value=1),
            Parameter("map_enabled", value=False),
            Parameter("newest_frame", value=False),  # every frame, in order
        ])
        self.peer = Node("pose_restart_peer", context=self.context)
        self.status: dict[str, dict[str, str]] = {}
        self.peer.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics,
                                      reliable_qos(50))
        self.pubs = {
            "image": self.peer.create_publisher(Image, topics.IMAGE_CORRECTED, reliable_qos(10)),
            "depth": self.peer.create_publisher(Image, topics.DEPTH_RELATIVE, reliable_qos(10)),
            "info": self.peer.create_publisher(CameraInfo, topics.CAMERA_INFO, reliable_qos(10)),
            "pose": self.peer.create_publisher(PoseStamped, topics.CAMERA_POSE, reliable_qos(10)),
        }
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.flow)
        self.executor.add_node(self.peer)
        texture = np.random.default_rng(5).uniform(0.2, 1.0, (CAMERA.height, CAMERA.width))
        self.image = texture.astype(np.float32)
        self.depth = np.full((CAMERA.height, CAMERA.width), 2.0, np.float32)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.status[status.name] = {kv.key: kv.value for kv in status.values}

    def spin_until(self, condition: Callable[[], bool], seconds: float = 20.0) -> bool:
        deadline = time.monotonic() + seconds
        while not condition() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
        return condition()

    def poses(self, first_ns: int, count: int) -> None:
        """``count`` poses from ``first_ns`` on, each taken by the node before the next."""
        health = self.flow.pose_health
        for k in range(count):
            seen = health.processed + health.clock_jumps + sum(health.dropped.values())
            T = rigid_transform([0.0, 0.0, 0.001 * k], [1e-4 * k, 0.0, 0.0])
            self.pubs["pose"].publish(matrix_to_pose(T, first_ns + k * POSE_NS,
                                                     topics.WORLD_FRAME))
            assert self.spin_until(lambda seen=seen: health.processed + health.clock_jumps
                                   + sum(health.dropped.values()) > seen), f"pose {k} not taken"

    def frames(self, first_ns: int, count: int) -> None:
        """``count`` frames from ``first_ns`` on, each processed by the node before the next."""
        health = self.flow.health
        for k in range(count):
            stamp = first_ns + k * FRAME_NS
            done = health.processed + health.clock_jumps + sum(health.dropped.values())
            info = CAMERA.to_camera_info(stamp)
            info.header.frame_id = topics.OPTICAL_FRAME
            self.pubs["info"].publish(info)
            self.pubs["depth"].publish(array_to_image(self.depth, "32FC1", stamp,
                                                      topics.OPTICAL_FRAME))
            self.pubs["image"].publish(array_to_image(self.image, "32FC1", stamp,
                                                      topics.OPTICAL_FRAME))
            assert self.spin_until(lambda done=done: health.processed + health.clock_jumps
                                   + sum(health.dropped.values()) > done), f"frame {k} not done"

    def close(self) -> None:
        self.executor.shutdown()
        self.flow.destroy_node()
        self.peer.destroy_node()
        rclpy.shutdown(context=self.context)


@pytest.fixture
def rig() -> Iterator[Rig]:
    rig = Rig()
    try:
        assert rig.spin_until(lambda: all(p.get_subscription_count() > 0
                                          for p in rig.pubs.values())
                              and rig.peer.count_publishers(topics.DIAGNOSTICS) > 0)
        yield rig
    finally:
        rig.close()


def _lines(text: str, pattern: str) -> list[str]:
    return [line for line in text.splitlines() if re.search(pattern, line)]


def test_frames_before_the_first_pose_and_loops_are_counted_warnings_not_errors(rig, capfd):
    flow = rig.flow
    for _ in range(2):  # two passes of a looped replay: the same stamps again
        # the pass's poses first (as at a loop, where they arrive ahead of the frames),
        # from 4 ms after its first image on
        rig.poses(START_NS + FIRST_POSE_NS, FRAMES * 2 + 2)
        rig.frames(START_NS, FRAMES)
    # then the pose stream steps back 0.7 s and goes on (a loop seen by a respawned
    # bridge), after the 1 s log throttle of the last jump has passed
    rig.spin_until(lambda: False, 1.1)
    back_ns = START_NS + FIRST_POSE_NS + (FRAMES * 2 + 1) * POSE_NS - 700 * MS
    rig.poses(back_ns, 4)

    health, poses = flow.health, flow.pose_health
    # the first frame of each pass had no pose and was processed without; every other
    # frame had its pose; nothing else was dropped
    assert dict(health.dropped) == {"PoseBeforeStreamError": 2}, health.dropped
    assert health.processed == 2 * FRAMES
    assert health.clock_jumps == 1  # the frames' loop (tracks, filter reset)
    assert poses.clock_jumps == 2 and not poses.dropped  # the loop and the 0.7 s step back
    assert poses.processed == 2 * (FRAMES * 2 + 2) + 4 - 2  # the two restarting poses: jumps
    assert rig.spin_until(lambda: rig.status.get("flow: frames", {}).get(
        "dropped.PoseBeforeStreamError") == "2"
        and rig.status.get("flow: poses", {}).get("clock_jumps") == "2")
    assert rig.status["flow: poses"]["dropped"] == "0"

    err = capfd.readouterr().err
    assert not _lines(err, r"\[ERROR\]"), err[-3000:]
    first = _lines(err, r"PoseBeforeStreamError \(1 so far\)")
    assert len(first) == 1 and first[0].startswith("[WARN]"), err[-3000:]
    assert "4.0 ms before the pose stream's first pose" in first[0]
    step = _lines(err, r"clock jump \(2 so far\): pose time jumped back 0\.700 s")
    assert len(step) == 1 and step[0].startswith("[WARN]"), err[-3000:]
