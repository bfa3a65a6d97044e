"""endo-record's node: batches in receive order, log times never back, the last take.

Review of issue 15's batched takes.
"""

from __future__ import annotations

import threading
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String

from endo_io.bag import BagReader, BagWriter, deserialize
from endo_io.qos import reliable_qos
from endo_io.record import Recording
from endo_io.record_node import (
    MAX_RAISE_NS,
    ReceiveOrder,
    RecordNode,
    _check_options,
    build_parser,
)

MS = 1_000_000


def test_a_batch_is_written_in_receive_order_and_later_arrivals_wait_for_the_next():
    order = ReceiveOrder()
    first = order.batch([(30 * MS, "/b", b"3"), (10 * MS, "/a", b"1"), (60 * MS, "/a", b"6")],
                        cut_ns=40 * MS)
    assert first == [(10 * MS, "/a", b"1"), (30 * MS, "/b", b"3")]
    assert order.held == 1
    # the held one goes with the next batch, in order among the newly taken
    second = order.batch([(50 * MS, "/b", b"5"), (70 * MS, "/b", b"7")], cut_ns=None)
    assert second == [(50 * MS, "/b", b"5"), (60 * MS, "/a", b"6"), (70 * MS, "/b", b"7")]
    assert order.held == 0 and order.raised == 0 and order.last_ns == 70 * MS


def test_a_message_received_before_the_last_written_is_raised_to_it_and_counted():
    # A fragmented image received at 25 ms, takeable only after the batch holding 30 ms was
    # written; then the node clock's offset moving back 2 ms between batches (sim time).
    order = ReceiveOrder()
    assert [t for t, _, _ in order.batch([(30 * MS, "/a", b"")], cut_ns=40 * MS)] == [30 * MS]
    late = order.batch([(25 * MS, "/img", b"big"), (28 * MS, "/a", b""), (45 * MS, "/a", b"")],
                       cut_ns=50 * MS)
    assert [t for t, _, _ in late] == [30 * MS, 30 * MS, 45 * MS]
    assert [topic for _, topic, _ in late] == ["/img", "/a", "/a"]
    assert order.raised == 2
    moved = order.batch([(43 * MS, "/a", b"")], cut_ns=60 * MS)
    assert [t for t, _, _ in moved] == [45 * MS] and order.raised == 3


def test_a_clock_jump_back_is_written_as_it_is_not_raised():
    # use_sim_time over a looping bag: the node clock goes back by the bag's length
    order = ReceiveOrder()
    order.batch([(60_000 * MS, "/a", b"")], cut_ns=None)
    back = 60_000 * MS - MAX_RAISE_NS - 1
    assert order.batch([(back, "/a", b"")], cut_ns=None) == [(back, "/a", b"")]
    assert order.raised == 0 and order.last_ns == back


@pytest.mark.ros
def test_the_last_take_writes_every_subscription_rclpy_still_gives(tmp_path):
    # Review of issue 15: contextlib.suppress(Exception) around the last take lost every
    # message already taken when one subscription refused it, silently.
    output = tmp_path / "end.mcap"
    options = build_parser().parse_args(
        ["--topics", "/rn_test/a", "/rn_test/b", "-o", str(output), "--take-period", "3600"])
    _check_options(options)
    rclpy.init()
    try:
        peer = Node("record_node_test_peer")
        pubs = {t: peer.create_publisher(String, t, reliable_qos(10))
                for t in ("/rn_test/a", "/rn_test/b")}
        probe: list[str] = []
        for topic in pubs:
            peer.create_subscription(String, topic, lambda m: probe.append(m.data),
                                     reliable_qos(10))
        recorder = RecordNode(Recording(BagWriter(output, compression="none")), options)
        executor = SingleThreadedExecutor()
        executor.add_node(peer)
        executor.add_node(recorder)
        deadline = time.monotonic() + 10.0
        while not all(p.get_subscription_count() == 2 for p in pubs.values()):
            assert time.monotonic() < deadline, "recorder did not subscribe"
            executor.spin_once(timeout_sec=0.05)
        for k in range(3):
            for topic, publisher in pubs.items():
                publisher.publish(String(data=f"{topic}:{k}"))
        while len(probe) < 6:  # delivered (the recorder's copies wait in its history)
            assert time.monotonic() < deadline, probe
            executor.spin_once(timeout_sec=0.05)
        executor.spin_once(timeout_sec=0.2)
        executor.shutdown()
        # the first subscription gone (its handle refuses the take), the context shut down
        # as SIGINT shuts it down
        recorder.destroy_subscription(recorder._taken_from["/rn_test/a"])
        rclpy.try_shutdown()
        recorder.close()
        assert recorder.exit_code == 0
    finally:
        rclpy.try_shutdown()
    with BagReader(output) as reader:
        written = [(m.topic, m.log_time_ns) for m in reader.messages()]
    assert [topic for topic, _ in written] == ["/rn_test/b"] * 3
    assert [t for _, t in written] == sorted(t for _, t in written)


