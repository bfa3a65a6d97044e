"""PoseStamped CDR: batched encoding (the one-by-one path's bytes), decoding (rclpy's values)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import deserialize_message
from scipy.spatial.transform import Rotation

from endo_io.bag.serde import serialize
from endo_io.errors import PoseError, UndecodableMessageError
from endo_io.pose import (
    PoseView,
    matrix_to_pose,
    pose_stamped_from_cdr,
    pose_to_matrix,
    transforms_to_pose_stamped_cdr,
)


@pytest.mark.parametrize("frame_id", ["world", "", "tracker_frame"])
def test_batched_pose_messages_equal_matrix_to_pose_serialised(frame_id: str) -> None:
    rng = np.random.default_rng(3)
    count = 400
    T = np.tile(np.eye(4), (count, 1, 1))
    T[:, :3, :3] = Rotation.random(count, random_state=4).as_matrix()
    T[:3, :3, :3] = np.diag([1.0, -1.0, -1.0])  # half turns: w == 0, the sign rule
    T[3, :3, :3] = np.eye(3)
    T[:, :3, 3] = rng.normal(scale=0.2, size=(count, 3))
    stamps = rng.integers(0, 2**41, count)
    data, read_back = transforms_to_pose_stamped_cdr(T, stamps, frame_id)
    for k in range(count):
        message = matrix_to_pose(T[k], int(stamps[k]), frame_id)
        assert data[k] == serialize(message)
        matrix, stamp = pose_to_matrix(message)
        assert stamp == stamps[k]
        assert np.array_equal(read_back[k], matrix)


def test_batched_pose_messages_refuse_what_matrix_to_pose_refuses() -> None:
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, 0, 0] = 2.0
    with pytest.raises(PoseError):
        transforms_to_pose_stamped_cdr(T, [1, 2, 3], "world")
    with pytest.raises(PoseError):
        transforms_to_pose_stamped_cdr(np.tile(np.eye(4), (2, 1, 1)), [1, -2], "world")


def _big_endian_pose(message: PoseStamped) -> bytes:
    """``message`` in big-endian CDR (encapsulation 0x0000), as another DDS may send it."""
    name = message.header.frame_id.encode() + b"\x00"
    body = struct.pack(">iI", message.header.stamp.sec, message.header.stamp.nanosec)
    body += struct.pack(">I", len(name)) + name
    body += bytes(-len(body) % 8)
    p, o = message.pose.position, message.pose.orientation
    return b"\x00\x00\x00\x00" + body + struct.pack(">7d", p.x, p.y, p.z, o.x, o.y, o.z, o.w)


def test_poses_read_from_cdr_give_rclpy_s_transforms_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    count = 300
    T = np.tile(np.eye(4), (count, 1, 1))
    T[:, :3, :3] = Rotation.random(count, random_state=6).as_matrix()
    T[:, :3, 3] = rng.normal(scale=0.2, size=(count, 3))
    stamps = rng.integers(0, 2**41, count)
    for k in range(count):
        frame_id = ("world", "", "tracker_frame_é", "x" * 7)[k % 4]  # every padding to 8
        message = matrix_to_pose(T[k], int(stamps[k]), frame_id)
        message.pose.orientation.w *= 1.0 + 1e-4 * (k % 3)  # not quite unit: normalised alike
        expected, stamp = pose_to_matrix(deserialize_message(serialize(message), PoseStamped))
        for data in (serialize(message), _big_endian_pose(message)):
            view = pose_stamped_from_cdr(data)
            assert isinstance(view, PoseView)
            assert view.header == message.header
            got, got_stamp = pose_to_matrix(view)
            assert got_stamp == stamp == stamps[k]
            assert np.array_equal(got, expected)


def test_bad_pose_bytes_are_refused_as_rclpy_refuses_them() -> None:
    message = matrix_to_pose(np.eye(4), 123, "world")
    data = serialize(message)
    for cut in range(len(data)):
        try:
            deserialize_message(data[:cut], PoseStamped)
        except Exception:
            with pytest.raises(UndecodableMessageError) as refused:
                pose_stamped_from_cdr(data[:cut])
            assert "\n" not in str(refused.value)
        else:  # pragma: no cover - rclpy refuses every cut of a PoseStamped
            raise AssertionError(f"rclpy decoded {cut} of {len(data)} bytes")
    with pytest.raises(UndecodableMessageError, match="not CDR"):
        pose_stamped_from_cdr(b"\x42\x01\x00\x00" + data[4:])
    # a NaN is decoded as it is and refused where a message's is: by pose_to_matrix
    message.pose.orientation.x = float("nan")
    view = pose_stamped_from_cdr(serialize(message))
    with pytest.raises(PoseError, match="NaN"):
        pose_to_matrix(view)
