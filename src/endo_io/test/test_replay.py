"""endo-replay's ROS-free core: selection, remapping, QoS, and the playback schedule."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from endo_io.bag import BagMessage
from endo_io.bag.qos_yaml import qos_profiles_to_yaml
from endo_io.errors import BagCorruptError
from endo_io.replay import (
    DEFAULT_PUBLISHER_DEPTH,
    PlaybackSchedule,
    Player,
    ReplayOptionError,
    TopicTally,
    adapt_offer_to_recorded_offers,
    build_remaps,
    load_qos_overrides,
    output_topics,
    parse_remap,
    publisher_qos_for_topic,
    select_topics,
)

MS = 1_000_000
T0 = 1_763_800_000_000_000_000  # a realistic epoch log time


# ---------------------------------------------------------------- selection


def test_select_topics_all_sorted_or_requested_with_missing_reported():
    bag = ["/b", "/a", "/c"]
    assert select_topics(bag, None) == (["/a", "/b", "/c"], [])
    assert select_topics(bag, []) == (["/a", "/b", "/c"], [])
    assert select_topics(bag, ["/c", "/x", "/a", "/x"]) == (["/a", "/c"], ["/x"])
    assert select_topics(bag, ["c", "y"]) == (["/c"], ["/y"])


def test_remap_rules_parse_and_apply():
    assert parse_remap("/camera/image:=/endoscope/image_raw") == (
        "/camera/image",
        "/endoscope/image_raw",
    )
    remaps = build_remaps(["/a:=/x", " /b := /y "])
    assert remaps == {"/a": "/x", "/b": "/y"}
    assert output_topics(["/a", "/b", "/c"], remaps) == {"/a": "/x", "/b": "/y", "/c": "/c"}


@pytest.mark.parametrize("rule", ["/a=/b", "/a:=", ":=/b", "a:=/b", "/a:=b"])
def test_malformed_remap_rules_are_named_errors(rule):
    with pytest.raises(ReplayOptionError, match="remap rule"):
        parse_remap(rule)


def test_remaps_that_merge_two_topics_or_conflict_are_rejected():
    with pytest.raises(ReplayOptionError, match="both be published on /b"):
        output_topics(["/a", "/b"], {"/a": "/b"})
    with pytest.raises(ReplayOptionError, match="remapped twice"):
        build_remaps(["/a:=/x", "/a:=/y"])


# ---------------------------------------------------------------- QoS


def _offer(reliability, durability, depth=7, deadline_ns=None):
    kwargs = {}
    if deadline_ns is not None:
        kwargs["deadline"] = Duration(nanoseconds=deadline_ns)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=reliability,
        durability=durability,
        **kwargs,
    )


def test_recorded_offer_is_reused_with_default_history():
    latched = _offer(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, depth=1)
    profile, mixed = adapt_offer_to_recorded_offers([latched, latched])
    assert not mixed
    assert profile.reliability == ReliabilityPolicy.RELIABLE
    assert profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert profile.history == HistoryPolicy.KEEP_LAST
    assert profile.depth == DEFAULT_PUBLISHER_DEPTH

    best_effort = _offer(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE)
    profile, mixed = adapt_offer_to_recorded_offers([best_effort])
    assert (profile.reliability, mixed) == (ReliabilityPolicy.BEST_EFFORT, False)


def test_differing_or_missing_offers_fall_back_to_reliable_volatile():
    a = _offer(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE)
    b = _offer(ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)
    for offers, expect_mixed in (([a, b], True), ([], False)):
        profile, mixed = adapt_offer_to_recorded_offers(offers)
        assert mixed is expect_mixed
        assert profile.reliability == ReliabilityPolicy.RELIABLE
        assert profile.durability == DurabilityPolicy.VOLATILE
        assert profile.depth == DEFAULT_PUBLISHER_DEPTH
    # Differing history only (local to the writer) is not a mixed offer.
    profile, mixed = adapt_offer_to_recorded_offers([a, _offer(a.reliability, a.durability, 99)])
    assert not mixed and profile.reliability == ReliabilityPolicy.BEST_EFFORT
    # A differing deadline is.
    _, mixed = adapt_offer_to_recorded_offers([a, _offer(a.reliability, a.durability, 7, 10 * MS)])
    assert mixed


def test_publisher_qos_from_recorded_yaml_text_or_override():
    latched = _offer(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
    text = qos_profiles_to_yaml([latched])
    profile, warning = publisher_qos_for_topic("/calib", text, {})
    assert warning == ""
    assert profile.durability == DurabilityPolicy.TRANSIENT_LOCAL

    override = _offer(ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE, depth=3)
    assert publisher_qos_for_topic("/calib", text, {"/calib": override})[0] is override
    # An override may name the topic as published (after remapping).
    assert publisher_qos_for_topic("/calib", text, {"/out": override}, "/out")[0] is override

    profile, warning = publisher_qos_for_topic("/calib", "- {not: [valid", {})
    assert "/calib" in warning
    assert profile.reliability == ReliabilityPolicy.RELIABLE


def test_qos_override_file_in_ros2_bag_play_format(tmp_path: Path):
    path = tmp_path / "overrides.yaml"
    path.write_text(
        "/talker:\n"
        "  reliability: best_effort\n"
        "  history: keep_all\n"
        "/calib:\n"
        "  durability: transient_local\n"
        "  depth: 1\n"
        "  deadline:\n"
        "    sec: 2\n"
        "    nsec: 500\n"
    )
    overrides = load_qos_overrides(path)
    assert set(overrides) == {"/talker", "/calib"}
    talker = overrides["/talker"]
    assert talker.reliability == ReliabilityPolicy.BEST_EFFORT
    assert talker.history == HistoryPolicy.KEEP_ALL
    assert talker.durability == DurabilityPolicy.VOLATILE  # not given: rosbag2's default
    calib = overrides["/calib"]
    assert calib.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert calib.reliability == ReliabilityPolicy.RELIABLE
    assert calib.depth == 1
    assert calib.deadline.nanoseconds == 2_000_000_500


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("/t:\n  reliability: sometimes\n", "reliability 'sometimes'"),
        ("/t:\n  relability: reliable\n", "unknown policy 'relability'"),
        ("/t:\n  deadline:\n    sec: 1\n", "needs both sec and nsec"),
        ("/t:\n  depth: -1\n", "depth"),
        ("- /t\n", "not a mapping"),
        ("/t: [1, 2\n", "not YAML"),
    ],
)
def test_bad_qos_override_files_are_named_errors(tmp_path: Path, body: str, match: str):
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    with pytest.raises(ReplayOptionError, match=match):
        load_qos_overrides(path)


# ---------------------------------------------------------------- schedule


def test_schedule_maps_log_time_to_wall_offset_by_rate():
    schedule = PlaybackSchedule(origin_ns=T0, rate=2.0)
    assert schedule.offset_ns(T0) == 0
    assert schedule.offset_ns(T0 + 1_000 * MS) == 500 * MS
    assert schedule.offset_ns(T0 - 5 * MS) == 0  # before the origin: due at once
    assert schedule.bag_time_ns(500 * MS) == T0 + 1_000 * MS
    fast = PlaybackSchedule(origin_ns=T0, rate=math.inf)
    assert fast.offset_ns(T0 + 10**12) == 0
    for rate in (0.0, -1.0, math.nan):
        with pytest.raises(ReplayOptionError, match="rate"):
            PlaybackSchedule(origin_ns=T0, rate=rate)


class FakeWaiter:
    """A monotonic clock that only moves when the player sleeps (or a test moves it)."""

    def __init__(self, oversleep_ns: int = 0, start_ns: int = 5_000 * MS) -> None:
        self.now = start_ns
        self.oversleep_ns = oversleep_ns
        self.stop = False
        self.sleeps: list[int] = []

    def monotonic_ns(self) -> int:
        return self.now

    def wait(self, seconds: float) -> bool:
        if self.stop:
            return True
        if seconds > 0:
            step = round(seconds * 1e9) + self.oversleep_ns
            self.sleeps.append(step)
            self.now += step
        return self.stop


def _messages(times_ms: list[tuple[str, int]]) -> list[BagMessage]:
    return [
        BagMessage(topic, "std_msgs/msg/Float32", T0 + t * MS, bytes([i]) * 8, T0 + t * MS)
        for i, (topic, t) in enumerate(times_ms)
    ]


def _player(messages, waiter, *, rate=1.0, origin=T0, loop=False, topics=("/a", "/b"), sent=None):
    sent = [] if sent is None else sent

    def open_messages() -> Iterator[BagMessage]:
        return iter([m for m in messages if m.log_time_ns >= origin])

    def publisher(topic):
        return lambda data: sent.append((topic, waiter.now, data))

    tallies = {t: TopicTally(t, "std_msgs/msg/Float32") for t in ("/a", "/b", "/unknown")}
    publishers = {t: publisher(t) for t in topics}
    player = Player(
        open_messages,
        publishers,
        tallies,
        PlaybackSchedule(origin, rate),
        loop=loop,
        waiter=waiter,
    )
    return player, sent


def test_messages_go_out_at_their_log_time_offsets_divided_by_rate():
    msgs = _messages([("/a", 0), ("/b", 10), ("/a", 33), ("/b", 50), ("/a", 100)])
    waiter = FakeWaiter()
    start = waiter.now
    player, sent = _player(msgs, waiter, rate=2.0)
    report = player.run()
    assert [t for _, t, _ in sent] == [start + ms * MS // 2 for ms in (0, 10, 33, 50, 100)]
    assert [(topic, data) for topic, _, data in sent] == [(m.topic, m.data) for m in msgs]
    assert report.topics["/a"].published == 3
    assert report.topics["/b"].published == 2
    assert report.topics["/a"].bytes == 24
    assert report.bag_span_ns == 100 * MS
    assert report.wall_ns == 50 * MS
    assert report.achieved_rate == pytest.approx(2.0)
    assert report.passes == 1 and not report.interrupted and report.error == ""


def test_oversleeping_does_not_accumulate_drift():
    # Each sleep overshoots by 3 ms; 200 messages 10 ms apart. Sleeping for the
    # gap after each message would end 600 ms late; scheduling by target time
    # keeps every message within one overshoot of its due time.
    msgs = _messages([("/a", 10 * i) for i in range(200)])
    waiter = FakeWaiter(oversleep_ns=3 * MS)
    start = waiter.now
    player, sent = _player(msgs, waiter)
    player.run()
    lateness = [t - (start + m.log_time_ns - T0) for (_, t, _), m in zip(sent, msgs, strict=True)]
    assert min(lateness) >= 0
    assert max(lateness) == 3 * MS


def test_a_late_message_does_not_delay_the_following_ones():
    msgs = _messages([("/a", 0), ("/a", 10), ("/a", 20), ("/a", 30), ("/a", 40)])
    waiter = FakeWaiter()
    start = waiter.now
    sent: list = []
    player, sent = _player(msgs, waiter, sent=sent)

    slow = player._publishers["/a"]

    def slow_second_publish(data: bytes) -> None:
        slow(data)
        if len(sent) == 2:
            waiter.now += 25 * MS  # publishing message 2 took 25 ms

    player._publishers = {"/a": slow_second_publish}
    player.run()
    times = [(t - start) // MS for _, t, _ in sent]
    assert times == [0, 10, 35, 35, 40]  # 3 and 4 are sent at once, 5 on time


def test_start_offset_moves_the_origin_and_skips_earlier_messages():
    msgs = _messages([("/a", 0), ("/a", 100), ("/b", 150), ("/a", 300)])
    waiter = FakeWaiter()
    start = waiter.now
    player, sent = _player(msgs, waiter, origin=T0 + 100 * MS)
    report = player.run()
    assert [(topic, (t - start) // MS) for topic, t, _ in sent] == [
        ("/a", 0),
        ("/b", 50),
        ("/a", 200),
    ]
    assert report.bag_span_ns == 200 * MS


def test_loop_anchors_each_pass_where_the_previous_last_message_was_due():
    msgs = _messages([("/a", 0), ("/b", 40), ("/a", 100)])
    waiter = FakeWaiter()
    start = waiter.now
    sent: list = []
    player, sent = _player(msgs, waiter, loop=True, sent=sent)
    publish_a = player._publishers["/a"]

    def stop_after_seven(data: bytes) -> None:
        publish_a(data)
        if len(sent) >= 7:
            waiter.stop = True

    player._publishers = {"/a": stop_after_seven, "/b": player._publishers["/b"]}
    report = player.run()
    assert [(t - start) // MS for _, t, _ in sent] == [0, 40, 100, 100, 140, 200, 200]
    assert report.interrupted
    assert report.passes == 3
    assert report.topics["/a"].published == 5


def test_infinite_rate_sends_everything_without_sleeping():
    msgs = _messages([("/a", 0), ("/b", 500), ("/a", 1000)])
    waiter = FakeWaiter()
    player, sent = _player(msgs, waiter, rate=math.inf)
    player.run()
    assert len(sent) == 3
    assert waiter.sleeps == []


def test_topics_without_publisher_are_counted_not_sent_and_not_waited_for():
    msgs = _messages([("/a", 0), ("/unknown", 500), ("/unknown", 900), ("/a", 20)])
    msgs = sorted(msgs, key=lambda m: m.log_time_ns)
    waiter = FakeWaiter()
    start = waiter.now
    player, sent = _player(msgs, waiter)
    report = player.run()
    assert [(topic, (t - start) // MS) for topic, t, _ in sent] == [("/a", 0), ("/a", 20)]
    assert report.topics["/unknown"].skipped == 2
    assert report.skipped == 2
    assert report.bag_span_ns == 20 * MS


def test_undecodable_messages_are_counted_not_published_and_playback_goes_on():
    from endo_io.bag import MessageDeserializationError

    msgs = _messages([("/a", 0), ("/a", 10), ("/b", 15), ("/a", 20), ("/a", 30)])
    waiter = FakeWaiter()
    sent: list = []

    def publish_a(data: bytes) -> None:
        if data[0] in (1, 3):  # the 2nd and 4th message do not decode
            raise MessageDeserializationError(f"/a: {len(data)} bytes are not a valid Float32")
        sent.append(("/a", data))

    tallies = {t: TopicTally(t, "std_msgs/msg/Float32") for t in ("/a", "/b")}
    publishers = {"/a": publish_a, "/b": lambda data: sent.append(("/b", data))}
    player = Player(lambda: iter(msgs), publishers, tallies, PlaybackSchedule(T0), waiter=waiter)
    report = player.run()
    assert [m for _, m in sent] == [msgs[0].data, msgs[2].data, msgs[4].data]
    assert (report.topics["/a"].published, report.topics["/a"].undecodable) == (2, 2)
    assert report.undecodable == 2 and report.error == ""
    lines = report.summary_lines()
    assert "/a [std_msgs/msg/Float32]: 2 messages, 16 bytes, 2 not published (undecodable; " in (
        lines[0]
    )
    assert "  not published: 2 messages whose bytes do not decode as their type" in lines


def test_damaged_bag_plays_up_to_the_damage_and_reports_it():
    msgs = _messages([("/a", 0), ("/b", 10), ("/a", 20)])

    def damaged() -> Iterator[BagMessage]:
        yield msgs[0]
        yield msgs[1]
        raise BagCorruptError("chunk at byte 4242 is truncated")

    waiter = FakeWaiter()
    sent: list = []
    tallies = {t: TopicTally(t, "std_msgs/msg/Float32") for t in ("/a", "/b")}
    publishers = {t: (lambda data, t=t: sent.append((t, data))) for t in ("/a", "/b")}
    player = Player(damaged, publishers, tallies, PlaybackSchedule(T0), loop=True, waiter=waiter)
    report = player.run()
    assert sent == [("/a", msgs[0].data), ("/b", msgs[1].data)]
    assert report.error == "chunk at byte 4242 is truncated"
    assert report.passes == 1
    assert any("damaged" in line for line in report.summary_lines())


def test_stop_interrupts_a_long_wait():
    msgs = _messages([("/a", 0), ("/a", 60_000)])
    waiter = FakeWaiter()
    sent: list = []
    player, sent = _player(msgs, waiter, sent=sent)
    publish = player._publishers["/a"]

    def stop_after_first(data: bytes) -> None:
        publish(data)
        waiter.stop = True

    player._publishers = {"/a": stop_after_first}
    report = player.run()
    assert len(sent) == 1
    assert report.interrupted


def test_clock_follows_playback_and_never_passes_the_next_unsent_message():
    msgs = _messages([("/a", 0), ("/a", 100), ("/a", 200)])
    waiter = FakeWaiter()
    player, _ = _player(msgs, waiter)
    assert player.bag_time_ns() == T0
    seen: list[tuple[int, int]] = []
    real_wait = waiter.wait

    def wait_and_look(seconds: float) -> bool:
        if seconds > 0:  # look half way through every sleep
            half = round(seconds * 1e9) // 2
            waiter.now += half
            seen.append((waiter.now, player.bag_time_ns()))
            return real_wait(seconds - half / 1e9)
        waiter.now += 30 * MS  # due, but the message goes out 30 ms late
        seen.append((waiter.now, player.bag_time_ns()))
        return real_wait(0)

    waiter.wait = wait_and_look
    start = waiter.now
    player.run()
    assert [(now - start) // MS for now, _ in seen] == [30, 65, 130, 165, 230]
    # The clock runs with the wall clock but waits at each unsent message.
    assert [(bag - T0) // MS for _, bag in seen] == [0, 65, 100, 165, 200]
    assert player.bag_time_ns() == T0 + 200 * MS  # stays at the last message after the end


# ---------------------------------------------------------------- the CLI on real bags


@pytest.fixture
def fresh_default_context():
    """main() runs a node in this process; leave rclpy's default context reusable."""
    import rclpy

    yield
    # The node ends spin() by shutting its context down, which (unlike
    # rclpy.try_shutdown()) does not replace the global default context.
    rclpy.try_shutdown()


