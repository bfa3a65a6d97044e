"""Replaying a bag onto live topics: topic selection, remapping, QoS and timing.

This module holds everything ``endo-replay`` decides without a ROS graph, so
that it can be tested with a fake clock: which topics play and under which
names, which QoS each publisher offers, and when each message goes out.

Timing. Every message gets a target on a monotonic clock computed from its
log time, never from the previous message's sleep:

    target_wall_ns = anchor_wall_ns + (log_time_ns - origin_ns) / rate

``origin_ns`` is the bag's first log time plus ``--start-offset``;
``anchor_wall_ns`` is the monotonic time playback started. A message that
goes out late (a slow disk, a busy core) does not delay the ones after it,
so playback never drifts from the recorded timeline. ``rate = inf`` plays as
fast as possible. With ``--loop`` each pass is anchored where the previous
pass's last message was due, so loops do not drift either.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import yaml
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from endo_io.bag.errors import MessageDeserializationError
from endo_io.bag.qos_yaml import (
    QosYamlError,
    qos_profile_from_dict,
    qos_profile_to_dict,
    qos_profiles_from_yaml,
)
from endo_io.errors import BagCorruptError, Endo3dError

#: Depth of the publisher history when the recorded offer is used. History is
#: local to the writer and not part of the offer, so rosbag2 substitutes the
#: ROS default depth; so do we.
DEFAULT_PUBLISHER_DEPTH = 10


class ReplayOptionError(Endo3dError, ValueError):
    """A replay option (remap rule, rate, topic list, QoS override) is malformed."""


class PlayedMessage(Protocol):
    """What the player needs of a bag message (``endo_io.bag.BagMessage`` fits)."""

    @property
    def topic(self) -> str: ...

    @property
    def log_time_ns(self) -> int: ...

    @property
    def data(self) -> bytes: ...


# --------------------------------------------------------------------------
# Topic selection and remapping


def parse_remap(rule: str) -> tuple[str, str]:
    """Split one ``FROM:=TO`` remap rule into its two absolute topic names.

    Raises :class:`ReplayOptionError` when the rule has no ``:=`` or either side
    is not an absolute topic name (``/name``).
    """
    source, sep, target = rule.partition(":=")
    source, target = source.strip(), target.strip()
    if not sep or not source or not target:
        raise ReplayOptionError(f"remap rule {rule!r} is not of the form /from:=/to")
    for name in (source, target):
        if not name.startswith("/"):
            raise ReplayOptionError(f"remap rule {rule!r}: {name!r} is not an absolute topic name")
    return source, target


def build_remaps(rules: Sequence[str]) -> dict[str, str]:
    """Parse ``FROM:=TO`` rules into a mapping; a source given twice is an error."""
    remaps: dict[str, str] = {}
    for rule in rules:
        source, target = parse_remap(rule)
        if source in remaps and remaps[source] != target:
            raise ReplayOptionError(
                f"topic {source} is remapped twice ({remaps[source]}, {target})"
            )
        remaps[source] = target
    return remaps


def select_topics(
    bag_topics: Iterable[str], requested: Sequence[str] | None
) -> tuple[list[str], list[str]]:
    """Choose the bag topics to play.

    Returns ``(selected, missing)``: ``selected`` are the bag topics to play in
    sorted order (all of them when ``requested`` is None or empty); ``missing``
    are requested topics the bag does not have, in request order. A requested
    name without the leading ``/`` means the absolute name (bag topics are
    absolute).
    """
    available = sorted(set(bag_topics))
    if not requested:
        return available, []
    absolute = ["/" + t.lstrip("/") for t in requested]
    wanted = set(absolute)
    missing = [t for t in dict.fromkeys(absolute) if t not in available]
    return [t for t in available if t in wanted], missing


def output_topics(selected: Sequence[str], remaps: Mapping[str, str]) -> dict[str, str]:
    """Map each selected bag topic to the topic it is published on.

    Raises :class:`ReplayOptionError` when two bag topics would be published on
    one output topic (their streams would interleave).
    """
    out = {topic: remaps.get(topic, topic) for topic in selected}
    seen: dict[str, str] = {}
    for source, target in out.items():
        if target in seen:
            raise ReplayOptionError(
                f"{seen[target]} and {source} would both be published on {target}"
            )
        seen[target] = source
    return out


# --------------------------------------------------------------------------
# QoS


def default_publisher_qos() -> QoSProfile:
    """The offer used when a bag records no QoS for a topic: rosbag2's default.

    Reliable, volatile, keep last ``DEFAULT_PUBLISHER_DEPTH``.
    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=DEFAULT_PUBLISHER_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def _same_compatibility(a: QoSProfile, b: QoSProfile) -> bool:
    # History and lifespan are local to a writer and do not take part in
    # matching; everything else that a reader checks must agree.
    return (
        a.reliability == b.reliability
        and a.durability == b.durability
        and a.deadline == b.deadline
        and a.liveliness == b.liveliness
        and a.liveliness_lease_duration == b.liveliness_lease_duration
    )


