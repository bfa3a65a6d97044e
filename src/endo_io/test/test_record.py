"""endo-record's ROS-free core: topic choice, subscription QoS, and the recording limits."""

from __future__ import annotations

import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from endo_io.record import (
    DEFAULT_QUEUE_DEPTH,
    EXCLUDED_BY_DEFAULT,
    Recording,
    RecordOptionError,
    TopicChoice,
    adapt_request_to_offers,
    is_hidden,
    mixed_offer_warning,
    seconds_to_ns,
    topics_to_record,
)

GRAPH = [
    ("/rosout", ["rcl_interfaces/msg/Log"]),
    ("/parameter_events", ["rcl_interfaces/msg/ParameterEvent"]),
    ("/endoscope/image_raw", ["sensor_msgs/msg/Image"]),
    ("/endoscope/camera_info", ["sensor_msgs/msg/CameraInfo"]),
    ("/_hidden/state", ["std_msgs/msg/Float32"]),
    ("/tool/pose", ["geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped"]),
    ("/only_subscribed", []),
]


def test_all_records_everything_but_rosout_parameter_events_and_hidden_topics():
    chosen = topics_to_record(GRAPH, record_all=True)
    assert [c.name for c in chosen] == [
        "/endoscope/camera_info",
        "/endoscope/image_raw",
        "/tool/pose",
    ]
    assert chosen[1] == TopicChoice("/endoscope/image_raw", "sensor_msgs/msg/Image")
    # A topic with two types is recorded as the first; the other is reported.
    assert chosen[2].msgtype == "geometry_msgs/msg/PoseStamped"
    assert chosen[2].other_types == ("geometry_msgs/msg/TransformStamped",)
    assert {"/rosout", "/parameter_events"} == EXCLUDED_BY_DEFAULT


def test_excluded_and_hidden_topics_are_recorded_when_asked_for_by_name():
    chosen = topics_to_record(GRAPH, ["/rosout", "/_hidden/state"], record_all=True)
    assert {c.name for c in chosen} >= {"/rosout", "/_hidden/state"}
    assert "/parameter_events" not in {c.name for c in chosen}


def test_listed_topics_only_and_each_only_once():
    requested = ["/endoscope/image_raw", "/not/yet/published"]
    assert [c.name for c in topics_to_record(GRAPH, requested)] == ["/endoscope/image_raw"]
    assert topics_to_record(GRAPH, requested, already={"/endoscope/image_raw"}) == []
    later = [*GRAPH, ("/not/yet/published", ["std_msgs/msg/Float32"])]
    assert [
        c.name for c in topics_to_record(later, requested, already={"/endoscope/image_raw"})
    ] == ["/not/yet/published"]


def test_hidden_topic_names():
    assert is_hidden("/_private")
    assert is_hidden("/ns/_private/topic")
    assert not is_hidden("/endoscope/image_raw")
    assert not is_hidden("/a_b")


def _offer(reliability, durability):
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=1, reliability=reliability, durability=durability
    )