def _recorder_with_peer(output, topic, take_period, peer_name, *, extra=(), writer=None,
                        depth=10):
    """A RecordNode on ``topic`` into ``output`` beside a peer publishing there.

    ``extra``: more endo-record arguments; ``writer``: makes the bag writer
    once the options are checked (an uncompressed BagWriter by default);
    ``depth``: the peer's history.
    Returns (publisher, recording, recorder, executor), both nodes in the one
    executor, once the recorder has subscribed.
    """
    options = build_parser().parse_args(
        ["--topics", topic, "-o", str(output), "--take-period", take_period, *extra])
    _check_options(options)
    peer = Node(peer_name)
    publisher = peer.create_publisher(String, topic, reliable_qos(depth))
    recording = Recording(BagWriter(output, compression="none") if writer is None else writer())
    recorder = RecordNode(recording, options)
    executor = SingleThreadedExecutor()
    executor.add_node(peer)
    executor.add_node(recorder)
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() == 0:
        assert time.monotonic() < deadline, "recorder did not subscribe"
        executor.spin_once(timeout_sec=0.05)
    return publisher, recording, recorder, executor


@pytest.mark.ros
def test_taken_messages_keep_their_dds_source_time_as_publish_time(tmp_path):
    # rosbag2 records the send time as publish time: a graph's latency can then be read
    # from the recording alone, from each message's own publish
    output = tmp_path / "published.mcap"
    rclpy.init()
    try:
        publisher, _, recorder, executor = _recorder_with_peer(
            output, "/rn_test/p", "3600", "record_node_test_peer_p")
        sent = []
        for k in range(3):
            before = time.time_ns()
            publisher.publish(String(data=f"p{k}"))
            sent.append((before, time.time_ns()))
            time.sleep(0.05)  # the publishes 50 ms apart, the take (below) after them all
        time.sleep(0.2)
        recorder._take(final=True)
        executor.shutdown()
        recorder.close()
        assert recorder.exit_code == 0
    finally:
        rclpy.try_shutdown()
    with BagReader(output) as reader:
        written = [(m.publish_time_ns, m.log_time_ns, deserialize(m).data)
                   for m in reader.messages()]
    assert [data for _, _, data in written] == ["p0", "p1", "p2"]
    for (published, logged, _), (before, after) in zip(written, sent, strict=True):
        assert before <= published <= after and published <= logged


