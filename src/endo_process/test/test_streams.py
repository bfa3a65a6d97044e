"""endo-process reads its small streams lazily and pairs camera_info by "newest at or before".

A driver that stamps camera_info on its own clock (not the image's stamp)
must work: each image takes the newest camera_info stamped at or before it,
and the output carries one camera_info beside every image, at its stamp.
Tracker poses are taken from the recording only as far as the frame being
processed needs (memory does not grow with the recording's length), and
every stream comes from one shared pass over the file.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import endo_process.inputs
from endo_io import topics
from endo_io.bag import BagMessage, BagReader, BagWriter, deserialize
from endo_io.bag.serde import serialize
from endo_io.stamp import ns_to_stamp, stamp_to_ns
from endo_process.inputs import InputTopics, open_recording, recording_streams
from endo_process.output import OutputBag
from endo_process.runner import ProcessOptions, ProcessReport, _PoseFeed, process_bag
from endo_tracker_bridge.chain import CameraPose
from endo_tracker_bridge.sample import TrackerSample

from .conftest import PHANTOM

MS = 1_000_000


def _own_clock_bag(path: Path, images: int, info_offsets: dict[int, int]) -> list[int]:
    """The phantom's first ``images`` frames and tracker, with camera_info on its own clock.

    Only the frames in ``info_offsets`` (frame index -> stamp offset in ns
    from its image) keep a camera_info. Returns the image stamps.
    """
    stamps: list[int] = []
    with BagReader(PHANTOM) as reader, BagWriter(path) as writer:
        for name in (topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE):
            writer.add_topic(name, reader.topics[name].msgtype)
        names = [topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE]
        for message in reader.messages(names):
            if message.topic == topics.IMAGE_RAW:
                if len(stamps) == images:
                    break
                stamps.append(stamp_to_ns(deserialize(message).header.stamp))
            if message.topic == topics.CAMERA_INFO:
                info = deserialize(message)
                index = stamps.index(stamp_to_ns(info.header.stamp))
                if index not in info_offsets:
                    continue
                info.header.stamp = ns_to_stamp(stamps[index] + info_offsets[index])
                writer.write(message.topic, serialize(info), message.log_time_ns)
                continue
            writer.write(message.topic, message.data, message.log_time_ns)
    return stamps


def test_camera_info_on_its_own_clock_pairs_with_the_newest_at_or_before(
    calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    # Two camera_infos for six images: one stamped 2 ms after image 1, one
    # 5 ms before image 3. Images 0 and 1 have none at or before them.
    bag = tmp_path / "own_clock.mcap"
    stamps = _own_clock_bag(bag, images=6, info_offsets={1: 2 * MS, 3: -5 * MS})
    out = tmp_path / "out.mcap"
    report = process_bag(ProcessOptions(
        bag=bag, output=out, calibration=calibrations[0], handeye=calibrations[1],
        solve_scale=0.5, jobs=1, progress=False,
    ))  # fmt: skip
    assert report.frames_in == 6 and report.frames_shaded == 4
    assert dict(report.dropped) == {"NoCameraInfoError": 2}
    with BagReader(out) as reader:
        infos = [deserialize(m) for m in reader.messages([topics.CAMERA_INFO])]
        depth = [deserialize(m) for m in reader.messages([topics.DEPTH_RELATIVE])]
    assert [stamp_to_ns(i.header.stamp) for i in infos] == stamps[2:]
    assert [stamp_to_ns(d.header.stamp) for d in depth] == stamps[2:]
    assert all(i.width == 640 and i.height == 480 and i.k[0] > 0 for i in infos)


class _Counting:
    """An iterator of camera poses at 60 Hz that counts what was taken from it."""

    def __init__(self, count: int) -> None:
        self.taken = 0
        self.count = count

    def __iter__(self) -> Iterator[CameraPose]:
        return self

    def __next__(self) -> CameraPose:
        if self.taken == self.count:
            raise StopIteration
        stamp = 1_000 * MS + self.taken * (1_000 * MS // 60)
        self.taken += 1
        T = np.eye(4)
        T[0, 3] = self.taken * 1e-4
        sample = TrackerSample(stamp_ns=stamp, T_tracker_marker=T, tool_id="tool")
        return CameraPose(sample=sample, stamp_ns=stamp, T_world_camera=T)


def test_tracker_poses_are_taken_only_as_far_as_each_frame(tmp_path: Path) -> None:
    poses = _Counting(60 * 60)  # a minute at 60 Hz
    output = OutputBag(tmp_path / "poses.mcap", "lz4")
    feed = _PoseFeed(poses, output, ("world", "tracker"), 100 * MS, ProcessReport())
    for frame in range(30):  # one second of frames at 30 Hz
        stamp = 1_000 * MS + frame * (1_000 * MS // 30) + 5 * MS
        T = feed.at(stamp)
        # Just past the frame: the pose after it, nothing more.
        assert feed.buffer.newest_ns is not None and feed.buffer.newest_ns > stamp
        assert feed.buffer.newest_ns - stamp <= 1_000 * MS // 60
        assert poses.taken <= 2 * frame + 2
        assert 0.0 < T[0, 3] < 1.0
        output.release(stamp)
    assert poses.taken <= 62
    feed.drain()
    assert poses.taken == 60 * 60
    output.close()
    with BagReader(tmp_path / "poses.mcap") as reader:
        assert reader.topics[topics.CAMERA_POSE].message_count == 60 * 60


def test_the_shared_pass_gives_each_stream_what_a_reader_of_its_own_gives(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One pass over the file feeds every stream; a stream that runs far ahead reads on alone."""
    inputs = open_recording(PHANTOM, InputTopics())
    with BagReader(PHANTOM) as reader:
        alone = {name: [(m.topic, m.log_time_ns, bytes(m.data)) for m in reader.messages(t)]
                 for name, t in recording_streams(inputs)._topics.items()}  # fmt: skip
    # Interleaved as a run takes them, then the tracker drained far ahead of the
    # images (then each stream drained in turn); with a queue limit of 20
    # messages the tracker leaves the pass (and the streams drained after it).
    for limit, tracker_alone in ((inputs.frame_count * 10, False), (20, True)):
        monkeypatch.setattr(endo_process.inputs, "MAX_QUEUED_MESSAGES", limit)
        streams = recording_streams(inputs)
        iterators = {name: streams.messages(name) for name in alone}
        got: dict[str, list[tuple[str, int, bytes]]] = {name: [] for name in alone}
        for name in ("image", "camera_info", "truth") * 3 + ("tracker",) * 150:
            got[name].append(_key(next(iterators[name])))
        for name, iterator in iterators.items():
            got[name] += [_key(m) for m in iterator]
        streams.close()
        assert got == alone
        assert ("tracker" in streams._detached) is tracker_alone


def _key(message: BagMessage) -> tuple[str, int, bytes]:
    return message.topic, message.log_time_ns, bytes(message.data)
