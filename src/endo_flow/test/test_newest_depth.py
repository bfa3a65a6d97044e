"""The flow node under newest-frame semantics: a backlog of depths gives one frame, the newest.

Five complete frames (image, depth_relative, camera_info, poses) arrive while
the node is busy (not spinning). It then processes only the newest depth,
paired with the image and camera_info of the same stamp (never another
frame's), counts the four stale depths as skipped (not dropped, not lost)
and lets out exactly one scale, stamped with that frame.
"""

from __future__ import annotations

import time

import pytest
import rclpy
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from endo_flow.node import FlowNode
from endo_io import topics
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose
from endo_io.qos import NEWEST_FRAME_DEPTH, reliable_qos
from endo_io.stamp import stamp_to_ns

pytestmark = pytest.mark.ros
FRAMES = 5


def test_a_backlog_of_depths_gives_the_newest_frame_with_its_own_image(moving):
    rclpy.init()
    flow = FlowNode(parameter_overrides=[Parameter("tracking_downsample", value=1)])
    peer = Node("flow_newest_peer")
    scales: list[Vector3Stamped] = []
    peer.create_subscription(Vector3Stamped, topics.SCALE, scales.append, reliable_qos(100))
    pubs = {
        "image": peer.create_publisher(Image, topics.IMAGE_CORRECTED,
                                       reliable_qos(NEWEST_FRAME_DEPTH)),
        "depth": peer.create_publisher(Image, topics.DEPTH_RELATIVE,
                                       reliable_qos(NEWEST_FRAME_DEPTH)),
        "info": peer.create_publisher(CameraInfo, topics.CAMERA_INFO, reliable_qos(10)),
        "pose": peer.create_publisher(PoseStamped, topics.CAMERA_POSE, reliable_qos(100)),
    }
    executor = SingleThreadedExecutor()
    executor.add_node(flow)
    executor.add_node(peer)

    def spin_until(condition, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        return condition()

    try:
        assert spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values())
                          and flow.scale_pub.get_subscription_count() > 0, 10.0)
        frames = moving.frames(moving.poses)[:FRAMES + 1]
        for k, frame in enumerate(frames):  # poses first, up to one frame past the last
            pubs["pose"].publish(matrix_to_pose(frame.T_world_camera, frame.stamp_ns,
                                                topics.WORLD_FRAME))
            if k == FRAMES:
                break
            info = frame.camera.to_camera_info(frame.stamp_ns)
            info.header.frame_id = topics.OPTICAL_FRAME
            pubs["info"].publish(info)
            pubs["depth"].publish(array_to_image(frame.depth_relative, "32FC1",
                                                 frame.stamp_ns, topics.OPTICAL_FRAME))
            pubs["image"].publish(array_to_image(frame.image, "32FC1", frame.stamp_ns,
                                                 topics.OPTICAL_FRAME))
        time.sleep(0.5)  # every message waits in the flow node's subscriptions
        assert spin_until(lambda: len(scales) >= 1, 20.0)
        spin_until(lambda: False, 1.0)  # nothing else may come
        newest = frames[FRAMES - 1].stamp_ns
        assert [stamp_to_ns(s.header.stamp) for s in scales] == [newest]
        assert flow.health.processed == 1
        assert flow.health.skipped[topics.DEPTH_RELATIVE] == FRAMES - 1
        assert not flow.health.dropped and flow.health.lost_on(topics.DEPTH_RELATIVE) == 0
        # the stale frames' images were let go, none is left to pair with a later depth
        assert flow._frames.pending() == (0, 0)
    finally:
        executor.shutdown()
        flow.destroy_node()
        peer.destroy_node()
        rclpy.shutdown()