def _write_bag_with_unknown_type(path: Path) -> None:
    from std_msgs.msg import Float32

    from endo_io.bag import BagWriter

    with BagWriter(path, chunk_size=512) as writer:
        writer.add_topic("/gadget", "acme_msgs/msg/Gadget")  # not installed here
        for i in range(40):
            writer.write_message("/scalar", Float32(data=0.25 * i), T0 + i * MS)
            if i % 8 == 0:
                writer.write("/gadget", b"\x00\x01\x00\x00\x07\x00\x00\x00", T0 + i * MS + 1)


@pytest.mark.ros
def test_cli_skips_uninstalled_types_and_reports_counts(
    tmp_path: Path, capsys, fresh_default_context
):
    from endo_io.replay_node import main

    bag = tmp_path / "mixed.mcap"
    _write_bag_with_unknown_type(bag)
    assert main(["endo-replay", str(bag), "--rate", "inf"]) == 0
    out = capsys.readouterr()
    assert "/scalar [std_msgs/msg/Float32]: 40 messages, 320 bytes" in out.out
    assert "/gadget [acme_msgs/msg/Gadget]: 0 messages, 0 bytes, 5 not published" in out.out
    assert "total: 40 messages" in out.out


@pytest.mark.ros
def test_cli_plays_a_truncated_bag_up_to_the_damage_and_fails(
    tmp_path: Path, capsys, fresh_default_context
):
    from endo_io.bag import BagReader
    from endo_io.replay_node import main

    whole = tmp_path / "whole.mcap"
    _write_bag_with_unknown_type(whole)
    cut = tmp_path / "cut.mcap"
    data = whole.read_bytes()
    with whole.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    chunks = sorted(c.chunk_start_offset for c in summary.chunk_indexes)
    cut.write_bytes(data[: chunks[len(chunks) // 2] + 10])  # inside the middle chunk
    intact = 0
    with BagReader(cut) as reader, pytest.raises(BagCorruptError):
        for message in reader.messages():
            intact += message.topic == "/scalar"
    assert 0 < intact < 40
    assert main(["endo-replay", str(cut), "--rate", "inf", "--topics", "/scalar"]) == 1
    out = capsys.readouterr()
    assert f"/scalar [std_msgs/msg/Float32]: {intact} messages" in out.out
    assert "damaged bag, every message it could read was played: " in out.out
    assert out.err.startswith("endo-replay: error: ")
    assert len(out.err.strip().splitlines()) == 1


def test_cli_rejects_bad_options_before_starting_ros(tmp_path: Path, capsys):
    from endo_io.replay_node import main

    assert main(["endo-replay", str(tmp_path / "missing.mcap")]) == 2
    assert "no such bag" in capsys.readouterr().err
    bag = tmp_path / "ok.mcap"
    _write_bag_with_unknown_type(bag)
    assert main(["endo-replay", str(bag), "--rate", "0"]) == 2
    assert "--rate" in capsys.readouterr().err
    assert main(["endo-replay", str(bag), "--remap", "/scalar=/x"]) == 2
    assert "remap rule" in capsys.readouterr().err
    assert main(["endo-replay", str(bag), "--topics", "/nope"]) == 2
    assert "none of the topics /nope is in the bag" in capsys.readouterr().err


def _write_three_second_bag(path: Path) -> None:
    from std_msgs.msg import Float32

    from endo_io.bag import BagWriter

    with BagWriter(path) as writer:
        for i in range(31):
            writer.write_message("/a", Float32(data=0.1 * i), T0 + i * 100 * MS)
        writer.write_message("/b", Float32(data=1.0), T0 + 500 * MS)


def test_cli_refuses_a_start_offset_with_nothing_after_it(tmp_path: Path, capsys):
    # Issue 16: --start-offset 999 on a 3 s bag exited 0 having sent nothing.
    from endo_io.bag import BagWriter
    from endo_io.replay_node import main

    bag = tmp_path / "three_seconds.mcap"
    _write_three_second_bag(bag)
    assert main(["endo-replay", str(bag), "--start-offset", "999"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "endo-replay: error: --start-offset 999 s is past the end of the bag, whose messages "
        "span 3.000 s\n"
    )
    assert main(["endo-replay", str(bag), "--start-offset", "1", "--topics", "/b"]) == 2
    err = capsys.readouterr().err
    assert "the selected topics have no message at or after --start-offset 1 s" in err
    assert len(err.splitlines()) == 1
    empty = tmp_path / "empty.mcap"
    with BagWriter(empty) as writer:
        writer.add_topic("/a", "std_msgs/msg/Float32")
    assert main(["endo-replay", str(empty)]) == 2
    err = capsys.readouterr().err
    assert f"{empty} holds no messages, nothing to play" in err and len(err.splitlines()) == 1


@pytest.mark.ros
def test_cli_drops_undecodable_messages_with_one_line_and_a_count(
    tmp_path: Path, capfd, fresh_default_context
):
    from sensor_msgs.msg import Image

    from endo_io.bag import BagWriter, serialize
    from endo_io.replay_node import main

    bag = tmp_path / "garbled.mcap"
    good = Image(height=2, width=2, encoding="mono8", step=2, data=bytes(4))
    with BagWriter(bag) as writer:
        writer.add_topic("/image", "sensor_msgs/msg/Image")
        for i in range(10):
            # the frame_id length (after the stamp) says 2 GiB: that cannot decode
            garbled = b"\x00\x01\x00\x00" + bytes(8) + b"\xff\xff\xff\x7f" + bytes(36)
            data = serialize(good) if i % 3 else garbled
            writer.write("/image", data, T0 + i * MS)
    assert main(["endo-replay", str(bag), "--rate", "inf"]) == 1
    out = capfd.readouterr()
    assert "/image [sensor_msgs/msg/Image]: 6 messages" in out.out
    assert "4 not published (undecodable; first: /image: 52 bytes are not a valid " in out.out
    logged = [line for line in out.err.splitlines() if "not publishing undecodable" in line]
    assert len(logged) == 1 and "/image" in logged[0]


def test_ros_arguments_are_split_from_ours_and_remap_values_stay_ours():
    from endo_io.replay_node import build_parser, split_ros_args

    argv = [
        "endo-replay", "run.mcap", "--remap", "/a:=/b", "--ros-args", "-r", "__node:=left",
        "-p", "use_sim_time:=true", "--", "--rate", "2",
    ]  # fmt: skip
    ours, ros = split_ros_args(argv)
    assert ours == ["run.mcap", "--remap", "/a:=/b", "--rate", "2"]
    assert ros == [
        "endo-replay", "--ros-args", "-r", "__node:=left", "-p", "use_sim_time:=true", "--",
    ]  # fmt: skip
    options = build_parser().parse_args(ours)
    assert (options.remap, options.rate, options.bag) == (["/a:=/b"], 2.0, Path("run.mcap"))
    assert split_ros_args(["endo-replay", "b.mcap"]) == (["b.mcap"], ["endo-replay"])
