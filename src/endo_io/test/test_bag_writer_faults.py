"""The writer when the disk fills up: what it says it wrote is what the file holds.

Issue 16: on a full disk endo-record reported "wrote 20/135" while the file
held 17/114. Here ``os.write`` is replaced by a disk of fixed capacity that
writes what fits and then fails with ENOSPC, as a real full disk does; the
writer must cut the partial record off, count as written exactly the
messages in complete chunks, count the rest as lost, and leave a file that
reads to its last chunk.

An exception other than OSError inside a write (session robust): the writer
used to keep its file position in Python, and a KeyboardInterrupt after a
chunk's ``os.write`` and before the position update left a summary 2.03 MB
off, a file no reader opened (session recdiag). ``os.write`` here writes
part of its data and then raises (a MemoryError, a KeyboardInterrupt of a
tool that embeds the writer) at every write of a small recording in turn:
the file must open in our reader, the MCAP library's and rosbags' with every
message written before the failure.
"""

from __future__ import annotations

import errno
import os
import types
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from sensor_msgs.msg import Image
from std_msgs.msg import Float32

from endo_io.bag import BagCorruptError, BagError, BagReader, BagWriter, serialize
from endo_io.bag import writer as writer_module
from endo_io.record import Recording

T0 = 1_700_000_000_000_000_000


class FullDisk:
    """``os.write`` on a disk with ``capacity`` free bytes (ENOSPC after a short write)."""

    def __init__(self, capacity: int) -> None:
        self.free = capacity
        self.real_write = os.write
        self.failures = 0

    def write(self, fd: int, data) -> int:
        if self.free <= 0:
            self.failures += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view = memoryview(data)[: self.free]
        written = self.real_write(fd, view)
        self.free -= written
        return written


def with_write(write) -> types.SimpleNamespace:
    """The ``os`` module as the writer module sees it, with ``write`` replaced."""
    return types.SimpleNamespace(**{**vars(os), "write": write})


def image(i: int) -> bytes:
    msg = Image(height=16, width=16, encoding="rgb8", step=48)
    msg.data = np.random.default_rng(i).integers(0, 256, 16 * 48, dtype=np.uint8).tobytes()
    return serialize(msg)


def read_counts(path: Path) -> tuple[dict[str, list[bytes]], str]:
    got: dict[str, list[bytes]] = {}
    error = ""
    try:
        with BagReader(path) as reader:
            for message in reader.messages():
                got.setdefault(message.topic, []).append(message.data)
    except BagCorruptError as exc:
        error = str(exc)
    return got, error


@pytest.mark.parametrize("target", ["run.mcap", "run_dir"])
@pytest.mark.parametrize("capacity", [9_000, 23_456, 40_000])
def test_on_a_full_disk_the_written_counts_are_what_the_file_holds(
    tmp_path, monkeypatch, target, capacity
):
    disk = FullDisk(capacity)
    monkeypatch.setattr(writer_module, "os", with_write(disk.write))
    path = tmp_path / target
    sent: dict[str, list[bytes]] = {"/image": [], "/value": []}
    recording = Recording(BagWriter(path, compression="none", chunk_size=4_000))
    recording.add_topic("/image", "sensor_msgs/msg/Image", "")
    recording.add_topic("/value", "std_msgs/msg/Float32", "")
    error = None
    for i in range(200):
        if i % 3:
            topic, data = "/image", image(i)
        else:
            topic, data = "/value", serialize(Float32(data=float(i)))
        try:
            recording.write(topic, data, T0 + i)
            sent[topic].append(data)
            if i % 25 == 24:
                recording.flush()
        except BagError as exc:
            sent[topic].append(data)  # received: the writer had accepted it
            error = str(exc)
            break
    assert error is not None and disk.failures >= 1
    assert "cannot write (disk full: No space left on device)" in error and "\n" not in error
    with pytest.raises(BagError, match="No space left"):  # every later write refuses
        recording.write("/value", b"late", T0 + 10**9)
    sent["/value"].append(b"late")  # received and refused: lost
    report = recording.close()
    monkeypatch.undo()
    mcap_path = path if target.endswith(".mcap") else path / f"{target}_0.mcap"
    got, damage = read_counts(mcap_path)
    assert "ends before the MCAP footer" in damage  # cut at a record boundary, no footer
    for topic, tally in report.topics.items():
        # The file holds exactly what the report says, and it is a prefix of what was sent.
        assert tally.messages == len(got.get(topic, [])), topic
        assert got.get(topic, []) == sent[topic][: tally.messages], topic
        assert tally.bytes == sum(len(d) for d in got.get(topic, []))
        assert tally.received == len(sent[topic])
    assert report.lost == sum(len(v) for v in sent.values()) - report.messages > 0
    lines = report.summary_lines()
    assert any(f"lost: {report.lost} of {report.received} received" in line for line in lines)
    if not target.endswith(".mcap"):
        meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["message_count"] == report.messages


