"""The recording's writer thread: order, the queue's bound, failures, limits, niceness."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Mapping

import pytest

from endo_io.errors import BagError
from endo_io.record import Recording
from endo_io.record_writer import BackgroundWriter


class _SlowWriter:
    """A RawBagWriter that holds every write until ``go`` is set, and can fail."""

    def __init__(self, fail_at: int | None = None, error: Exception | None = None) -> None:
        self.go = threading.Event()
        self.entered = threading.Event()  # a write has begun (and waits for go)
        self.error = error or BagError("no space left on device")
        self.rows: list[tuple[str, bytes, int]] = []
        self.flushes = 0
        self.fail_at = fail_at
        self.threads: set[int] = set()

    def add_topic(self, name: str, msgtype: str, offered_qos_profiles: str = "") -> None:
        pass

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        self.entered.set()
        self.go.wait()
        self.threads.add(threading.get_ident())
        if self.fail_at is not None and len(self.rows) == self.fail_at:
            raise self.error
        self.rows.append((topic, data, log_time_ns))

    def flush(self) -> None:
        self.flushes += 1

    def close(self) -> None:
        pass

    @property
    def written(self) -> Mapping[str, tuple[int, int]]:
        counts: dict[str, tuple[int, int]] = {}
        for topic, data, _ in self.rows:
            n, size = counts.get(topic, (0, 0))
            counts[topic] = (n + 1, size + len(data))
        return counts


def _recording(writer: _SlowWriter, **limits: int) -> Recording:
    recording = Recording(writer, **limits)
    recording.start(0)
    for topic in ("/a", "/b"):
        recording.add_topic(topic, "std_msgs/msg/String", "")
    return recording


def test_messages_are_written_in_order_on_another_thread_and_flushed():
    sink = _SlowWriter()
    sink.go.set()
    recording = _recording(sink)
    writer = BackgroundWriter(recording, flush_period_s=0.05)
    for k in range(50):
        assert writer.put("/a" if k % 3 else "/b", bytes([k]) * 10, k)
    time.sleep(0.2)  # idle: the flush timer of the writer thread still closes chunks
    writer.close()
    report = recording.close()
    assert [row[2] for row in sink.rows] == list(range(50))
    assert sink.threads and threading.get_ident() not in sink.threads
    assert sink.flushes >= 2
    assert report.lost == 0 and report.messages == 50
    assert not writer.put("/a", b"late", 99)  # closed: refused, not queued


def test_a_full_queue_refuses_counts_and_reports_what_it_refused():
    sink = _SlowWriter()  # the disk stalls: nothing is written until go
    recording = _recording(sink)
    writer = BackgroundWriter(recording, max_bytes=1000, flush_period_s=10.0)
    accepted = [writer.put("/a", b"x" * 100, k) for k in range(25)]
    # the first message may already be in the writer's hands (out of the queue's bytes)
    assert 10 <= sum(accepted) <= 11 and accepted[:10] == [True] * 10
    assert writer.peak_bytes <= 1000  # never over the bound (no message alone is larger)
    refused = 25 - sum(accepted)
    assert writer.refused["/a"] == refused
    sink.go.set()  # the disk catches up: everything queued is written
    writer.close()
    report = recording.close()
    assert report.messages == sum(accepted)
    assert report.topics["/a"].received == 25 and report.lost == refused
    lines = "\n".join(report.summary_lines())
    assert f"lost: {refused} of 25 received messages" in lines
    assert "--buffer-mb" in lines and "fell behind" in lines


def test_a_failed_write_stops_the_writer_and_counts_what_was_queued():
    sink = _SlowWriter(fail_at=3)
    recording = _recording(sink)
    writer = BackgroundWriter(recording, flush_period_s=10.0)
    for k in range(8):
        writer.put("/b", b"y" * 10, k)
    sink.go.set()
    deadline = time.monotonic() + 5.0
    while writer.state.error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert isinstance(writer.state.error, BagError)
    assert not writer.put("/b", b"after", 9)  # stopped: nothing more is taken
    writer.close()
    report = recording.close()
    assert report.messages == 3 and report.topics["/b"].received == 8
    assert report.lost == 5 and "no space left on device" in report.write_error


def test_what_waits_behind_a_failed_write_is_counted_lost():
    # the first write holds (the disk stalls) with the rest queued behind it, then fails
    sink = _SlowWriter(fail_at=0)
    recording = _recording(sink)
    writer = BackgroundWriter(recording, flush_period_s=10.0)
    writer.put("/a", b"first", 0)
    assert sink.entered.wait(5.0)  # the writer holds the first message alone
    for k in range(1, 6):
        assert writer.put("/b" if k % 2 else "/a", b"queued", k)
    sink.go.set()
    writer.close()
    report = recording.close()
    assert report.messages == 0 and report.lost == 6
    assert report.topics["/a"].received == 3 and report.topics["/b"].received == 3


def test_any_exception_on_the_writer_thread_stops_it_counted_and_named():
    sink = _SlowWriter(fail_at=2, error=RuntimeError("a bug in the writer"))
    recording = _recording(sink)
    writer = BackgroundWriter(recording, flush_period_s=10.0)
    for k in range(6):
        writer.put("/a", b"m", k)
    sink.go.set()
    deadline = time.monotonic() + 5.0
    while writer.state.error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert isinstance(writer.state.error, RuntimeError)
    assert not writer.put("/a", b"after", 9)  # stopped: refused, not queued into nothing
    writer.close()
    report = recording.close()
    assert report.messages == 2 and report.topics["/a"].received == 6 and report.lost == 4
    assert "writer thread failed: RuntimeError: a bug in the writer" in report.write_error


def test_topics_declared_while_writing_go_in_order_on_the_writer_thread(tmp_path):
    # Review, session 13: add_topic on the node's thread wrote schema and channel records
    # into the chunk the writer thread was filling: unreadable bags, "lost: 0"
    from endo_io.bag import BagReader, BagWriter

    path = tmp_path / "topics.mcap"
    recording = Recording(BagWriter(path, compression="none", chunk_size=4096))
    recording.start(0)
    writer = BackgroundWriter(recording, flush_period_s=0.001)
    count = 0
    for k in range(120):
        writer.add_topic(f"/t{k}", "std_msgs/msg/String", "")
        for _ in range(20):
            assert writer.put(f"/t{k}", bytes(range(20)) * 4, count)
            count += 1
    writer.close()
    report = recording.close()
    assert report.messages == count and report.lost == 0
    with BagReader(path) as reader:
        got = [(m.topic, m.log_time_ns) for m in reader.messages()]
    assert len(got) == count and [t for _, t in got] == list(range(count))
    assert {topic for topic, _ in got} == {f"/t{k}" for k in range(120)}


def test_a_limit_stops_the_writer_without_counting_losses():
    sink = _SlowWriter()
    sink.go.set()
    recording = _recording(sink, max_messages=5)
    writer = BackgroundWriter(recording)
    for k in range(12):
        writer.put("/a", b"z", k)
    deadline = time.monotonic() + 5.0
    while not writer.state.limit and time.monotonic() < deadline:
        time.sleep(0.01)
    assert writer.state.limit == "5 messages"
    writer.close()
    report = recording.close()
    assert report.messages == 5 and report.lost == 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread niceness")
def test_the_writer_thread_alone_is_niced():
    sink = _SlowWriter()
    sink.go.set()
    recording = _recording(sink)
    before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    writer = BackgroundWriter(recording, nice=7)
    writer.put("/a", b"q", 0)
    writer.close()
    recording.close()
    assert writer.thread_nice == min(before + 7, 19)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == before


@pytest.mark.parametrize("bad", [{"max_bytes": 0}, {"nice": -1}, {"flush_period_s": 0.0}])
def test_bad_options_are_refused(bad):
    with pytest.raises(ValueError):
        BackgroundWriter(_recording(_SlowWriter()), **bad)
