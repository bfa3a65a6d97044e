"""endo_io.bag.streams: counts of a finished and of a cut bag, pose streams, depth frames."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from endo_io.bag import BagError, BagWriter
from endo_io.bag.streams import (
    GrowingCounter,
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


def _write_flushed(path: Path, compression: str) -> list[int]:
    """A recorder's file: 3 topics, flushed every 7 messages; the file's size after each flush."""
    sizes = []
    with BagWriter(path, compression=compression, chunk_size=1 << 12) as writer:
        for k in range(60):
            stamp = k * 10 * MS
            writer.write_message("/pose", matrix_to_pose(rigid_transform([0.0, 0.0, 0.001 * k],
                                                                          [k, 0.0, 0.0]),
                                                         stamp, "tracker"), stamp)
            if k % 3 == 0:  # the depth topic appears after the first flushes
                depth = np.full((8, 10), 0.01 * (k + 1), np.float32)
                writer.write_message("/depth", array_to_image(depth, "32FC1", stamp, "cam"),
                                     stamp)
            if k == 30:
                writer.add_topic("/late", "std_msgs/msg/Float32")  # a topic without messages
            if k % 7 == 6:
                writer.flush()
                sizes.append(path.stat().st_size)
    return sizes


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_growing_counter_counts_as_count_messages_does_while_the_file_grows(
    tmp_path: Path, compression: str
) -> None:
    whole = tmp_path / "whole.mcap"
    flushed = _write_flushed(whole, compression)
    data = whole.read_bytes()
    assert count_messages(whole) == {"/pose": 60, "/depth": 20, "/late": 0}
    assert GrowingCounter(whole).count() == count_messages(whole)
    # a file being written: every prefix, counted by one counter reading on, and alone
    growing = tmp_path / "growing.mcap"
    counter = GrowingCounter(growing)
    assert counter.count() == {}  # not created yet
    whole_chunks = 0
    for cut in sorted({*range(0, len(data), 97), *flushed, len(data)}):
        growing.write_bytes(data[:cut])  # a rewrite of the same bytes, longer
        on, alone = counter.count(), GrowingCounter(growing).count()
        partial = count_messages(growing, partial=True)
        if cut in flushed or cut == len(data):
            # every chunk and its indexes whole: the same counts as the full read
            assert on == alone == partial
            whole_chunks += 1
            continue
        # cut inside a chunk or its indexes: never more than the full read, and at least
        # the chunks flushed before the cut
        before = max((s for s in flushed if s <= cut), default=None)
        done = (Counter() if before is None
                else count_messages(_prefix(tmp_path, data, before), partial=True))
        for counts in (on, alone):
            assert all(done[t] <= counts[t] <= partial[t] for t in partial)
    assert whole_chunks == len(flushed) + 1
    assert counter.count() == count_messages(whole) and not counter.damage


def _prefix(tmp_path: Path, data: bytes, size: int) -> Path:
    path = tmp_path / f"prefix_{size}.mcap"
    if not path.exists():
        path.write_bytes(data[:size])
    return path


def test_growing_counter_stops_at_a_damaged_chunk_and_refuses_other_files(tmp_path: Path) -> None:
    whole = tmp_path / "whole.mcap"
    flushed = _write_flushed(whole, "lz4")
    data = bytearray(whole.read_bytes())
    # the first chunk declares the channels: damage its compressed data
    first_chunk = 8 + 9 + int.from_bytes(data[9:17], "little")  # after magic and header
    assert data[first_chunk] == 0x06  # a chunk's opcode
    data[first_chunk + 9 + 40 : first_chunk + 9 + 60] = bytes(20)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data[: flushed[1]]))
    counter = GrowingCounter(damaged)
    assert sum(counter.count().values()) == 0
    assert "chunk" in counter.damage or "lz4" in counter.damage
    other = tmp_path / "other.mcap"
    other.write_bytes(b"not an mcap file at all")
    with pytest.raises(BagError, match="not an MCAP file"):
        GrowingCounter(other).count()


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
