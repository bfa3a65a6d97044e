"""``endo-replay``: play a rosbag2 MCAP bag onto live topics with its recorded timing.

The node is a thin adapter around :mod:`endo_io.replay`: it opens the bag,
creates one publisher per played topic with the recorded (or overridden) QoS,
optionally waits until subscribers have matched, and hands raw CDR bytes to
the publishers on the player's schedule. Nothing is deserialised. See
``docs/replay_record.md`` for the options and their behaviour.

Each message is checked to decode as its type before it is published
(rclpy's own deserialisation, about 0.06 ms for a 640x480 rgb8 image): one that
does not is not published, is logged once per topic and counted in the
summary, and the exit status is then 1.

Exit status: 0 when the bag played to its end (or was interrupted by SIGINT
or SIGTERM), 1 when the bag is damaged (everything before the damage was
played, undecodable messages excepted) or publishing failed, 2 when the
options or the bag cannot be used, including a bag with nothing to play
(empty, or ``--start-offset`` at or past its end).
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from endo_io.bag import BagMessage, BagReader, MessageDeserializationError, message_class
from endo_io.bag.serde import cdr_check
from endo_io.cli import exit_on_error
from endo_io.errors import Endo3dError
from endo_io.process import run_node, split_ros_args
from endo_io.qos import create_reliable_publisher
from endo_io.replay import (
    EventWaiter,
    PlaybackSchedule,
    Player,
    ReplayOptionError,
    ReplayReport,
    TopicTally,
    build_remaps,
    load_qos_overrides,
    output_topics,
    publisher_qos_for_topic,
    select_topics,
)
from endo_io.stamp import ns_to_stamp

#: /clock publishing frequency when ``--clock`` is given without a value.
DEFAULT_CLOCK_HZ = 100.0
#: Extra time after every publisher has matched its subscribers, so that the
#: subscriber side has also matched the publisher before the first message.
SUBSCRIBER_SETTLE_S = 0.25
CLOCK_TOPIC = "/clock"


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-replay`` command line (ROS arguments after ``--ros-args`` are separate)."""
    parser = argparse.ArgumentParser(
        prog="endo-replay",
        description="Play a rosbag2 MCAP bag onto live ROS 2 topics with its recorded timing.",
    )
    parser.add_argument("bag", type=Path, help=".mcap file or rosbag2 directory with metadata.yaml")
    parser.add_argument(
        "-r",
        "--rate",
        type=float,
        default=1.0,
        help="playback speed factor (default 1; > 0; 2 = twice as fast; 'inf' = as fast as "
        "possible)",
    )
    parser.add_argument(
        "-l", "--loop", action="store_true", help="play again from the start at the end"
    )
    parser.add_argument(
        "--start-offset",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="skip this many seconds from the bag's first message (default 0)",
    )
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these bag topics")
    parser.add_argument(
        "--remap",
        action="append",
        default=[],
        metavar="FROM:=TO",
        help="publish bag topic FROM on TO (repeatable)",
    )
    parser.add_argument(
        "--clock",
        nargs="?",
        type=float,
        const=DEFAULT_CLOCK_HZ,
        default=None,
        metavar="HZ",
        help=f"publish /clock from the bag time at HZ (default {DEFAULT_CLOCK_HZ:g} Hz)",
    )
    parser.add_argument(
        "--qos-profile-overrides-path",
        type=Path,
        default=None,
        metavar="FILE",
        help="YAML of per-topic QoS overrides, as for 'ros2 bag play'",
    )
    parser.add_argument(
        "--wait-for-subscribers",
        type=int,
        default=0,
        metavar="N",
        help="before playing, wait until every publisher has matched N subscriptions, at most "
        "--wait-timeout (default 0: no wait)",
    )
    parser.add_argument(
        "--wait-topics",
        nargs="+",
        default=None,
        metavar="TOPIC",
        help="wait only for these bag topics' subscribers (default: every played topic "
        "and /clock); TOPIC=N waits for N subscribers of that topic instead",
    )
    parser.add_argument(
        "--wait-timeout",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="give up waiting for subscribers after this long and play anyway (default 10)",
    )
    parser.add_argument(
        "--delay",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="sleep this long before playing (default 0)",
    )
    parser.add_argument(
        "--ack-timeout",
        type=float,
        default=5.0,
        metavar="SECONDS",
        help="at the end, wait up to this long for reliable subscribers to acknowledge "
        "everything (default 5)",
    )
    return parser


