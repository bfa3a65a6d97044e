"""The TransformStamped a live tf broadcaster sends, against the poses it comes from.

geometry_msgs is installed pip-only, so the message the broadcaster puts in
each ``TFMessage`` is checked here number by number; the ``TFMessage``
wrapper and its DDS publisher need tf2_msgs (src/endo_tracker_bridge/test/
test_node_tf.py runs that half where it is importable).
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, TransformStamped

from endo_io.pose import invert_transform, pose_to_matrix, rigid_transform
from endo_io.stamp import NS_PER_S
from endo_io.tf import (
    FrameNames,
    StampedTransform,
    TransformError,
    camera_transform,
    static_transforms,
    transform_stamped,
)
from endo_io.tf_broadcast import tf_message_class
from endo_io.topics import MARKER_FRAME, OPTICAL_FRAME, TRACKER_FRAME, WORLD_FRAME


def _matrix(msg: TransformStamped) -> tuple[np.ndarray, int]:
    pose = PoseStamped()
    pose.header = msg.header
    t, q = msg.transform.translation, msg.transform.rotation
    pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = t.x, t.y, t.z
    o = pose.pose.orientation
    o.x, o.y, o.z, o.w = q.x, q.y, q.z, q.w
    return pose_to_matrix(pose)


@pytest.mark.parametrize("seed", [3, 11])
def test_transform_stamped_equals_the_pose(seed):
    rng = np.random.default_rng(seed)
    stamps = [0, NS_PER_S - 1, NS_PER_S, 1_763_900_000_123_456_789]
    stamps += [int(s) for s in rng.integers(0, 2**31 * NS_PER_S, size=20)]
    for stamp in stamps:
        T = rigid_transform(rng.normal(size=3) * 2.0, rng.normal(size=3) * 0.5)
        edge = camera_transform(T, stamp)
        msg = transform_stamped(edge)
        assert (msg.header.frame_id, msg.child_frame_id) == (WORLD_FRAME, OPTICAL_FRAME)
        assert msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec == stamp
        assert 0 <= msg.header.stamp.nanosec < NS_PER_S
        t, q = msg.transform.translation, msg.transform.rotation
        assert [t.x, t.y, t.z] == list(edge.translation)  # copied, not recomputed
        assert [q.x, q.y, q.z, q.w] == list(edge.rotation)
        T_msg, stamp_msg = _matrix(msg)
        assert stamp_msg == stamp
        np.testing.assert_allclose(T_msg, T, atol=1e-12)


def test_static_edges_as_messages_with_frame_names():
    T_world_tracker = rigid_transform([0.1, -0.2, 3.0], [0.5, -1.25, 0.75])
    T_marker_camera = rigid_transform([1.0, 0.5, -0.25], [0.01, -0.02, 0.15])
    assert FrameNames() == FrameNames(WORLD_FRAME, TRACKER_FRAME, OPTICAL_FRAME, MARKER_FRAME)
    frames = FrameNames(world="map", tracker="polaris", camera="cam_optical", marker="rb")
    edges = static_transforms(
        T_world_tracker=T_world_tracker, T_marker_camera=T_marker_camera, stamp_ns=5,
        frames=frames,
    )
    tracker, marker = (transform_stamped(edge) for edge in edges)
    assert (tracker.header.frame_id, tracker.child_frame_id) == ("map", "polaris")
    assert (marker.header.frame_id, marker.child_frame_id) == ("cam_optical", "rb")
    np.testing.assert_allclose(_matrix(tracker)[0], T_world_tracker, atol=1e-12)
    np.testing.assert_allclose(_matrix(marker)[0], invert_transform(T_marker_camera), atol=1e-12)


def test_an_edge_that_cannot_be_sent_is_refused():
    edge = StampedTransform(0, WORLD_FRAME, WORLD_FRAME, np.zeros(3), np.array([0, 0, 0, 1.0]))
    with pytest.raises(TransformError, match="its own parent"):
        transform_stamped(edge)
    with pytest.raises(TransformError, match="its own parent"):
        camera_transform(np.eye(4), 0, frames=FrameNames(camera=WORLD_FRAME))


def test_tf_message_class_is_there_exactly_when_tf2_msgs_is():
    found = tf_message_class()
    assert (found is None) == (importlib.util.find_spec("tf2_msgs") is None)
    if found is not None:
        assert found.__module__.startswith("tf2_msgs.msg") and found.__name__ == "TFMessage"