def adapt_offer_to_recorded_offers(offers: Sequence[QoSProfile]) -> tuple[QoSProfile, bool]:
    """The QoS to publish a topic with, given the offers recorded for it.

    Follows ``ros2 bag play``: when every recorded publisher offered the same
    compatibility-relevant policies (reliability, durability, deadline,
    liveliness), publish with that offer and a keep-last
    ``DEFAULT_PUBLISHER_DEPTH`` history; when there are none, or they differ,
    fall back to :func:`default_publisher_qos`.

    Returns ``(profile, mixed)``; ``mixed`` is True when differing offers forced
    the fallback (the caller logs it).
    """
    if not offers:
        return default_publisher_qos(), False
    first = offers[0]
    if not all(_same_compatibility(first, other) for other in offers[1:]):
        return default_publisher_qos(), True
    profile = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=DEFAULT_PUBLISHER_DEPTH,
        reliability=first.reliability,
        durability=first.durability,
        deadline=first.deadline,
        lifespan=first.lifespan,
        liveliness=first.liveliness,
        liveliness_lease_duration=first.liveliness_lease_duration,
        avoid_ros_namespace_conventions=first.avoid_ros_namespace_conventions,
    )
    return profile, False


def publisher_qos_for_topic(
    bag_topic: str,
    offered_qos_profiles: str,
    overrides: Mapping[str, QoSProfile],
    output_topic: str | None = None,
) -> tuple[QoSProfile, str]:
    """The QoS to publish one bag topic with, and a warning ("" if none).

    An override for the bag topic (or, failing that, for its output topic)
    wins; otherwise the recorded ``offered_qos_profiles`` text (rosbag2 YAML)
    is adapted with :func:`adapt_offer_to_recorded_offers`. Unreadable
    recorded offers fall back to :func:`default_publisher_qos` with a warning.
    """
    override = overrides.get(bag_topic)
    if override is None and output_topic is not None:
        override = overrides.get(output_topic)
    if override is not None:
        return override, ""
    try:
        offers = qos_profiles_from_yaml(offered_qos_profiles)
    except QosYamlError as error:
        return default_publisher_qos(), f"{bag_topic}: {error}; publishing with the default QoS"
    profile, mixed = adapt_offer_to_recorded_offers(offers)
    if mixed:
        return profile, (
            f"{bag_topic}: the recorded publishers offered different QoS; publishing with "
            "the default (reliable, volatile)"
        )
    return profile, ""


_OVERRIDE_POLICIES: dict[str, Any] = {
    "history": HistoryPolicy,
    "reliability": ReliabilityPolicy,
    "durability": DurabilityPolicy,
    "liveliness": LivelinessPolicy,
}
_OVERRIDE_DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")