@pytest.mark.ros
def test_take_period_0_records_each_message_in_its_own_callback(tmp_path):
    output = tmp_path / "each.mcap"
    rclpy.init()
    try:
        publisher, recording, recorder, executor = _recorder_with_peer(
            output, "/rn_test/c", "0", "record_node_test_peer0")
        deadline = time.monotonic() + 10.0
        for k in range(5):
            publisher.publish(String(data=f"c{k}"))
        # the writer thread declares the topic in the report (add_topic is queued to it):
        # looked up again at each turn, not once right after the subscription matched
        while (tally := recording.report.topics.get("/rn_test/c")) is None or tally.received < 5:
            # written by the executor's callbacks, no take timer
            assert time.monotonic() < deadline, tally
            executor.spin_once(timeout_sec=0.05)
        executor.shutdown()
        recorder.close()
        assert recorder.exit_code == 0 and recorder.order.raised == 0
    finally:
        rclpy.try_shutdown()
    with BagReader(output) as reader:
        written = [(m.log_time_ns, deserialize(m)) for m in reader.messages()]
    assert [msg.data for _, msg in written] == [f"c{k}" for k in range(5)]
    times = [t for t, _ in written]
    assert times == sorted(times)


class _StalledDisk(BagWriter):
    """A BagWriter whose writes wait until ``go`` is set (a disk that stalls)."""

    def __init__(self, path, go):
        super().__init__(path, compression="none")
        self._go = go

    def write(self, topic, data, log_time_ns, publish_time_ns=None):
        self._go.wait()
        super().write(topic, data, log_time_ns, publish_time_ns)


@pytest.mark.ros
def test_a_stalled_disk_does_not_stop_the_taking_and_what_the_queue_refuses_is_reported(
        tmp_path):
    # The writer thread waits on the disk; the node keeps taking every 20 ms. Its queue
    # (--buffer-mb, here ~200 bytes) holds what it can; the rest is refused, counted,
    # logged once and reported as lost; everything queued is written once the disk goes on.
    output = tmp_path / "stalled.mcap"
    topic = "/rn_test/s"
    go = threading.Event()
    rclpy.init()
    try:
        publisher, recording, recorder, executor = _recorder_with_peer(
            output, topic, "0.02", "record_node_test_peer_s",
            extra=("--buffer-mb", str(200 / 2**20)), writer=lambda: _StalledDisk(output, go),
            depth=100)
        deadline = time.monotonic() + 10.0
        for k in range(60):  # ~28 bytes of CDR each: ~7 fit the queue
            publisher.publish(String(data=f"stalled message {k:03d}"))
        refused = recorder._writer.refused
        settled = time.monotonic()
        while time.monotonic() - settled < 0.5:  # every message taken: the count settles
            before = sum(refused.values())
            executor.spin_once(timeout_sec=0.05)
            if sum(refused.values()) != before or before == 0:
                settled = time.monotonic()
            assert time.monotonic() < deadline, dict(refused)
        lost = sum(refused.values())
        assert 40 <= lost < 60, lost  # the queue took some, the stall refused the rest
        go.set()
        executor.shutdown()
        recorder.close()
        assert recorder.exit_code == 0
    finally:
        rclpy.try_shutdown()
    report = recording.report
    assert report.topics[topic].received == 60 and report.lost == lost
    with BagReader(output) as reader:
        data = [deserialize(m).data for m in reader.messages()]
    assert len(data) == 60 - lost and data == sorted(data)  # what was queued, in order
    assert data[0] == "stalled message 000"


def test_endo_record_writes_past_the_page_cache_unless_told_not_to(tmp_path, monkeypatch):
    # Session 14: O_DIRECT took the recorder from 10.6-12.3 to 8.3-8.9 CPU-ms per graph
    # frame (bench_flow_node --node record); --no-direct keeps the page cache.
    from endo_io import record_node
    from endo_io.errors import Endo3dError

    assert build_parser().parse_args(["-a"]).direct is True
    assert build_parser().parse_args(["-a", "--no-direct"]).direct is False
    given: list[bool] = []

    class StopError(Endo3dError):
        pass

    def writer(path, *, compression, direct):  # type: ignore[no-untyped-def]
        given.append(direct)
        raise StopError("stop here")

    monkeypatch.setattr(record_node, "BagWriter", writer)
    for extra, expected in (([], True), (["--no-direct"], False)):
        output = tmp_path / f"{expected}.mcap"
        assert record_node.main(["endo-record", "-a", "-o", str(output), *extra]) != 0
        assert given[-1] is expected