def test_a_failed_write_keeps_a_chunk_whose_indexes_did_not_fit(tmp_path, monkeypatch):
    # The chunk record fits, its message index records do not: the messages
    # are on disk (the reader counts a chunk without indexes by opening it).
    path = tmp_path / "edge.mcap"
    writer = BagWriter(path, compression="none", chunk_size=1 << 20)
    writer.add_topic("/value", "std_msgs/msg/Float32")
    for i in range(10):
        writer.write("/value", serialize(Float32(data=i)), T0 + i)
    chunk_ends = []
    real_write = os.write

    def write_chunk_then_fail(fd, data):
        if not len(data):
            return 0
        if chunk_ends:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        chunk_ends.append(len(data))
        return real_write(fd, data)

    monkeypatch.setattr(writer_module, "os", with_write(write_chunk_then_fail))
    with pytest.raises(BagError, match="holds the 10 messages written before, 0 not yet"):
        writer.flush()
    writer.close()
    monkeypatch.undo()
    assert writer.written == {"/value": (10, 80)} and writer.lost == 0
    got, _ = read_counts(path)
    assert len(got["/value"]) == 10


def test_written_counts_follow_the_chunks_on_disk(tmp_path):
    path = tmp_path / "count.mcap"
    with BagWriter(path, chunk_size=1 << 20) as writer:
        writer.add_topic("/value", "std_msgs/msg/Float32")
        for i in range(5):
            writer.write("/value", serialize(Float32(data=i)), T0 + i)
        assert writer.written == {"/value": (0, 0)}  # still in the open chunk
        writer.flush()
        assert writer.written == {"/value": (5, 40)}
        writer.write("/value", serialize(Float32(data=5)), T0 + 5)
    assert writer.written == {"/value": (6, 48)} and writer.lost == 0
    with BagReader(path) as reader:
        assert reader.damage is None and reader.message_count == 6
        assert reader.metadata is not None and reader.metadata["message_count"] == 6


def test_metadata_yaml_counts_what_each_flush_put_on_disk(tmp_path):
    path = tmp_path / "dir_bag"
    writer = BagWriter(path, chunk_size=1 << 20)
    writer.add_topic("/value", "std_msgs/msg/Float32")
    for batch, flushed in ((3, 3), (4, 7)):
        for i in range(batch):
            writer.write("/value", serialize(Float32(data=i)), T0 + i)
        writer.flush()
        meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["message_count"] == flushed
        assert meta["topics_with_message_count"][0]["message_count"] == flushed
        assert meta["files"][0]["message_count"] == flushed
    writer.close()


MESSAGES = 40


def small_message(i: int) -> tuple[str, bytes]:
    if i % 3:
        return "/image", image(i)
    return "/value", serialize(Float32(data=float(i)))


