"""Recording live topics into a bag: which topics, which QoS, when to stop.

This module holds what ``endo-record`` decides without a ROS graph: which of
the discovered topics to record, the subscription QoS that matches every
publisher of a topic, and the bookkeeping around :class:`~endo_io.bag.BagWriter`
(per-topic counts, message and duration limits, periodic flushes so that a
killed recorder still leaves a readable file).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from endo_io.bag.errors import MessageDeserializationError
from endo_io.errors import BagError, Endo3dError

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

    Args:
        graph: ``(topic, [type, ...])`` pairs as ``Node.get_topic_names_and_types``
            returns them; types like ``"sensor_msgs/msg/Image"``.
        requested: Topic names to record.
        record_all: Also record every other topic except :data:`EXCLUDED_BY_DEFAULT` and
            hidden ones (those are recorded only when ``requested`` names them).
        already: Topics subscribed to before; they are not returned again.

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

    @property
    def written(self) -> Mapping[str, tuple[int, int]]:
        """Topic -> (messages, payload bytes) that are on disk."""
        ...


#: Checks that a message's bytes decode as its type; raises
#: :class:`~endo_io.bag.MessageDeserializationError` when they do not.
CdrCheck = Callable[[bytes], object]


@dataclass
class RecordedTopic:
    """Counts of one recorded topic.

    ``messages`` and ``bytes`` are what the file holds (messages in complete
    chunks on disk, taken from the writer); ``received`` counts every message
    handed to the writer, so ``received - messages`` were lost when a write
    failed. ``undecodable`` messages did not decode as ``msgtype`` (they are
    recorded anyway, as received); ``undecodable_reason`` is the first one's
    error.
    """

    msgtype: str
    messages: int = 0
    bytes: int = 0
    received: int = 0
    undecodable: int = 0
    undecodable_reason: str = ""


@dataclass
class RecordReport:
    """What a recording wrote: per-topic counts and the time span received."""

    topics: dict[str, RecordedTopic] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    stop_reason: str = ""
    write_error: str = ""

    @property
    def messages(self) -> int:
        """Messages the file holds over all topics."""
        return sum(t.messages for t in self.topics.values())

    @property
    def bytes(self) -> int:
        """Payload bytes the file holds over all topics."""
        return sum(t.bytes for t in self.topics.values())

    @property
    def received(self) -> int:
        """Messages received (handed to the writer) over all topics."""
        return sum(t.received for t in self.topics.values())

    @property
    def lost(self) -> int:
        """Messages received that a failed write kept out of the file."""
        return sum(max(0, t.received - t.messages) for t in self.topics.values())

    @property
    def undecodable(self) -> int:
        """Messages whose bytes did not decode as their type (recorded anyway)."""
        return sum(t.undecodable for t in self.topics.values())

    def summary_lines(self) -> list[str]:
        """Human-readable lines: one per topic, then the totals."""
        lines = []
        for name, t in sorted(self.topics.items()):
            line = f"  {name} [{t.msgtype}]: {t.messages} messages, {t.bytes} bytes"
            if t.received > t.messages:
                line += f", {t.received - t.messages} received but lost"
            if t.undecodable:
                line += (
                    f", {t.undecodable} undecodable (recorded as received; first: "
                    f"{t.undecodable_reason})"
                )
            lines.append(line)
        span = (
            (self.last_ns - self.first_ns) / 1e9
            if self.first_ns is not None and self.last_ns
            else 0.0
        )
        lines.append(
            f"  total: {self.messages} messages, {self.bytes} bytes over {span:.3f} s"
            + (f"; stopped: {self.stop_reason}" if self.stop_reason else "")
        )
        if self.lost:
            lines.append(
                f"  lost: {self.lost} of {self.received} received messages are not in the "
                f"file ({self.write_error})"
            )
        if self.undecodable:
            lines.append(
                f"  undecodable: {self.undecodable} messages did not decode as their type"
            )
        return lines


class Recording:
    """Writes raw messages into a bag as they arrive and says when to stop.

    Args:
        writer: An open bag writer; :meth:`close` closes it.
        max_messages: Stop after this many messages over all topics (None: no limit).
        max_duration_ns: Stop this long after :meth:`start` (None: no limit).
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
        self._checks: dict[str, CdrCheck] = {}
        self.report = RecordReport()

    def start(self, now_ns: int) -> None:
        """Mark the start of the recording (for ``max_duration_ns``)."""
        self._started_ns = now_ns

    def add_topic(
        self, name: str, msgtype: str, offered_qos_profiles: str, check: CdrCheck | None = None
    ) -> None:
        """Declare a topic before its first message.

        ``check`` (optional) is called with each message's bytes and raises
        :class:`~endo_io.bag.MessageDeserializationError` when they do not
        decode as ``msgtype``; such messages are counted as undecodable.
        """
        self._writer.add_topic(name, msgtype, offered_qos_profiles)
        self.report.topics[name] = RecordedTopic(msgtype)
        if check is not None:
            self._checks[name] = check

    def write(self, topic: str, data: bytes, receive_ns: int,
              publish_ns: int | None = None) -> bool:
        """Write one message received at ``receive_ns`` (log time), published at ``publish_ns``.

        ``publish_ns`` None: the receive time is the publish time too.

        Returns True when a limit has been reached and recording should stop;
        messages arriving after that are not written. A message that does not
        decode as its topic's type is written all the same and counted in
        ``report.topics[topic].undecodable``.

        Raises:
            BagError: the writer failed (:meth:`close` then reports what the
                file holds).
        """
        if self._closed or self.limit_reached(receive_ns):
            return True
        tally = self.report.topics[topic]
        check = self._checks.get(topic)
        if check is not None:
            try:
                check(data)
            except MessageDeserializationError as error:
                tally.undecodable += 1
                tally.undecodable_reason = tally.undecodable_reason or str(error)
        tally.received += 1
        try:
            self._writer.write(topic, data, receive_ns,
                               receive_ns if publish_ns is None else max(publish_ns, 0))
        except BagError as error:
            self.report.write_error = str(error)
            self._take_written()
            raise
        if self.report.first_ns is None:
            self.report.first_ns = receive_ns
        self.report.last_ns = receive_ns
        return self.limit_reached(receive_ns)

    def _take_written(self) -> None:
        """Set the report's file counts from what the writer has on disk."""
        for name, (messages, size) in self._writer.written.items():
            tally = self.report.topics.get(name)
            if tally is not None:
                tally.messages, tally.bytes = messages, size

    def limit_reached(self, now_ns: int) -> bool:
        """True when the message count or the duration limit has been reached."""
        if self._max_messages is not None and self.report.received >= self._max_messages:
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
        """Write buffered messages as a chunk, so a killed process leaves them readable.

        Raises:
            BagError: the writer failed (the report then counts what is on disk).
        """
        if not self._closed:
            try:
                self._writer.flush()
            except BagError as error:
                self.report.write_error = str(error)
                raise
            finally:
                self._take_written()

    def close(self) -> RecordReport:
        """Finalise the bag (summary, footer) once; returns the report.

        The report's counts are what the file holds, also when finishing it
        fails (then BagError is raised and :attr:`report` has the counts).
        """
        if not self._closed:
            self._closed = True
            try:
                self._writer.close()
            except BagError as error:
                self.report.write_error = self.report.write_error or str(error)
                raise
            finally:
                self._take_written()
        return self.report


def seconds_to_ns(seconds: float | None) -> int | None:
    """Option seconds to integer nanoseconds (None stays None; must be finite and > 0)."""
    if seconds is None:
        return None
    if not (0 < seconds < math.inf):
        raise RecordOptionError(f"duration must be a positive number of seconds, got {seconds}")
    return round(seconds * 1e9)
