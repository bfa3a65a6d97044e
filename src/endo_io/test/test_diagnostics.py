"""endo_io.diagnostics.InputHealth: what its status says and counts.

Stale and never-seen inputs, recovery after a window, separate counters,
frames lost in transport, undecodable CDR, no false drop while shutting down.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from endo_io.diagnostics import InputHealth
from endo_io.errors import ClockJumpError, ImageEncodingError
from endo_io.image import array_to_image, image_from_cdr, image_to_array
from endo_io.qos import reliable_qos
from endo_io.sequence_gaps import SequenceGapCounter

MS = 1_000_000


@pytest.fixture
def node():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node("diagnostics_under_test", context=context)
    yield node
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def _values(health: InputHealth) -> dict[str, str]:
    return {kv.key: kv.value for kv in health.status().values}


class FakeClock:
    """A monotonic clock the test moves by hand: the windows below do not depend on the load."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_an_input_never_seen_or_stale_warns_and_recovers(node):
    clock = FakeClock()
    health = InputHealth(node, "image input", settings={"input_stale_s": 0.2}, clock=clock)
    health.watch("/camera")
    status = health.status()
    assert status.level == DiagnosticStatus.WARN
    assert status.message == "no message yet on /camera"
    assert _values(health)["age_s./camera"] == "never"
    health.received("/camera")
    assert health.status().level == DiagnosticStatus.OK and health.status().message == "ok"
    clock.now += 0.19
    assert health.status().level == DiagnosticStatus.OK  # not yet stale
    clock.now += 0.02
    status = health.status()
    assert status.level == DiagnosticStatus.WARN
    assert status.message == "/camera stale: nothing for 0.2 s"
    assert _values(health)["age_s./camera"] == "0.21"
    health.received("/camera")
    assert health.status().level == DiagnosticStatus.OK


def test_a_silent_input_says_whether_it_has_no_publisher_an_incompatible_one_or_a_matched_one(
        node):
    # what a user checks first when an input stays silent: is anyone publishing
    # it here, can this subscription match them, or is it matched and still silent
    health = InputHealth(node, "image input")
    health.subscribe(Image, "/camera", lambda msg: None, reliable_qos(5))
    assert health.status().message == "no message yet on /camera (no publisher)"
    assert _values(health)["publishers./camera"] == "0"

    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)

    def spin_until(condition, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        return condition()

    # a best-effort publisher cannot serve a reliable subscription
    best_effort = node.create_publisher(Image, "/camera", qos_profile_sensor_data)
    assert spin_until(lambda: node.count_publishers("/camera") == 1)
    assert health.status().message == (
        "no message yet on /camera (1 publisher on the graph, none matched: incompatible QoS?)")
    assert _values(health)["publishers./camera"] == "0"
    node.destroy_publisher(best_effort)

    reliable = node.create_publisher(Image, "/camera", reliable_qos(5))
    assert spin_until(lambda: _values(health)["publishers./camera"] == "1")
    assert health.status().message == "no message yet on /camera (1 publisher matched)"
    reliable.publish(array_to_image(np.zeros((4, 4), np.uint8), "mono8"))
    assert spin_until(lambda: _values(health)["received./camera"] == "1")
    assert health.status().level == DiagnosticStatus.OK
    executor.shutdown()


def test_one_drop_warns_for_the_window_then_the_level_returns_to_ok(node):
    # issue 16: "a status stays WARN forever after a single drop"
    clock = FakeClock()
    health = InputHealth(node, "input", window_s=0.3, clock=clock)
    health.guard(lambda: 1 / 0)()
    status = health.status()
    assert status.level == DiagnosticStatus.WARN
    assert "1 dropped in the last 0.3 s (last: ZeroDivisionError" in status.message
    clock.now += 0.29
    assert health.status().level == DiagnosticStatus.WARN  # still within the window
    clock.now += 0.02
    status = health.status()
    assert status.level == DiagnosticStatus.OK and status.message == "ok"
    # the counters stay: the history is not forgotten, only the level recovers
    assert _values(health)["dropped.ZeroDivisionError"] == "1"


def test_an_expected_condition_is_counted_like_a_drop_and_logged_as_a_warning(node, capfd):
    # issue 16: a frame before the pose stream's first pose (every loop) was an [ERROR]
    health = InputHealth(node, "frames")
    health.drop("PoseBeforeStreamError", "frame 7 ns has no pose, processed without: …",
                expected=True)
    health.drop("PoseGapError", "frame 9 ns has no pose, processed without: a gap")
    values = _values(health)
    assert values["dropped"] == "2" and values["dropped.PoseBeforeStreamError"] == "1"
    assert health.status().level == DiagnosticStatus.WARN
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if "so far" in line]
    assert len(lines) == 2, err
    assert lines[0].startswith("[WARN]") and lines[0].endswith(
        "PoseBeforeStreamError (1 so far): frame 7 ns has no pose, processed without: …")
    assert lines[1].startswith("[ERROR]") and "dropped message (1 so far): PoseGapError" in lines[1]


