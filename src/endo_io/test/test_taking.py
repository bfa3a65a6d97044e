"""endo_io.taking: messages taken from a subscription the executor never runs."""

from __future__ import annotations

import logging
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from std_msgs.msg import String

from endo_io import taking
from endo_io.qos import reliable_qos
from endo_io.taking import NeverExecutedGroup, system_to_monotonic_ns, take_waiting

S = 1_000_000_000


@pytest.fixture
def node():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node("taking_under_test", context=context)
    yield node
    node.destroy_node()
    rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_messages_wait_until_taken_then_come_oldest_first_with_their_receive_time(node):
    called: list = []
    subscription = node.create_subscription(String, "/taking_test", called.append,
                                            reliable_qos(10), raw=True,
                                            callback_group=NeverExecutedGroup())
    publisher = node.create_publisher(String, "/taking_test", reliable_qos(10))
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() == 0:
        assert time.monotonic() < deadline
        executor.spin_once(timeout_sec=0.05)
    before = time.time_ns()
    for k in range(3):
        publisher.publish(String(data=f"m{k}"))
    found: list = []
    while len(found) < 3:
        assert time.monotonic() < deadline, found
        executor.spin_once(timeout_sec=0.05)  # never runs the subscription's callback
        found += take_waiting(subscription)
    after = time.time_ns()
    assert not called
    assert [deserialize_message(data, String).data for data, _ in found] == ["m0", "m1", "m2"]
    received = [ns for _, ns in found]
    assert received == sorted(received) and before <= received[0] and received[-1] <= after
    assert take_waiting(subscription) == []
    publisher.publish(String(data="typed"))
    typed: list = []
    while not typed:
        assert time.monotonic() < deadline
        typed = take_waiting(subscription, raw=False)
    assert isinstance(typed[0][0], String) and typed[0][0].data == "typed"
    executor.shutdown()


class _Handle:
    """An rclpy subscription handle whose middleware gives no receive time."""

    def __init__(self, messages: list[bytes]) -> None:
        self._messages = messages

    def __enter__(self) -> _Handle:
        return self

    def __exit__(self, *_: object) -> None:
        return None

    def take_message(self, _msg_type: object, _raw: bool):
        return (self._messages.pop(0), {"source_timestamp": 0}) if self._messages else None


class _Subscription:
    msg_type = String

    def __init__(self, messages: list[bytes]) -> None:
        self.handle = _Handle(messages)


def test_without_a_receive_time_the_take_time_is_used_and_said_once(caplog, monkeypatch):
    monkeypatch.setattr(taking, "_warned_no_receive_time", False)
    with caplog.at_level(logging.WARNING, logger="endo_io.taking"):
        before = time.time_ns()
        first = take_waiting(_Subscription([b"a", b"b"]))  # type: ignore[arg-type]
        second = take_waiting(_Subscription([b"c"]))  # type: ignore[arg-type]
        after = time.time_ns()
    assert [data for data, _ in first + second] == [b"a", b"b", b"c"]
    assert all(before <= ns <= after for _, ns in first + second)
    warnings = [r.getMessage() for r in caplog.records if r.name == "endo_io.taking"]
    assert len(warnings) == 1 and "no receive time" in warnings[0]


def test_a_system_time_moves_onto_the_monotonic_clock_by_its_age():
    now_system, now_mono = time.time_ns(), time.monotonic_ns()
    past = system_to_monotonic_ns(now_system - 2 * S)
    # 2 s before now on the monotonic clock, within the time the two reads above took
    assert -S // 2 < (now_mono - 2 * S) - past < S // 2
    # a receive time ahead of the system clock (it was stepped back) is "now", not the future
    ahead = system_to_monotonic_ns(time.time_ns() + 5 * S)
    assert ahead <= time.monotonic_ns() and time.monotonic_ns() - ahead < S // 2
