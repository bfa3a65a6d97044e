"""Pairing two message streams by header stamp (message_filters is not a dependency).

An image and its camera_info carry the same stamp but arrive separately and
in either order. :class:`StampMatcher` keeps a few recent messages of each
stream; a pair comes out as soon as both halves of one stamp have arrived
(or, with a tolerance, the nearest partner within it). Anything older than a
matched pair can no longer be matched and is dropped, as are the oldest
entries beyond the queue size, so memory stays bounded when one stream
stops.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

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
    """

    def __init__(self, queue_size: int = 10, tolerance_ns: int = 0) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be at least 1, got {queue_size}")
        if tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
        self.queue_size = queue_size
        self.tolerance_ns = tolerance_ns
        self._first: OrderedDict[int, A] = OrderedDict()
        self._second: OrderedDict[int, B] = OrderedDict()
        self.dropped = 0

    def add_first(self, stamp_ns: int, message: A) -> MatchedPair[A, B] | None:
        """Offer a message of the first stream; returns its pair if complete."""
        partner = self._closest(self._second, stamp_ns)
        if partner is None:
            self._store(self._first, stamp_ns, message)
            return None
        second = self._second.pop(partner)
        self._forget_older_than(min(stamp_ns, partner))
        return MatchedPair(stamp_ns, message, second)

    def add_second(self, stamp_ns: int, message: B) -> MatchedPair[A, B] | None:
        """Offer a message of the second stream; returns its pair if complete."""
        partner = self._closest(self._first, stamp_ns)
        if partner is None:
            self._store(self._second, stamp_ns, message)
            return None
        first = self._first.pop(partner)
        self._forget_older_than(min(stamp_ns, partner))
        return MatchedPair(partner, first, message)

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