@dataclass(frozen=True)
class PlayedTopic:
    """One bag topic to play: where, as what, with which QoS, or why not."""

    bag_topic: str
    output_topic: str
    msgtype: str
    qos: QoSProfile
    msg_class: type | None
    skip_reason: str = ""


@dataclass(frozen=True)
class ReplayPlan:
    """Everything decided before the node starts."""

    topics: list[PlayedTopic]
    schedule: PlaybackSchedule
    warnings: list[str]


def make_plan(reader: BagReader, options: argparse.Namespace) -> ReplayPlan:
    """Decide topics, names, QoS and the schedule from the bag and the options.

    Raises :class:`~endo_io.replay.ReplayOptionError` (or another
    :class:`~endo_io.errors.Endo3dError`) on unusable options.
    """
    warnings: list[str] = []
    selected, missing = select_topics(reader.topics, options.topics)
    if options.topics and not selected:
        raise ReplayOptionError(f"none of the topics {', '.join(missing)} is in the bag")
    warnings += [f"topic {t} is not in the bag" for t in missing]
    names = output_topics(selected, build_remaps(options.remap))
    overrides = (
        load_qos_overrides(options.qos_profile_overrides_path)
        if options.qos_profile_overrides_path is not None
        else {}
    )
    topics = []
    for topic in selected:
        info = reader.topics[topic]
        qos, warning = publisher_qos_for_topic(
            topic, info.offered_qos_profiles, overrides, names[topic]
        )
        if warning:
            warnings.append(warning)
        try:
            msg_class: type | None = message_class(info.msgtype)
            reason = ""
        except Endo3dError as error:
            msg_class, reason = None, f"type {info.msgtype} not installed"
            warnings.append(f"not publishing {topic}: {error}")
        topics.append(PlayedTopic(topic, names[topic], info.msgtype, qos, msg_class, reason))
    time_range = reader.time_range_ns
    if time_range is None:
        damage = f" ({reader.damage})" if reader.damage else ""
        raise ReplayOptionError(f"{reader.path} holds no messages, nothing to play{damage}")
    start_ns, end_ns = time_range
    origin = start_ns + round(options.start_offset * 1e9)
    if origin > end_ns:
        raise ReplayOptionError(
            f"--start-offset {options.start_offset:g} s is past the end of the bag, whose "
            f"messages span {(end_ns - start_ns) / 1e9:.3f} s"
        )
    if not _any_message(reader, selected, origin):
        which = "the selected topics" if options.topics else "the bag"
        raise ReplayOptionError(
            f"{which} have no message at or after --start-offset {options.start_offset:g} s"
            + (f" ({reader.damage})" if reader.damage else "")
        )
    warnings += reader.warnings
    return ReplayPlan(topics, PlaybackSchedule(origin, options.rate), warnings)


def _any_message(reader: BagReader, topics: list[str], start_ns: int) -> bool:
    """Whether an intact message of ``topics`` has a log time >= ``start_ns``."""
    try:
        next(reader.messages(topics=topics, start_ns=start_ns))
    except StopIteration:
        return False
    except Endo3dError:  # damaged: nothing intact there
        return False
    return True