class FailingWrite:
    """``os.write`` that, at its ``fail_at``-th call, writes half its data and raises."""

    def __init__(self, fail_at: int, error: type[BaseException]) -> None:
        self.fail_at = fail_at
        self.error = error
        self.calls = 0
        self.real_write = os.write

    def __call__(self, fd: int, data) -> int:
        self.calls += 1
        if self.calls == self.fail_at:
            view = memoryview(data)
            self.real_write(fd, view[: len(view) // 2])
            raise self.error("injected")
        return self.real_write(fd, data)


def record(path: Path, write: FailingWrite, compression: str, direct: bool = False):
    """A small recording; returns (the writer, sent per topic, written counts before the failure).

    Every message handed to ``write`` counts as sent; the counts before are
    the writer's messages on disk just before the call that failed (None: none
    failed). A bag directory is split every 4 kB.
    """
    sent: dict[str, list[bytes]] = {"/image": [], "/value": []}
    before: dict[str, int] = {}
    split = None if path.suffix == ".mcap" else 4_000
    writer = BagWriter(path, compression=compression, chunk_size=1_500, split_size_bytes=split,
                       direct=direct)
    failed = False

    def call(function, *args) -> None:
        nonlocal failed, before
        if failed:
            with pytest.raises(BagError, match="writing stopped by"):
                function(*args)
            return
        counts = {t: n for t, (n, _) in writer.written.items()}
        try:
            function(*args)
        except write.error:
            failed, before = True, counts

    call(writer.add_topic, "/image", "sensor_msgs/msg/Image")
    call(writer.add_topic, "/value", "std_msgs/msg/Float32")
    for i in range(MESSAGES):
        topic, data = small_message(i)
        if topic in writer.written:
            sent[topic].append(data)
        call(writer.write, topic, data, T0 + i * 10_000_000)
        if i % 15 == 14:
            call(writer.flush)
    counts = {t: n for t, (n, _) in writer.written.items()}
    try:
        writer.close()
    except write.error:
        assert not failed
        failed, before = True, counts
    return writer, sent, before if failed else None


def clean_writes(path: Path, compression: str, direct: bool = False) -> int:
    counter = FailingWrite(0, RuntimeError)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(writer_module, "os", with_write(counter))
        writer, _, _ = record(path, counter, compression, direct)
    assert len(writer.file_paths) == (1 if path.suffix == ".mcap" else 7)
    return counter.calls


@pytest.mark.parametrize(("suffix", "compression"),
                         [(".mcap", "zstd"), (".mcap", "none"), ("_dir", "lz4")])
@pytest.mark.parametrize("error", [KeyboardInterrupt, MemoryError])
@pytest.mark.parametrize("direct", [False, True])  # review, session 14: O_DIRECT left no summary
def test_a_failure_at_any_write_leaves_a_file_every_reader_opens(
        tmp_path, suffix, compression, error, direct):
    writes = clean_writes(tmp_path / f"clean{suffix}", compression, direct)
    assert writes > 20  # headers, several chunks and their indexes, summaries
    for fail_at in range(1, writes + 1):
        path = tmp_path / f"fail_{fail_at}{suffix}"
        failing = FailingWrite(fail_at, error)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(writer_module, "os", with_write(failing))
            try:
                writer, sent, before = record(path, failing, compression, direct)
            except error:
                # the constructor's header: no file rather than one no reader opens
                assert fail_at <= 2 and not path.exists(), fail_at
                continue
        assert before is not None, fail_at
        written = {t: n for t, (n, _) in writer.written.items()}
        with BagReader(path) as reader:
            assert reader.damage is None, (fail_at, reader.damage)
            got: dict[str, list[bytes]] = {}
            for m in reader.messages():
                got.setdefault(m.topic, []).append(bytes(m.data))
        for topic, data in sent.items():
            held = got.get(topic, [])
            assert held == data[: len(held)], (fail_at, topic)  # a prefix of what was sent
            assert len(held) == written.get(topic, 0), (fail_at, topic)
            assert len(held) >= before.get(topic, 0), (fail_at, topic)  # nothing written lost
        by_library = []
        for file_path in writer.file_paths:  # a file its header did not reach is not listed
            with file_path.open("rb") as stream:
                mcap = make_reader(stream)
                summary = mcap.get_summary()
                assert summary is not None and summary.statistics is not None, fail_at
                in_file = [(c.topic, bytes(m.data)) for _, c, m in mcap.iter_messages()]
                assert summary.statistics.message_count == len(in_file), fail_at
                by_library += in_file
        with AnyReader([path]) as rosbags_reader:
            by_rosbags = [(c.topic, bytes(raw)) for c, _, raw in rosbags_reader.messages()]
        ours = sorted((t, d) for t, ds in got.items() for d in ds)
        assert sorted(by_library) == ours and sorted(by_rosbags) == ours, fail_at