def qos_override_from_dict(topic: str, policies: Mapping[str, Any]) -> QoSProfile:
    """One topic's entry of a ``--qos-profile-overrides-path`` file as a ``QoSProfile``.

    Keys and values are those of ``ros2 bag play``'s override files: policy
    short names (``reliability: best_effort``, ``durability: transient_local``,
    ``history: keep_all``...), ``depth``, durations as ``{sec, nsec}``, and
    ``avoid_ros_namespace_conventions``. Policies not given keep the values of
    :func:`default_publisher_qos` (not the recorded offer), as in rosbag2.

    Raises :class:`ReplayOptionError` naming the topic and the bad key or value.
    """
    if not isinstance(policies, Mapping):
        raise ReplayOptionError(f"QoS override of {topic} is not a mapping of policies")
    merged = qos_profile_to_dict(default_publisher_qos())
    for key, value in policies.items():
        if key in _OVERRIDE_POLICIES:
            names = _OVERRIDE_POLICIES[key].short_keys()
            if not isinstance(value, str) or value.lower() not in names:
                raise ReplayOptionError(
                    f"QoS override of {topic}: {key} {value!r} is not one of {', '.join(names)}"
                )
            merged[key] = value.lower()
        elif key == "depth":
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ReplayOptionError(f"QoS override of {topic}: depth {value!r} is not >= 0")
            merged[key] = value
        elif key in _OVERRIDE_DURATIONS:
            if not isinstance(value, Mapping) or set(value) != {"sec", "nsec"}:
                raise ReplayOptionError(
                    f"QoS override of {topic}: {key} needs both sec and nsec, got {value!r}"
                )
            merged[key] = dict(value)
        elif key == "avoid_ros_namespace_conventions":
            if not isinstance(value, bool):
                raise ReplayOptionError(f"QoS override of {topic}: {key} must be true or false")
            merged[key] = value
        else:
            raise ReplayOptionError(f"QoS override of {topic}: unknown policy {key!r}")
    try:
        return qos_profile_from_dict(merged)
    except QosYamlError as error:
        raise ReplayOptionError(f"QoS override of {topic}: {error}") from error


def load_qos_overrides(path: Path) -> dict[str, QoSProfile]:
    """Read a ``ros2 bag play`` QoS override file: ``{topic: {policy: value}}``.

    Raises :class:`ReplayOptionError` when the file is not such a mapping or a
    policy is unknown or malformed; ``OSError`` when it cannot be read.
    """
    try:
        loaded = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as error:
        raise ReplayOptionError(f"{path} is not YAML: {str(error).splitlines()[0]}") from error
    if loaded is None:
        return {}
    if not isinstance(loaded, Mapping):
        raise ReplayOptionError(f"{path} is not a mapping of topic names to QoS policies")
    return {str(topic): qos_override_from_dict(str(topic), p) for topic, p in loaded.items()}


# --------------------------------------------------------------------------
# Timing


@dataclass(frozen=True)
class PlaybackSchedule:
    """Maps bag log times to offsets from the moment playback started.

    ``origin_ns`` is the bag time that plays at offset 0; ``rate`` is the
    playback speed (2.0 plays twice as fast; ``math.inf`` as fast as possible).
    """

    origin_ns: int
    rate: float = 1.0

    def __post_init__(self) -> None:
        if not self.rate > 0:  # also rejects NaN
            raise ReplayOptionError(f"rate must be > 0, got {self.rate}")

    def offset_ns(self, log_time_ns: int) -> int:
        """Wall-clock nanoseconds after the anchor at which ``log_time_ns`` is due (>= 0)."""
        if math.isinf(self.rate):
            return 0
        return max(0, round((log_time_ns - self.origin_ns) / self.rate))

    def bag_time_ns(self, elapsed_ns: int) -> int:
        """The bag time reached ``elapsed_ns`` wall nanoseconds after the anchor.

        For an infinite rate there is no such mapping; the origin is returned.
        """
        if math.isinf(self.rate):
            return self.origin_ns
        return self.origin_ns + round(max(0, elapsed_ns) * self.rate)


class Waiter(Protocol):
    """The player's clock: a monotonic time source and an interruptible sleep."""

    def monotonic_ns(self) -> int: ...

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``; return True when playback was asked to stop."""
        ...


class EventWaiter:
    """:class:`Waiter` over ``time.monotonic_ns`` and a ``threading.Event`` (set = stop)."""

    def __init__(self, stop: threading.Event | None = None) -> None:
        self.stop_event = stop if stop is not None else threading.Event()

    def monotonic_ns(self) -> int:
        """Nanoseconds on the monotonic clock."""
        return time.monotonic_ns()

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``; True when stopped."""
        if seconds <= 0:
            return self.stop_event.is_set()
        return self.stop_event.wait(seconds)