class ReplayNode(Node):
    """Publishes a bag's messages on a playback thread; shuts the context down when done."""

    def __init__(self, reader: BagReader, plan: ReplayPlan, options: argparse.Namespace) -> None:
        super().__init__("endo_replay")
        self._reader = reader
        self._plan = plan
        self._options = options
        self.exit_code = 0
        self._bag_publishers: dict[str, Publisher] = {}
        publish_checked: dict[str, Callable[[bytes], None]] = {}
        tallies: dict[str, TopicTally] = {}
        for topic in plan.topics:
            tallies[topic.bag_topic] = TopicTally(
                topic.output_topic, topic.msgtype, skip_reason=topic.skip_reason
            )
            if topic.msg_class is not None:
                publisher = self.create_publisher(topic.msg_class, topic.output_topic, topic.qos)
                self._bag_publishers[topic.bag_topic] = publisher
                publish_checked[topic.bag_topic] = self._checked(topic, publisher)
        for text in plan.warnings:
            self.get_logger().warning(text)
        selected = [t.bag_topic for t in plan.topics]
        origin = plan.schedule.origin_ns

        def open_messages() -> Iterator[BagMessage]:
            return reader.messages(topics=selected, start_ns=origin)

        self._stop = threading.Event()
        self._player = Player(
            open_messages,
            publish_checked,
            tallies,
            plan.schedule,
            loop=options.loop,
            waiter=EventWaiter(self._stop),
        )
        self._clock_publisher: Publisher | None = None
        self._clock_lock = threading.Lock()
        self._player_done = False  # set once the player has returned
        self._clock_final = False  # set once the final bag time has been published
        if options.clock is not None:
            self._clock_publisher = create_reliable_publisher(self, Clock, CLOCK_TOPIC)
            self.create_timer(1.0 / options.clock, self._publish_clock)
        self.context.on_shutdown(self._stop.set)
        self._thread = threading.Thread(target=self._play, name="endo_replay_player", daemon=True)
        # Start playing from inside spin(): a short bag must not end (and shut
        # the context down) before the node is up and spinning.
        self._start_timer = self.create_timer(0.0, self._start_playback)

    def _checked(self, topic: PlayedTopic, publisher: Publisher) -> Callable[[bytes], None]:
        """Publish bytes that decode as the topic's type; raise (and log once) for others."""
        check = cdr_check(topic.msgtype, topic.bag_topic)
        logged = False

        def publish(data: bytes) -> None:
            nonlocal logged
            try:
                check(data)
            except MessageDeserializationError as error:
                if not logged:
                    logged = True
                    self.get_logger().error(
                        f"not publishing undecodable messages of {topic.bag_topic}, counting "
                        f"them: {error}"
                    )
                raise
            publisher.publish(data)

        return publish

    def _start_playback(self) -> None:
        self._start_timer.cancel()
        if self._thread.ident is None:  # not started yet
            self._thread.start()

    def _publish_clock(self) -> None:
        # One lock: the timer and the final publish after playback never
        # interleave, so /clock is published in non-decreasing order.
        with self._clock_lock:
            if self._clock_publisher is None or self._clock_final:
                return
            self._clock_final = self._player_done
            self._clock_publisher.publish(Clock(clock=ns_to_stamp(self._player.bag_time_ns())))

    def _wait_for_subscribers(self) -> None:
        default = self._options.wait_for_subscribers
        counts = wait_counts(self._options.wait_topics, default)
        chosen = None if self._options.wait_topics is None else counts
        wanted = {p: default if chosen is None else chosen[t]
                  for t, p in self._bag_publishers.items() if chosen is None or t in chosen}
        if self._clock_publisher is not None and chosen is None:
            wanted[self._clock_publisher] = default
        if max(wanted.values(), default=0) <= 0:
            return
        deadline = time.monotonic() + self._options.wait_timeout
        while not all(p.get_subscription_count() >= n for p, n in wanted.items()):
            if time.monotonic() >= deadline:
                lacking = [f"{p.topic_name} ({p.get_subscription_count()} of {n})"
                           for p, n in wanted.items() if p.get_subscription_count() < n]
                self.get_logger().warning(
                    f"playing although {', '.join(lacking)} did not reach their subscriber "
                    f"count within {self._options.wait_timeout:g} s"
                )
                return
            if self._stop.wait(0.01):
                return
        self._stop.wait(SUBSCRIBER_SETTLE_S)

    def _wait_for_acks(self) -> None:
        # Fast DDS acknowledges in reply to heartbeats, which a writer sends
        # every few seconds when idle: wait on all publishers at once, so the
        # total wait is one heartbeat period rather than one per topic.
        timeout = Duration(nanoseconds=round(self._options.ack_timeout * 1e9))
        publishers = [
            p
            for p in self._bag_publishers.values()
            if p.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        ]
        if self._clock_publisher is not None:
            self._publish_clock()  # the final bag time; the timer publishes no more
            publishers.append(self._clock_publisher)
        late: list[str] = []

        def wait(publisher: Publisher) -> None:
            if not publisher.wait_for_all_acked(timeout):
                late.append(publisher.topic_name)

        waiters = [threading.Thread(target=wait, args=(p,), daemon=True) for p in publishers]
        for waiter in waiters:
            waiter.start()
        for waiter in waiters:
            waiter.join()
        if late:
            self.get_logger().warning(
                f"not every subscriber acknowledged {', '.join(sorted(late))} within "
                f"{self._options.ack_timeout:g} s"
            )

    def _play(self) -> None:
        try:
            self._wait_for_subscribers()
            if self._options.delay > 0:
                self._stop.wait(self._options.delay)
            if not self._stop.is_set():
                report = self._player.run()
                self._player_done = True
                if not report.interrupted:
                    self._wait_for_acks()
                if report.error or report.undecodable:
                    self.exit_code = 1
            else:
                self._player.report.interrupted = True
        except Exception as error:
            # A publisher used while SIGINT shuts the context down raises; that
            # is an interruption, not a failure.
            if not self._stop.is_set() and self.context.ok():
                self._player.report.error = f"{type(error).__name__}: {error}"
                self.exit_code = 1
            else:
                self._player.report.interrupted = True
        finally:
            # Ends spin() in run_node; SIGINT/SIGTERM have done this already.
            self.context.try_shutdown()

    @property
    def report(self) -> ReplayReport:
        """The player's counts so far (final after :meth:`close`)."""
        return self._player.report

    def close(self) -> None:
        """Stop playback (if still running) and print what was done."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join()
        report = self._player.report
        print(f"endo-replay: {self._options.bag}", flush=True)
        for line in report.summary_lines():
            print(line, flush=True)
        if report.error:
            print(f"endo-replay: error: {report.error}", file=sys.stderr, flush=True)


def wait_counts(wait_topics: Sequence[str] | None, default: int) -> dict[str, int]:
    """Bag topic -> subscribers to wait for, from ``--wait-topics`` (``TOPIC`` or ``TOPIC=N``).

    Raises:
        ValueError: an N that is not a whole number >= 0.
    """
    counts = {}
    for item in wait_topics or ():
        topic, _, number = item.partition("=")
        if number and not number.isdigit():
            raise ValueError(f"--wait-topics {item}: expected TOPIC or TOPIC=N with N >= 0")
        counts[topic] = int(number) if number else default
    return counts


def check_options(options: argparse.Namespace) -> None:
    """Refuse options ``endo-replay`` cannot play with (``endo-launch`` checks them first).

    Raises:
        ValueError: one line naming the option and its value.
    """
    if not options.rate > 0:
        raise ValueError(f"--rate must be > 0, got {options.rate}")
    if options.clock is not None and not (0 < options.clock < math.inf):
        raise ValueError(f"--clock must be a positive frequency in Hz, got {options.clock}")
    if options.start_offset < 0:
        raise ValueError(f"--start-offset must be >= 0, got {options.start_offset}")
    if options.wait_timeout < 0 or options.delay < 0 or options.ack_timeout < 0:
        raise ValueError("--wait-timeout, --delay and --ack-timeout must be >= 0")
    waited = wait_counts(options.wait_topics, options.wait_for_subscribers)
    unknown = set(waited) - set(options.topics or waited)
    if unknown:
        raise ValueError(f"--wait-topics {' '.join(sorted(unknown))} not among --topics")


@exit_on_error("endo-replay", errors=(Endo3dError, ValueError, OSError), label="error")
def main(argv: Sequence[str] | None = None) -> int:
    """Run ``endo-replay``; returns the process exit status (2: bad options or bag)."""
    ours, ros_args = split_ros_args(list(sys.argv if argv is None else argv))
    options = build_parser().parse_args(ours)
    check_options(options)
    with BagReader(options.bag) as reader:
        plan = make_plan(reader, options)
        nodes: list[ReplayNode] = []

        def factory() -> ReplayNode:
            nodes.append(ReplayNode(reader, plan, options))
            return nodes[0]

        code = run_node(factory, ros_args)
        return code if nodes else 1


if __name__ == "__main__":
    sys.exit(main())
