"""endo_io.bag.streams: counts of a finished and of a cut bag, pose streams, depth frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from endo_io.bag import BagError, BagWriter
from endo_io.bag.streams import (
    PoseStreamCollector,
    count_messages,
    read_depth_frames,
    read_pose_stream,
)
from endo_io.errors import PoseError
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose, rigid_transform

MS = 1_000_000


def _write(path: Path, poses: int = 40) -> list[np.ndarray]:
    """PoseStamped on /pose (last two stamps swapped), 2 depth frames, an empty topic."""
    transforms = [rigid_transform([0.0, 0.0, 0.01 * k], [k, 2.0 * k, 0.5]) for k in range(poses)]
    stamps = [k * 10 * MS for k in range(poses)]
    stamps[-2], stamps[-1] = stamps[-1], stamps[-2]  # a driver that sent two late
    with BagWriter(path, compression="none", chunk_size=1 << 11) as writer:
        writer.add_topic("/empty", "std_msgs/msg/Float32")
        for k, (T, stamp) in enumerate(zip(transforms, stamps, strict=True)):
            writer.write_message("/pose", matrix_to_pose(T, stamp, "tracker"), k * 10 * MS)
        for k in range(2):
            depth = np.full((4, 6), 0.05 * (k + 1), np.float32)
            writer.write_message("/depth", array_to_image(depth, "32FC1", k * MS, "cam"), k * MS)
    return transforms


def test_counts_list_every_topic_and_a_cut_bag_counts_what_is_intact(tmp_path: Path) -> None:
    whole = tmp_path / "whole.mcap"
    _write(whole)
    assert count_messages(whole) == {"/empty": 0, "/pose": 40, "/depth": 2}
    assert "/empty" in count_messages(whole)

    cut = tmp_path / "cut.mcap"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) * 3 // 10])  # inside the poses
    with pytest.raises(BagError):
        count_messages(cut)
    partial = count_messages(cut, partial=True)
    assert 0 < partial["/pose"] < 40
    # a bag not yet created (a recorder still starting) is empty, not an error
    assert count_messages(tmp_path / "not_yet.mcap", partial=True) == {}
    with pytest.raises(BagError):
        count_messages(tmp_path / "not_yet.mcap")


def test_pose_stream_is_sorted_by_stamp_and_scaled(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    transforms = _write(path)
    stamps, poses = read_pose_stream(path, "/pose")
    assert stamps.dtype == np.int64 and poses.shape == (40, 4, 4)
    np.testing.assert_array_equal(stamps, np.arange(40) * 10 * MS)
    # the two swapped samples come back in stamp order
    np.testing.assert_allclose(poses[-2], transforms[-1], atol=1e-12)
    np.testing.assert_allclose(poses[-1], transforms[-2], atol=1e-12)
    np.testing.assert_allclose(poses[:-2], np.stack(transforms[:-2]), atol=1e-12)

    millimetres = read_pose_stream(path, "/pose", metres_per_unit=1e-3)
    np.testing.assert_allclose(millimetres.poses[5, :3, 3], [0.005, 0.010, 0.0005])
    np.testing.assert_allclose(millimetres.poses[5, :3, :3], poses[5, :3, :3])

    empty = read_pose_stream(path, "/missing")
    assert empty.stamps_ns.shape == (0,) and empty.poses.shape == (0, 4, 4)


def test_collector_refuses_a_bad_pose_and_keeps_the_good_ones(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    good = matrix_to_pose(np.eye(4), 5, "tracker")
    bad = matrix_to_pose(np.eye(4), 6, "tracker")
    bad.pose.orientation.w = 1.5  # not a unit quaternion
    with BagWriter(path) as writer:
        writer.write_message("/pose", good, 5)
        writer.write_message("/pose", bad, 6)
    from endo_io.bag import BagReader

    collector = PoseStreamCollector()
    with BagReader(path) as reader:
        messages = list(reader.messages())
    collector.add(messages[0])
    with pytest.raises(PoseError, match="norm"):
        collector.add(messages[1])
    assert collector.stream().stamps_ns.tolist() == [5]


def test_depth_frames_by_stamp(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write(path)
    frames = read_depth_frames(path, "/depth")
    assert sorted(frames) == [0, MS]
    assert frames[MS].dtype == np.float32 and frames[MS].shape == (4, 6)
    assert float(frames[MS][0, 0]) == pytest.approx(0.10)
    assert list(read_depth_frames(path, "/depth", {MS})) == [MS]
    assert read_depth_frames(path, "/missing") == {}