# --------------------------------------------------------------------------
# Playback


@dataclass
class TopicTally:
    """What happened to one bag topic during playback.

    ``skipped`` messages were not published because their type is not
    installed; ``undecodable`` ones because their bytes do not decode as
    their type (``undecodable_reason`` is the first one's error).
    """

    output_topic: str
    msgtype: str
    published: int = 0
    bytes: int = 0
    skipped: int = 0
    skip_reason: str = ""
    undecodable: int = 0
    undecodable_reason: str = ""


@dataclass
class ReplayReport:
    """Summary of one replay: per-topic counts, timing, and how it ended.

    ``wall_ns`` is the playback time from the first due message to the last
    one sent; ``bag_span_ns`` the bag time covered (summed over loop passes).
    """

    topics: dict[str, TopicTally] = field(default_factory=dict)
    passes: int = 0
    wall_ns: int = 0
    bag_span_ns: int = 0
    interrupted: bool = False
    error: str = ""

    @property
    def published(self) -> int:
        """Messages published over all topics."""
        return sum(t.published for t in self.topics.values())

    @property
    def published_bytes(self) -> int:
        """Payload bytes published over all topics."""
        return sum(t.bytes for t in self.topics.values())

    @property
    def skipped(self) -> int:
        """Messages not published (type not installed) over all topics."""
        return sum(t.skipped for t in self.topics.values())

    @property
    def undecodable(self) -> int:
        """Messages not published because their bytes do not decode, over all topics."""
        return sum(t.undecodable for t in self.topics.values())

    @property
    def achieved_rate(self) -> float:
        """Bag seconds played per wall second (NaN when nothing took time)."""
        return self.bag_span_ns / self.wall_ns if self.wall_ns > 0 else math.nan

    def summary_lines(self) -> list[str]:
        """Human-readable lines: one per topic, then totals and timing."""
        lines = []
        for topic, tally in sorted(self.topics.items()):
            name = topic if tally.output_topic == topic else f"{topic} -> {tally.output_topic}"
            text = f"  {name} [{tally.msgtype}]: {tally.published} messages, {tally.bytes} bytes"
            if tally.skipped:
                text += f", {tally.skipped} not published ({tally.skip_reason})"
            if tally.undecodable:
                text += (
                    f", {tally.undecodable} not published (undecodable; first: "
                    f"{tally.undecodable_reason})"
                )
            lines.append(text)
        wall_s = self.wall_ns / 1e9
        mb_s = self.published_bytes / 1e6 / wall_s if wall_s > 0 else math.nan
        msg_s = self.published / wall_s if wall_s > 0 else math.nan
        lines.append(
            f"  total: {self.published} messages, {self.published_bytes} bytes in {wall_s:.3f} s "
            f"({msg_s:.1f} msg/s, {mb_s:.2f} MB/s); bag time {self.bag_span_ns / 1e9:.3f} s "
            f"in {self.passes} pass(es), achieved rate {self.achieved_rate:.3f}x"
        )
        if self.skipped:
            lines.append(f"  not published: {self.skipped} messages of uninstalled types")
        if self.undecodable:
            lines.append(
                f"  not published: {self.undecodable} messages whose bytes do not decode "
                "as their type"
            )
        if self.interrupted:
            lines.append("  interrupted before the end of the bag")
        if self.error:
            # the reader yields what it can reach (past a lost chunk too; not past framing
            # damage in a file without its summary) before it raises
            lines.append(f"  damaged bag, every message it could read was played: {self.error}")
        return lines


