"""Frames lost in transport, from the stamps of a stream at a nominal rate.

A camera publishes at a fixed rate; a best-effort DDS subscription that
loses a fragment, or a subscriber queue that overflows while the node is
busy, loses whole frames without a trace. :class:`SequenceGapCounter`
estimates the stream's period as the median of its recent stamp intervals
(so it follows the stream, whatever its rate: 30 Hz live, a bag's own rate
at any replay speed) and counts each interval of about ``k`` periods as
``k - 1`` missing frames.

Intervals longer than ``max_gap_periods`` periods are a pause or a restart
of the stream (a replay between two passes, a driver restarted), not loss:
they are not counted, nor are stamps that go backwards (a clock jump, which
restarts the estimate).
"""

from __future__ import annotations

from collections import deque

import numpy as np


class SequenceGapCounter:
    """Counts missing stamps of one stream at its estimated nominal rate.

    Args:
        history: stamp intervals the period is estimated from.
        min_intervals: intervals needed before anything is counted.
        max_gap_periods: longest interval, in periods, counted as loss.
    """

    def __init__(
        self, *, history: int = 31, min_intervals: int = 8, max_gap_periods: int = 30
    ) -> None:
        if history < 1 or min_intervals < 1 or max_gap_periods < 2:
            raise ValueError("history and min_intervals must be >= 1, max_gap_periods >= 2")
        self.min_intervals = min_intervals
        self.max_gap_periods = max_gap_periods
        self.lost = 0
        self._intervals: deque[int] = deque(maxlen=history)
        self._last: int | None = None

    @property
    def period_ns(self) -> float | None:
        """The estimated nominal period, ns (None until ``min_intervals`` are known)."""
        if len(self._intervals) < self.min_intervals:
            return None
        return float(np.median(np.fromiter(self._intervals, np.int64, len(self._intervals))))

    def reset(self) -> None:
        """Forget the stream (the count stays)."""
        self._intervals.clear()
        self._last = None

    def add(self, stamp_ns: int) -> int:
        """Take the next stamp (integer ns); returns how many frames were missing before it."""
        stamp_ns = int(stamp_ns)
        last, self._last = self._last, stamp_ns
        if last is None:
            return 0
        interval = stamp_ns - last
        if interval <= 0:
            if interval < 0:
                self._intervals.clear()  # time went back: a new stream
            else:
                self._last = last  # a repeated stamp is not an interval
            return 0
        period = self.period_ns
        periods = 1 if period is None or period <= 0 else round(interval / period)
        if periods > self.max_gap_periods:
            return 0  # a pause, not loss; nor a sample of the period
        self._intervals.append(interval)
        missing = max(periods - 1, 0)
        self.lost += missing
        return missing
