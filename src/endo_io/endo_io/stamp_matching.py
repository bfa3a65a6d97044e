"""Pairing two message streams by header stamp (message_filters is not a dependency).

An image and its camera_info carry the same stamp but arrive separately and
in either order. :class:`StampMatcher` keeps a few recent messages of each
stream; a pair comes out as soon as both halves of one stamp have arrived
(or, with a tolerance, the nearest partner within it). Anything older than a
matched pair can no longer be matched and is dropped, as are the oldest
entries beyond the queue size, so memory stays bounded when one stream
stops.

A stream whose time jumps (a bag that loops, a camera driver that
restarts; :class:`endo_io.clock_jump.ClockJumpDetector`) would leave the old
timeline's unmatched messages behind, where a later message of the same
stamp could pair with them: on a jump of one stream, its queue is emptied
and the other stream's messages far (more than the jump tolerance) from the
new stamp are dropped, counted in :attr:`StampMatcher.dropped` and
:attr:`StampMatcher.clock_jumps`.

Two streams that never agree (a driver that stamps camera_info a few ms
apart from its image) would otherwise only grow a counter: once each
stream brought :data:`MISMATCH_ARRIVALS` messages without a partner since
the last pair, :meth:`StampMatcher.mismatch` says so in one line, with the
nearest stamp difference seen, so the node can name the cause and the
parameter. One stream that stops (a dead upstream node) is not a mismatch.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from endo_io.clock_jump import ClockJumpDetector
from endo_io.errors import StampOrderError
from endo_io.stamp import NS_PER_S

#: Messages of each stream without a partner since the last pair before
#: :meth:`StampMatcher.mismatch` speaks (a second at 30 fps: more than the
#: transient misses around a queue overflow or a clock jump).
MISMATCH_ARRIVALS = 30

A = TypeVar("A")
B = TypeVar("B")


@dataclass(frozen=True)
class MatchedPair(Generic[A, B]):
    """One pair: the stamp of the first stream's message (integer ns) and both messages."""

    stamp_ns: int
    first: A
    second: B