class Player:
    """Sends bag messages to publishers at their scheduled times.

    Args:
        open_messages: Returns a fresh iterator over the messages to play (selected topics,
            log time >= the schedule's origin, log-time order); called once per
            pass. It may raise :class:`~endo_io.errors.BagCorruptError` after the
            last intact message.
        publishers: Bag topic -> function publishing raw CDR bytes. Messages on topics
            without a publisher (type not installed) are counted as skipped. A
            function may raise :class:`~endo_io.bag.MessageDeserializationError`
            for bytes that do not decode: that message is counted as
            undecodable, not published, and playback goes on.
        tallies: Bag topic -> :class:`TopicTally` for every topic that may appear.
        schedule: Maps log times to wall offsets.
        loop: Start again from the origin after the last message, until stopped.
        waiter: Monotonic clock and interruptible sleep.
    """

    def __init__(
        self,
        open_messages: Callable[[], Iterator[PlayedMessage]],
        publishers: Mapping[str, Callable[[bytes], None]],
        tallies: Mapping[str, TopicTally],
        schedule: PlaybackSchedule,
        *,
        loop: bool = False,
        waiter: Waiter | None = None,
    ) -> None:
        self._open = open_messages
        self._publishers = publishers
        self._schedule = schedule
        self._loop = loop
        self._waiter: Waiter = waiter if waiter is not None else EventWaiter()
        self.report = ReplayReport(topics=dict(tallies))
        self._lock = threading.Lock()
        self._anchor_ns: int | None = None  # monotonic ns of the current pass's origin
        self._pending_ns: int | None = None  # log time of the message being waited for
        self._clock_ns = schedule.origin_ns  # bag time when no message is pending

    def bag_time_ns(self) -> int:
        """The current playback time in bag nanoseconds (for ``/clock``).

        Runs with the wall clock at ``rate`` but never past the next message
        not yet sent, and stays at the last message's time after the end.
        """
        with self._lock:
            if self._anchor_ns is None or self._pending_ns is None:
                return self._clock_ns
            if math.isinf(self._schedule.rate):
                return self._clock_ns
            elapsed = self._waiter.monotonic_ns() - self._anchor_ns
            return max(self._clock_ns, min(self._schedule.bag_time_ns(elapsed), self._pending_ns))

    def run(self) -> ReplayReport:
        """Play until the end of the bag (every pass with ``loop``), a stop, or damage."""
        waiter = self._waiter
        report = self.report
        first_start: int | None = None
        anchor = waiter.monotonic_ns()
        while True:
            with self._lock:
                self._anchor_ns = anchor
                self._clock_ns = self._schedule.origin_ns
            if first_start is None:
                first_start = anchor
            last_log: int | None = None
            try:
                for message in self._open():
                    publish = self._publishers.get(message.topic)
                    tally = report.topics[message.topic]
                    if publish is None:
                        tally.skipped += 1
                        continue
                    target = anchor + self._schedule.offset_ns(message.log_time_ns)
                    with self._lock:
                        self._pending_ns = message.log_time_ns
                    if self._sleep_until(target):
                        report.interrupted = True
                        break
                    try:
                        publish(message.data)
                    except MessageDeserializationError as error:
                        tally.undecodable += 1
                        tally.undecodable_reason = tally.undecodable_reason or str(error)
                        continue
                    tally.published += 1
                    tally.bytes += len(message.data)
                    last_log = message.log_time_ns
                    with self._lock:
                        self._clock_ns = last_log
                        self._pending_ns = None
            except BagCorruptError as error:
                report.error = str(error)
            report.passes += 1
            with self._lock:
                self._pending_ns = None
            if last_log is not None:
                report.bag_span_ns += max(0, last_log - self._schedule.origin_ns)
            report.wall_ns = waiter.monotonic_ns() - first_start
            if not self._loop or report.interrupted or report.error or last_log is None:
                break
            # Anchor the next pass where this pass's last message was due.
            anchor += self._schedule.offset_ns(last_log)
            if math.isinf(self._schedule.rate) or self._schedule.offset_ns(last_log) == 0:
                anchor = max(anchor, waiter.monotonic_ns())
        return report

    def _sleep_until(self, target_ns: int) -> bool:
        """Sleep until the monotonic clock reaches ``target_ns``; True when stopped."""
        waiter = self._waiter
        while True:
            remaining = target_ns - waiter.monotonic_ns()
            if remaining <= 0:
                return waiter.wait(0)
            if waiter.wait(remaining / 1e9):
                return True
