"""Recording live topics into a bag: which topics, which QoS, when to stop.

This module holds what ``endo-record`` decides without a ROS graph: which of
the discovered topics to record, the subscription QoS that matches every
publisher of a topic, and the bookkeeping around :class:`~endo_io.bag.BagWriter`
(per-topic counts, message and duration limits, periodic flushes so that a
killed recorder still leaves a readable file).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from endo_io.errors import Endo3dError

#: Topics that ``--all`` leaves out unless they are asked for by name: every
#: node has them, and they describe the recorder's own graph, not the data.
EXCLUDED_BY_DEFAULT: frozenset[str] = frozenset({"/rosout", "/parameter_events"})

#: Subscription history depth. Deeper than the ROS default (10) so that a
#: burst of large frames during a slow disk write is queued, not dropped.
DEFAULT_QUEUE_DEPTH = 100


class RecordOptionError(Endo3dError, ValueError):
    """A record option (topic list, limits, compression) is malformed."""


def is_hidden(topic: str) -> bool:
    """True for a hidden topic: one with a name component starting with ``_``."""
    return any(part.startswith("_") for part in topic.split("/") if part)


@dataclass(frozen=True)
class TopicChoice:
    """A topic to subscribe to, with the one type it is recorded as."""

    name: str
    msgtype: str
    other_types: tuple[str, ...] = ()


def topics_to_record(
    graph: Iterable[tuple[str, Sequence[str]]],
    requested: Sequence[str] = (),
    *,
    record_all: bool = False,
    already: Iterable[str] = (),
) -> list[TopicChoice]:
    """Choose the newly discovered topics to subscribe to.

    Parameters
    ----------
    graph:
        ``(topic, [type, ...])`` pairs as ``Node.get_topic_names_and_types``
        returns them; types like ``"sensor_msgs/msg/Image"``.
    requested:
        Topic names to record.
    record_all:
        Also record every other topic except :data:`EXCLUDED_BY_DEFAULT` and
        hidden ones (those are recorded only when ``requested`` names them).
    already:
        Topics subscribed to before; they are not returned again.

    Returns the choices in topic-name order. A topic published with several
    types is recorded as the first one; the others are listed in
    ``other_types`` for the caller to warn about.
    """
    done = set(already)
    wanted = set(requested)
    choices = []
    for name, types in sorted(graph, key=lambda pair: pair[0]):
        if name in done or not types:
            continue
        if name not in wanted and not (
            record_all and name not in EXCLUDED_BY_DEFAULT and not is_hidden(name)
        ):
            continue
        choices.append(TopicChoice(name, types[0], tuple(types[1:])))
    return choices


def adapt_request_to_offers(
    offers: Sequence[QoSProfile], depth: int = DEFAULT_QUEUE_DEPTH
) -> QoSProfile:
    """The subscription QoS that matches every publisher offering ``offers``.

    Reliable when every publisher is reliable, else best effort (a best-effort
    reader matches both kinds); transient local when every publisher is, so
    that latched messages are received, else volatile. Keep last ``depth``.
    Deadline and liveliness stay unset, which every offer is compatible with.
    With no offers the request is reliable and volatile.
    """
    if depth < 1:
        raise RecordOptionError(f"queue depth must be >= 1, got {depth}")
    reliable = all(o.reliability == ReliabilityPolicy.RELIABLE for o in offers)
    latched = bool(offers) and all(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def mixed_offer_warning(topic: str, offers: Sequence[QoSProfile]) -> str:
    """A warning when only some publishers of ``topic`` are reliable or latched, else ""."""
    notes = []
    n_reliable = sum(o.reliability == ReliabilityPolicy.RELIABLE for o in offers)
    if 0 < n_reliable < len(offers):
        notes.append("some publishers are reliable and some best effort: subscribing best effort")
    n_latched = sum(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers)
    if 0 < n_latched < len(offers):
        notes.append("some publishers are transient local: subscribing volatile")
    return f"{topic}: " + "; ".join(notes) if notes else ""


class RawBagWriter(Protocol):
    """The part of :class:`~endo_io.bag.BagWriter` the recording uses."""

    def add_topic(self, name: str, msgtype: str, offered_qos_profiles: str = "") -> None: ...

    def write(
        self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


@dataclass
class RecordedTopic:
    """Counts of one recorded topic."""

    msgtype: str
    messages: int = 0
    bytes: int = 0


@dataclass
class RecordReport:
    """What a recording wrote: per-topic counts and the time span received."""

    topics: dict[str, RecordedTopic] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    stop_reason: str = ""

    @property
    def messages(self) -> int:
        """Messages written over all topics."""
        return sum(t.messages for t in self.topics.values())

    @property
    def bytes(self) -> int:
        """Payload bytes written over all topics."""
        return sum(t.bytes for t in self.topics.values())

    def summary_lines(self) -> list[str]:
        """Human-readable lines: one per topic, then the totals."""
        lines = [
            f"  {name} [{t.msgtype}]: {t.messages} messages, {t.bytes} bytes"
            for name, t in sorted(self.topics.items())
        ]
        span = (
            (self.last_ns - self.first_ns) / 1e9
            if self.first_ns is not None and self.last_ns
            else 0.0
        )
        lines.append(
            f"  total: {self.messages} messages, {self.bytes} bytes over {span:.3f} s"
            + (f"; stopped: {self.stop_reason}" if self.stop_reason else "")
        )
        return lines


class Recording:
    """Writes raw messages into a bag as they arrive and says when to stop.

    Parameters
    ----------
    writer:
        An open bag writer; :meth:`close` closes it.
    max_messages:
        Stop after this many messages over all topics (None: no limit).
    max_duration_ns:
        Stop this long after :meth:`start` (None: no limit).
    """

    def __init__(
        self,
        writer: RawBagWriter,
        *,
        max_messages: int | None = None,
        max_duration_ns: int | None = None,
    ) -> None:
        if max_messages is not None and max_messages < 1:
            raise RecordOptionError(f"max messages must be >= 1, got {max_messages}")
        if max_duration_ns is not None and max_duration_ns <= 0:
            raise RecordOptionError(f"max duration must be > 0 ns, got {max_duration_ns}")
        self._writer = writer
        self._max_messages = max_messages
        self._max_duration_ns = max_duration_ns
        self._started_ns: int | None = None
        self._closed = False
        self.report = RecordReport()

    def start(self, now_ns: int) -> None:
        """Mark the start of the recording (for ``max_duration_ns``)."""
        self._started_ns = now_ns

    def add_topic(self, name: str, msgtype: str, offered_qos_profiles: str) -> None:
        """Declare a topic before its first message."""
        self._writer.add_topic(name, msgtype, offered_qos_profiles)
        self.report.topics[name] = RecordedTopic(msgtype)

    def write(self, topic: str, data: bytes, receive_ns: int) -> bool:
        """Write one message received at ``receive_ns`` (log and publish time).

        Returns True when a limit has been reached and recording should stop;
        messages arriving after that are not written.
        """
        if self._closed or self.limit_reached(receive_ns):
            return True
        self._writer.write(topic, data, receive_ns, receive_ns)
        tally = self.report.topics[topic]
        tally.messages += 1
        tally.bytes += len(data)
        if self.report.first_ns is None:
            self.report.first_ns = receive_ns
        self.report.last_ns = receive_ns
        return self.limit_reached(receive_ns)

    def limit_reached(self, now_ns: int) -> bool:
        """True when the message count or the duration limit has been reached."""
        if self._max_messages is not None and self.report.messages >= self._max_messages:
            self.report.stop_reason = self.report.stop_reason or f"{self._max_messages} messages"
            return True
        if (
            self._max_duration_ns is not None
            and self._started_ns is not None
            and now_ns - self._started_ns >= self._max_duration_ns
        ):
            limit_s = self._max_duration_ns / 1e9
            self.report.stop_reason = self.report.stop_reason or f"{limit_s:g} s"
            return True
        return False

    def flush(self) -> None:
        """Write buffered messages as a chunk, so a killed process leaves them readable."""
        if not self._closed:
            self._writer.flush()

    def close(self) -> RecordReport:
        """Finalise the bag (summary, footer) once; returns the report."""
        if not self._closed:
            self._closed = True
            self._writer.close()
        return self.report


def seconds_to_ns(seconds: float | None) -> int | None:
    """Option seconds to integer nanoseconds (None stays None; must be finite and > 0)."""
    if seconds is None:
        return None
    if not (0 < seconds < math.inf):
        raise RecordOptionError(f"duration must be a positive number of seconds, got {seconds}")
    return round(seconds * 1e9)