class StampMatcher(Generic[A, B]):
    """Pairs messages of two streams whose stamps agree within ``tolerance_ns``.

    Args:
        queue_size: How many unmatched messages of each stream are kept.
        tolerance_ns: Largest stamp difference of a pair, integer nanoseconds (0: exact).
        jump_tolerance_ns: A stream's stamp this far before its newest is a clock jump.
    """

    def __init__(
        self, queue_size: int = 10, tolerance_ns: int = 0, *, jump_tolerance_ns: int = NS_PER_S
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, got {queue_size}")
        if tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
        self.queue_size = queue_size
        self.tolerance_ns = tolerance_ns
        self._first: OrderedDict[int, A] = OrderedDict()
        self._second: OrderedDict[int, B] = OrderedDict()
        self.dropped = 0
        self.clock_jumps = 0
        self._misses = [0, 0]  # arrivals without a partner since the last pair, per stream
        self._nearest_miss_ns: int | None = None  # since the last pair
        self.jump_tolerance_ns = int(jump_tolerance_ns)
        self._clocks = (
            ClockJumpDetector(back_tolerance_ns=self.jump_tolerance_ns),
            ClockJumpDetector(back_tolerance_ns=self.jump_tolerance_ns),
        )

    def add_first(self, stamp_ns: int, message: A) -> MatchedPair[A, B] | None:
        """Offer a message of the first stream; returns its pair if complete."""
        self._follow(0, stamp_ns)
        partner = self._closest(self._second, stamp_ns)
        if partner is None:
            self._miss(0, self._second, stamp_ns)
            self._store(self._first, stamp_ns, message)
            return None
        second = self._second.pop(partner)
        self._forget_older_than(min(stamp_ns, partner))
        self._matched()
        return MatchedPair(stamp_ns, message, second)

    def add_second(self, stamp_ns: int, message: B) -> MatchedPair[A, B] | None:
        """Offer a message of the second stream; returns its pair if complete."""
        self._follow(1, stamp_ns)
        partner = self._closest(self._first, stamp_ns)
        if partner is None:
            self._miss(1, self._first, stamp_ns)
            self._store(self._second, stamp_ns, message)
            return None
        first = self._first.pop(partner)
        self._forget_older_than(min(stamp_ns, partner))
        self._matched()
        return MatchedPair(partner, first, message)

    def mismatch(self, first: str, second: str) -> str | None:
        """One line when both streams come but stopped pairing (:data:`MISMATCH_ARRIVALS`).

        Args:
            first: the first stream's name (e.g. its topic), for the line.
            second: the second stream's name.
        """
        if min(self._misses) < MISMATCH_ARRIVALS or self._nearest_miss_ns is None:
            return None
        apart_ms, tolerance_ms = self._nearest_miss_ns / 1e6, self.tolerance_ns / 1e6
        return (f"{self._misses[0]} {first} and {self._misses[1]} {second} messages without a "
                f"partner since the last pair: the closest stamps were {apart_ms:.3f} ms apart, "
                f"beyond the stamp tolerance of {tolerance_ms:g} ms (a driver that stamps them "
                f"apart needs stamp_tolerance, seconds, above that)")

    def _matched(self) -> None:
        self._misses = [0, 0]
        self._nearest_miss_ns = None

    def _miss(self, stream: int, other: OrderedDict[int, Any], stamp_ns: int) -> None:
        """Count an arrival without a partner; remember how close the other stream came."""
        self._misses[stream] += 1
        if other:
            nearest = min(abs(s - stamp_ns) for s in other)
            if self._nearest_miss_ns is None or nearest < self._nearest_miss_ns:
                self._nearest_miss_ns = nearest

    def clear(self) -> None:
        """Drop every unmatched message and forget both streams' timelines."""
        self.dropped += len(self._first) + len(self._second)
        self._first.clear()
        self._second.clear()
        for clock in self._clocks:
            clock.reset()

    def _follow(self, stream: int, stamp_ns: int) -> None:
        """Track a stream's time; on a jump, drop what the old timeline left unmatched."""
        try:
            jump = self._clocks[stream].check(stamp_ns)
        except StampOrderError:
            return  # out of order or one wild stamp: matching does not care
        if jump is None:
            return
        own, other = (self._first, self._second) if stream == 0 else (self._second, self._first)
        far = [s for s in other if abs(s - stamp_ns) > self.jump_tolerance_ns]
        self.dropped += len(own) + len(far)
        own.clear()
        for stale in far:
            del other[stale]
        self.clock_jumps += 1

    def pending(self) -> tuple[int, int]:
        """Unmatched messages held of (first, second) stream."""
        return len(self._first), len(self._second)

    def _closest(self, queue: OrderedDict[int, Any], stamp_ns: int) -> int | None:
        if stamp_ns in queue:
            return stamp_ns
        if self.tolerance_ns == 0 or not queue:
            return None
        best = min(queue, key=lambda s: abs(s - stamp_ns))
        return best if abs(best - stamp_ns) <= self.tolerance_ns else None

    def _store(self, queue: OrderedDict[int, A] | OrderedDict[int, B], stamp_ns: int,
               message: object) -> None:
        if stamp_ns in queue:
            queue.pop(stamp_ns)  # a repeated stamp replaces the older message
            self.dropped += 1
        queue[stamp_ns] = message  # type: ignore[assignment]
        while len(queue) > self.queue_size:
            queue.popitem(last=False)
            self.dropped += 1

    def _forget_older_than(self, stamp_ns: int) -> None:
        for queue in (self._first, self._second):
            for old in [s for s in queue if s < stamp_ns - self.tolerance_ns]:
                del queue[old]
                self.dropped += 1