RELIABLE_VOLATILE = _offer(ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)
RELIABLE_LATCHED = _offer(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
BEST_EFFORT = _offer(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE)


@pytest.mark.parametrize(
    ("offers", "reliability", "durability"),
    [
        ([RELIABLE_VOLATILE], ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE),
        (
            [RELIABLE_LATCHED, RELIABLE_LATCHED],
            ReliabilityPolicy.RELIABLE,
            DurabilityPolicy.TRANSIENT_LOCAL,
        ),
        (
            [RELIABLE_LATCHED, RELIABLE_VOLATILE],
            ReliabilityPolicy.RELIABLE,
            DurabilityPolicy.VOLATILE,
        ),
        ([BEST_EFFORT], ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE),
        (
            [RELIABLE_VOLATILE, BEST_EFFORT],
            ReliabilityPolicy.BEST_EFFORT,
            DurabilityPolicy.VOLATILE,
        ),
        ([], ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE),
    ],
)
def test_subscription_qos_matches_every_publisher(offers, reliability, durability):
    request = adapt_request_to_offers(offers)
    assert request.reliability == reliability
    assert request.durability == durability
    assert request.history == HistoryPolicy.KEEP_LAST
    assert request.depth == DEFAULT_QUEUE_DEPTH
    assert adapt_request_to_offers(offers, depth=3).depth == 3


def test_mixed_offers_are_warned_about():
    assert mixed_offer_warning("/t", [RELIABLE_VOLATILE, RELIABLE_VOLATILE]) == ""
    assert "best effort" in mixed_offer_warning("/t", [RELIABLE_VOLATILE, BEST_EFFORT])
    assert "transient local" in mixed_offer_warning("/t", [RELIABLE_LATCHED, RELIABLE_VOLATILE])
    with pytest.raises(RecordOptionError, match="depth"):
        adapt_request_to_offers([], depth=0)


class FakeWriter:
    def __init__(self) -> None:
        self.topics: dict[str, tuple[str, str]] = {}
        self.messages: list[tuple[str, bytes, int, int | None]] = []
        self.flushes = 0
        self.closes = 0

    def add_topic(self, name: str, msgtype: str, offered_qos_profiles: str = "") -> None:
        self.topics[name] = (msgtype, offered_qos_profiles)

    def write(self, topic, data, log_time_ns, publish_time_ns=None) -> None:
        assert topic in self.topics
        self.messages.append((topic, data, log_time_ns, publish_time_ns))

    def flush(self) -> None:
        self.flushes += 1

    def close(self) -> None:
        self.closes += 1

    @property
    def written(self) -> dict[str, tuple[int, int]]:
        counts: dict[str, tuple[int, int]] = {}
        for topic, data, _, _ in self.messages:
            messages, size = counts.get(topic, (0, 0))
            counts[topic] = (messages + 1, size + len(data))
        return counts


def test_recording_writes_receive_time_as_log_and_publish_time_and_counts():
    writer = FakeWriter()
    recording = Recording(writer)
    recording.start(1_000)
    recording.add_topic("/a", "std_msgs/msg/Float32", "- history: keep_last")
    recording.add_topic("/b", "sensor_msgs/msg/Image", "")
    assert not recording.write("/a", b"\x00\x01\x00\x00\x00\x00\x80\x3f", 2_000)
    assert not recording.write("/b", b"x" * 100, 2_500)
    assert not recording.write("/a", b"\x00\x01\x00\x00\x00\x00\x00\x40", 3_000)
    assert writer.topics["/a"] == ("std_msgs/msg/Float32", "- history: keep_last")
    assert writer.messages[1] == ("/b", b"x" * 100, 2_500, 2_500)
    report = recording.close()
    recording.close()
    assert writer.closes == 1
    assert report.messages == 3
    assert report.bytes == 116
    assert report.topics["/a"].messages == 2
    assert (report.first_ns, report.last_ns) == (2_000, 3_000)
    # After closing nothing more is written.
    assert recording.write("/a", b"late", 4_000)
    assert len(writer.messages) == 3


def test_max_messages_stops_after_exactly_n():
    writer = FakeWriter()
    recording = Recording(writer, max_messages=3)
    recording.add_topic("/a", "std_msgs/msg/Float32", "")
    assert [recording.write("/a", b"m", t) for t in range(5)] == [False, False, True, True, True]
    assert len(writer.messages) == 3
    assert recording.report.stop_reason == "3 messages"


def test_max_duration_counts_from_start():
    writer = FakeWriter()
    recording = Recording(writer, max_duration_ns=seconds_to_ns(2.0))
    recording.start(10_000_000_000)
    recording.add_topic("/a", "std_msgs/msg/Float32", "")
    assert not recording.limit_reached(11_999_999_999)
    assert not recording.write("/a", b"m", 11_000_000_000)
    assert recording.limit_reached(12_000_000_000)
    assert recording.write("/a", b"m", 12_000_000_001)
    assert len(writer.messages) == 1
    assert recording.report.stop_reason == "2 s"


def test_flush_passes_through_until_closed():
    writer = FakeWriter()
    recording = Recording(writer)
    recording.flush()
    recording.flush()
    recording.close()
    recording.flush()
    assert writer.flushes == 2


def test_bad_limits_are_named_errors():
    with pytest.raises(RecordOptionError, match="max messages"):
        Recording(FakeWriter(), max_messages=0)
    with pytest.raises(RecordOptionError, match="positive"):
        seconds_to_ns(0.0)
    with pytest.raises(RecordOptionError, match="positive"):
        seconds_to_ns(float("inf"))
    assert seconds_to_ns(None) is None
    assert seconds_to_ns(1.5) == 1_500_000_000


def test_record_cli_rejects_bad_options_before_starting_ros(tmp_path, capsys):
    from endo_io.record_node import main

    assert main(["endo-record", "-o", str(tmp_path / "a.mcap")]) == 2
    assert "--topics" in capsys.readouterr().err
    existing = tmp_path / "existing.mcap"
    existing.write_bytes(b"keep me")
    assert main(["endo-record", "--all", "-o", str(existing)]) == 2
    assert "not overwriting" in capsys.readouterr().err
    assert existing.read_bytes() == b"keep me"
    b, c = str(tmp_path / "b.mcap"), str(tmp_path / "c.mcap")
    assert main(["endo-record", "--all", "--max-messages", "0", "-o", b]) == 2
    assert "--max-messages" in capsys.readouterr().err
    assert main(["endo-record", "--all", "--max-duration", "-1", "-o", c]) == 2
    assert "positive" in capsys.readouterr().err
    assert not (tmp_path / "a.mcap").exists()
    assert not (tmp_path / "b.mcap").exists()
    assert not (tmp_path / "c.mcap").exists()
