"""Newest-frame subscriptions: a busy node processes the newest frame, counts the rest skipped.

Frames are published while the subscriber does not spin (a node busy with an
earlier frame); one spin then delivers only the newest, and /diagnostics says
how many were skipped (not dropped, not lost). A frame younger than
``frame_backlog_s`` is not stale: a short stall delays frames instead of
skipping them; past it the node skips to the newest, and two such skips
within a second keep it on the newest frame. With ``newest_frame`` false
every frame comes, in order. Also the header stamp read from the CDR bytes.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image

from endo_io import diagnostics
from endo_io.diagnostics import InputHealth
from endo_io.image import array_to_image
from endo_io.qos import NEWEST_FRAME_DEPTH, NEWEST_FRAME_QOS, reliable_qos
from endo_io.serialized_stamp import serialized_header_stamp_ns
from endo_io.stamp import stamp_to_ns

PERIOD_NS = 33_333_333
START_NS = 1_700_000_000 * 1_000_000_000


@pytest.fixture
def node():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node("newest_frame_under_test", context=context)
    yield node
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def _frame(k: int) -> Image:
    return array_to_image(np.full((4, 6), k, np.float32), "32FC1", START_NS + k * PERIOD_NS, "c")


def _deliver(node: Node, health: InputHealth, topic: str, frames: int, got: list[Image],
             expected_calls: int, *, wait_after: int = -1, wait_s: float = 0.0,
             first: int = 0) -> None:
    """Publish ``frames`` frames while not spinning, then spin until ``expected_calls`` came.

    Frames are numbered from ``first``; ``wait_s`` seconds pass after
    publishing frame ``wait_after`` (a stall upstream).
    """
    publisher = node.create_publisher(Image, topic, reliable_qos(NEWEST_FRAME_DEPTH))
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + 10.0
    while publisher.get_subscription_count() == 0:
        executor.spin_once(timeout_sec=0.05)
        assert time.monotonic() < deadline, "no subscription matched"
    for k in range(first, first + frames):
        publisher.publish(_frame(k))
        if k == wait_after:
            time.sleep(wait_s)
    time.sleep(0.3)  # every frame has reached the subscription's queue
    deadline = time.monotonic() + 10.0
    while len(got) < expected_calls:
        executor.spin_once(timeout_sec=0.05)
        assert time.monotonic() < deadline, (len(got), health.skipped)
    executor.spin_once(timeout_sec=0.2)  # nothing else may come
    executor.shutdown()


def _values(health: InputHealth) -> dict[str, str]:
    return {kv.key: kv.value for kv in health.status().values}


def test_a_busy_node_gets_the_newest_frame_and_counts_the_stale_ones_as_skipped(node):
    health = InputHealth(node, "image input", settings={"newest_frame": True})
    got: list[Image] = []
    health.subscribe(Image, "/newest_test/image", got.append, NEWEST_FRAME_QOS, gaps=True,
                     newest=True)
    _deliver(node, health, "/newest_test/image", 5, got, 1)
    assert [stamp_to_ns(m.header.stamp) for m in got] == [START_NS + 4 * PERIOD_NS]
    assert np.frombuffer(bytes(got[0].data), np.float32)[0] == 4.0
    values = _values(health)
    assert values["received"] == "5" and values["processed"] == "1"
    assert values["skipped"] == values["skipped./newest_test/image"] == "4"
    assert values["dropped"] == "0" and values["lost"] == "0"


def _stamps(got: list[Image]) -> list[int]:
    return [(stamp_to_ns(m.header.stamp) - START_NS) // PERIOD_NS for m in got]


def test_frames_younger_than_the_backlog_limit_are_processed_in_order_not_skipped(node):
    # the limit above the test's 0.3 s: a stall that short delays every frame, skips none
    got: list[Image] = []
    health = _limited(node, "/newest_test/young", got, 5.0)
    _deliver(node, health, "/newest_test/young", 5, got, 5)
    assert _stamps(got) == [0, 1, 2, 3, 4]
    values = _values(health)
    assert values["processed"] == "5" and values["skipped"] == "0"


def _limited(node: Node, topic: str, got: list[Image], limit_s: float) -> InputHealth:
    """A newest-frame input on ``topic`` with ``frame_backlog_s`` ``limit_s``, into ``got``."""
    health = InputHealth(node, "image input", settings={"newest_frame": True,
                                                        "frame_backlog_s": limit_s})
    health.subscribe(Image, topic, got.append, NEWEST_FRAME_QOS, gaps=True, newest=True)
    return health


def test_past_the_limit_the_node_skips_to_the_newest_and_a_lone_stall_costs_no_more(node):
    # frames 0-2 wait 1.0 s longer than 3-4: at spin time they are ~1.3 s old, past the
    # 0.8 s limit (3-4 ~0.3 s, inside it); the node skips to the newest, 4. Frames 5-7
    # then come young: in order, the lone stall skipped nothing more
    got: list[Image] = []
    health = _limited(node, "/newest_test/lone", got, 0.8)
    _deliver(node, health, "/newest_test/lone", 5, got, 1, wait_after=2, wait_s=1.0)
    assert _stamps(got) == [4]
    values = _values(health)
    assert values["received"] == "5" and values["processed"] == "1"
    assert values["skipped"] == "4" and values["dropped"] == "0" and values["lost"] == "0"
    _deliver(node, health, "/newest_test/lone", 3, got, 4, first=5)
    assert _stamps(got) == [4, 5, 6, 7]
    assert _values(health)["skipped"] == "4"


def test_two_skips_within_the_hold_keep_the_node_on_the_newest_frame(node, monkeypatch):
    monkeypatch.setattr(diagnostics, "BEHIND_HOLD_S", 30.0)  # the test's own pace can't end it
    got: list[Image] = []
    health = _limited(node, "/newest_test/behind", got, 0.8)
    _deliver(node, health, "/newest_test/behind", 5, got, 1, wait_after=2, wait_s=1.0)
    _deliver(node, health, "/newest_test/behind", 3, got, 2, first=5, wait_after=5, wait_s=1.0)
    assert _stamps(got) == [4, 7]  # a second stale frame within the hold: behind
    # young frames, but the node is behind: a frame with a newer one waiting is passed over
    held_until = health._behind_until["/newest_test/behind"]
    _deliver(node, health, "/newest_test/behind", 3, got, 3, first=8)
    assert _stamps(got) == [4, 7, 10]
    assert _values(health)["skipped"] == "8"
    # ... and those young skips do not extend the hold (frames that come in pairs
    # would otherwise keep a fast node behind for good: review of session 15)
    assert health._behind_until["/newest_test/behind"] == held_until


def test_a_zero_limit_skips_every_frame_that_has_a_newer_one_behind_it(node):
    got: list[Image] = []
    health = _limited(node, "/newest_test/zero", got, 0.0)
    _deliver(node, health, "/newest_test/zero", 5, got, 1)
    assert _stamps(got) == [4]
    assert _values(health)["skipped"] == "4"


def test_with_newest_frame_false_every_frame_comes_in_order(node):
    health = InputHealth(node, "image input", settings={"newest_frame": False})
    got: list[Image] = []
    health.subscribe(Image, "/newest_test/all", got.append, NEWEST_FRAME_QOS, gaps=True,
                     newest=True)
    _deliver(node, health, "/newest_test/all", 5, got, 5)
    assert [stamp_to_ns(m.header.stamp) for m in got] == [
        START_NS + k * PERIOD_NS for k in range(5)
    ]
    assert _values(health)["skipped"] == "0"


def test_the_header_stamp_is_read_from_the_cdr_bytes():
    for msg in (_frame(7), CameraInfo()):
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_123, 456_789
        assert serialized_header_stamp_ns(serialize_message(msg)) == 1_700_000_123_000_456_789
    assert serialized_header_stamp_ns(b"\x00\x01\x00") is None
    assert serialized_header_stamp_ns(b"\x00\x07" + bytes(20)) is None  # not plain CDR
