"""Batched PoseStamped encoding: the bytes and read-back transforms of the one-by-one path."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_io.bag.serde import serialize
from endo_io.errors import PoseError
from endo_io.pose import matrix_to_pose, pose_to_matrix, transforms_to_pose_stamped_cdr


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