def test_counters_separate_received_processed_and_dropped_by_cause(node):
    health = InputHealth(node, "pairs")
    outputs = []

    def half(value: int) -> None:
        if value < 0:
            raise ImageEncodingError("bad")
        if value % 2:  # every second message completes an output
            outputs.append(value)
            health.ok()

    guarded = health.guard(half, input_name="/in", processed=False)
    for value in (0, 1, 2, 3, -1, 5):
        guarded(value)
    values = _values(health)
    assert values["received"] == values["received./in"] == "6"
    assert values["processed"] == "3" == str(len(outputs))
    assert values["dropped"] == values["dropped.ImageEncodingError"] == "1"


def test_a_clock_jump_is_counted_as_a_reset_not_a_drop(node):
    health = InputHealth(node, "poses", window_s=60.0)

    def insert() -> None:
        raise ClockJumpError("pose time jumped back 3.000 s; pose buffer reset")

    health.guard(insert)()
    values = _values(health)
    assert values["clock_jumps"] == "1" and values["dropped"] == "0"
    assert "1 clock jump" in health.status().message
    assert health.status().level == DiagnosticStatus.WARN


def test_set_problem_holds_warn_until_cleared_and_refresh_runs_each_period(node):
    health = InputHealth(node, "tracker input")
    state = {"connected": False}

    def refresh() -> None:
        message = None if state["connected"] else "not connected to 127.0.0.1:18944"
        health.set_problem("connection", message)

    health.on_refresh(refresh)
    health.publish()
    assert health.status().message == "not connected to 127.0.0.1:18944"
    state["connected"] = True
    health.publish()
    assert health.status().level == DiagnosticStatus.OK


def test_gap_counter_counts_missing_frames_at_the_estimated_rate():
    counter = SequenceGapCounter()
    period = 33_333_333
    stamps = [k * period + (k % 3) * 2 * MS for k in range(60)]  # ±2 ms jitter
    missing = {20, 21, 40}
    counts = [counter.add(s) for k, s in enumerate(stamps) if k not in missing]
    assert counter.lost == 3 and sum(counts) == 3
    assert counter.period_ns == pytest.approx(period, rel=0.1)
    # a pause of 10 s (a replay between passes) is not loss, nor is a jump back
    assert counter.add(stamps[-1] + 10_000 * MS) == 0
    assert counter.add(0) == 0 and counter.lost == 3
    # a new stream at 15 Hz: no loss counted while the estimate follows it
    counts = [counter.add(k * 2 * period) for k in range(1, 40)]
    assert sum(counts) <= 2


def _matched_publisher(node: Node, topic: str) -> tuple[Any, SingleThreadedExecutor]:
    """An Image publisher on ``topic`` once the node's subscription matched, and an executor."""
    publisher = node.create_publisher(Image, topic, reliable_qos(10))
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return publisher, executor


def test_undecodable_cdr_is_logged_and_counted_and_good_frames_pass(node):
    health = InputHealth(node, "image input")
    got: list[Image] = []
    # decoded as the image nodes decode (pixels a view of the bytes)
    health.subscribe(Image, "/diag_test/image", got.append, reliable_qos(10), gaps=True,
                     decode=image_from_cdr)
    publisher, executor = _matched_publisher(node, "/diag_test/image")
    good = array_to_image(np.ones((4, 6), np.float32), "32FC1", 1_000 * MS, "cam")
    data = serialize_message(good)
    for payload in (data, data[:40], b"\x00\x01\x00\x00" + b"\xff" * 64, good):
        publisher.publish(payload)
    deadline = time.monotonic() + 10.0
    while health.dropped["UndecodableMessageError"] + len(got) < 4:
        executor.spin_once(timeout_sec=0.05)
        assert time.monotonic() < deadline, _values(health)
    assert [m.width for m in got] == [6, 6]
    values = _values(health)
    assert values["dropped.UndecodableMessageError"] == "2"
    assert values["received./diag_test/image"] == "4" and values["processed"] == "2"
    assert "do not decode as Image" in health.last_error
    assert "truncated at header.frame_id: 4294967295 byte(s) needed" in health.last_error
    executor.shutdown()


def test_a_passive_input_waits_in_dds_until_taken_and_counts_what_it_takes(node):
    health = InputHealth(node, "image input")
    taken: list = []
    passive = health.subscribe_passive(Image, "/diag_test/passive",
                                       lambda msg, arrival: taken.append((msg, arrival)),
                                       reliable_qos(10), decode=image_from_cdr)
    publisher, executor = _matched_publisher(node, "/diag_test/passive")
    good = [array_to_image(np.full((4, 6), k, np.float32), "32FC1", (1_000 + k) * MS, "cam")
            for k in range(3)]
    for payload in (serialize_message(good[0]), b"\x00\x01\x00\x00" + b"\xff" * 64,
                    serialize_message(good[1]), good[2]):
        publisher.publish(payload)
    for _ in range(20):  # the executor never takes them itself
        executor.spin_once(timeout_sec=0.01)
    assert not taken and not health.dropped
    deadline = time.monotonic() + 10.0
    while len(taken) + health.dropped["UndecodableMessageError"] < 4:
        assert time.monotonic() < deadline, _values(health)
        passive.take()
        time.sleep(0.01)
    # oldest first, decoded as the nodes decode, each with its arrival on the monotonic clock
    assert [float(image_to_array(msg)[0, 0]) for msg, _ in taken] == [0.0, 1.0, 2.0]
    assert all(0 < time.monotonic_ns() - arrival < 20 * 10**9 for _, arrival in taken)
    assert passive.take() == 0
    # a message given directly (tests, offline drivers) takes the same path
    passive.subscription.callback(good[0])
    assert float(image_to_array(taken[-1][0])[0, 0]) == 0.0 and len(taken) == 4
    values = _values(health)
    assert values["received./diag_test/passive"] == "5"
    assert values["dropped.UndecodableMessageError"] == "1" and values["processed"] == "0"
    executor.shutdown()


def test_a_passive_input_wakes_the_node_at_each_arrival_only_while_asked(node):
    health = InputHealth(node, "image input")
    taken: list = []
    woken: list = []
    passive = health.subscribe_passive(Image, "/diag_test/woken",
                                       lambda msg, arrival: taken.append(msg), reliable_qos(10),
                                       decode=image_from_cdr, on_arrival=lambda: woken.append(1))
    publisher, executor = _matched_publisher(node, "/diag_test/woken")
    frames = [array_to_image(np.full((2, 3), k, np.float32), "32FC1", k * MS, "cam")
              for k in range(3)]
    publisher.publish(frames[0])
    for _ in range(20):  # not asked: the message waits in DDS
        executor.spin_once(timeout_sec=0.01)
    assert not taken and not woken
    passive.wake_on_arrival(True)
    deadline = time.monotonic() + 10.0
    while len(taken) < 1:  # asked: the executor delivers the waiting one, then on_arrival
        assert time.monotonic() < deadline
        executor.spin_once(timeout_sec=0.01)
    publisher.publish(frames[1])
    while len(taken) < 2:  # and each new one
        assert time.monotonic() < deadline
        executor.spin_once(timeout_sec=0.01)
    assert [float(image_to_array(msg)[0, 0]) for msg in taken] == [0.0, 1.0] and woken == [1, 1]
    passive.wake_on_arrival(False)
    executor.spin_once(timeout_sec=0.01)  # the wait set rebuilt without it
    publisher.publish(frames[2])
    for _ in range(20):
        executor.spin_once(timeout_sec=0.01)
    assert len(taken) == 2
    while passive.take() == 0:  # still there to be taken
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert float(image_to_array(taken[-1])[0, 0]) == 2.0 and woken == [1, 1]
    values = _values(health)
    assert values["received./diag_test/woken"] == "3" and values["dropped"] == "0"
    executor.shutdown()


def test_an_error_while_shutting_down_is_not_a_dropped_message():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node("shutdown_under_test", context=context)
    health = InputHealth(node, "input")
    publisher = node.create_publisher(Image, "/diag_test/out", reliable_qos(1))
    rclpy.shutdown(context=context)  # what SIGINT does while a callback runs
    health.guard(lambda: publisher.publish(Image()))()
    assert not health.dropped and health.processed == 0
    node.destroy_node()
