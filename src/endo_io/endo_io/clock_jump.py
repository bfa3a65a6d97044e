"""Detecting time that jumps in a stamped stream: bag loops, driver restarts, ``/clock`` resets.

Every piece of state a node keeps over time (the tracker bridge's sample
gate, pose buffers, stamp matchers, the SFS warm start, the flow filter)
assumes its input's stamps go forwards. They do not always:

* a bag replayed with ``--loop`` starts again at its first stamp;
* a tracker driver or camera that restarts may start its clock elsewhere;
* one sample may carry a wild stamp (a driver bug, a clock set by hand).

:class:`ClockJumpDetector` classifies each stamp of one stream against the
newest stamp of the stream's current timeline (its *reference*):

* **in order**: after the reference, by at most ``forward_tolerance_ns``
  (or by any amount when the stamp gap agrees with the arrival-time gap
  within that tolerance: a silence, not a jump). It becomes the reference.
* **a jump back**: more than ``back_tolerance_ns`` before the reference.
  :meth:`ClockJumpDetector.check` returns a :class:`ClockJump`; the caller
  resets its state, logs one line, counts it and goes on with this stamp.
* **suspect**: forward by more than the tolerance, or back by at most the
  back tolerance (or a repeat of the reference). One such stamp raises
  (:class:`~endo_io.errors.FutureStampError`,
  :class:`~endo_io.errors.StampOrderError`) and the caller drops that sample;
  it does not move the reference, so one future-stamped sample cannot lock
  the stream out. When the *next* stamp continues the suspect's timeline
  (after it, within the forward tolerance) the jump is confirmed: a
  :class:`ClockJump` is returned, and the stream resumes on the new
  timeline, having lost one sample. A stamp that continues the old timeline
  instead discards the suspect.

All stamps are integer nanoseconds; arrival times, when given, are
integer nanoseconds of a monotonic clock (``time.monotonic_ns()``).
"""

from __future__ import annotations

from dataclasses import dataclass

from endo_io.errors import FutureStampError, StampOrderError
from endo_io.stamp import NS_PER_S

#: A stamp more than this before its stream's newest is a jump back (s).
DEFAULT_BACK_TOLERANCE_NS = NS_PER_S
#: A stamp more than this after its stream's newest, while the arrival times
#: do not show an equally long silence, is suspect (s).
DEFAULT_FORWARD_TOLERANCE_NS = 10 * NS_PER_S


@dataclass(frozen=True)
class ClockJump:
    """One detected jump of a stream's time.

    Attributes:
        previous_ns: the newest stamp of the old timeline, integer ns.
        stamp_ns: the first stamp of the new timeline that was accepted, integer ns.
    """

    previous_ns: int
    stamp_ns: int

    @property
    def delta_ns(self) -> int:
        """Signed size of the jump, integer ns (negative: back in time)."""
        return self.stamp_ns - self.previous_ns

    def describe(self, what: str = "time") -> str:
        """One line: ``"<what> jumped back 3.000 s (from A to B ns)"``."""
        direction = "back" if self.delta_ns < 0 else "forward"
        return (
            f"{what} jumped {direction} {abs(self.delta_ns) / NS_PER_S:.3f} s "
            f"(from {self.previous_ns} to {self.stamp_ns} ns)"
        )

    def __str__(self) -> str:
        return self.describe()


class ClockJumpDetector:
    """Classifies the stamps of one stream (see the module docstring).

    Args:
        back_tolerance_ns: a stamp more than this before the reference is a
            jump back; one less before it (or equal) is out of order.
        forward_tolerance_ns: a stamp more than this after the reference is
            suspect unless the arrival times show an equal silence.
    """

    def __init__(
        self,
        *,
        back_tolerance_ns: int = DEFAULT_BACK_TOLERANCE_NS,
        forward_tolerance_ns: int = DEFAULT_FORWARD_TOLERANCE_NS,
    ) -> None:
        if back_tolerance_ns < 0 or forward_tolerance_ns <= 0:
            raise ValueError("back_tolerance_ns must be >= 0 and forward_tolerance_ns > 0")
        self.back_tolerance_ns = int(back_tolerance_ns)
        self.forward_tolerance_ns = int(forward_tolerance_ns)
        self.jumps = 0
        self._reference: int | None = None
        self._reference_arrival: int | None = None
        self._suspect: int | None = None
        self._suspect_arrival: int | None = None

    @property
    def reference_ns(self) -> int | None:
        """The newest stamp of the current timeline (None before the first)."""
        return self._reference

    def is_late(self, stamp_ns: int) -> bool:
        """True for a stamp at or before the reference by at most the back tolerance.

        A frame paired with another input (its camera_info, its pose) can be
        handed out after a newer frame was processed, when its partner came
        late on a loaded machine: that frame is stale, to be skipped and
        counted as such, not checked (:meth:`check` would raise
        :class:`~endo_io.errors.StampOrderError` for it, and a second such
        frame would confirm a clock jump and reset the stream's state). The
        price: a stream that really steps back by less than the tolerance is
        skipped until it passes its old newest stamp instead of reset.
        """
        reference = self._reference
        return reference is not None and 0 <= reference - int(stamp_ns) <= self.back_tolerance_ns

    def reset(self) -> None:
        """Forget the stream: the next stamp starts a timeline."""
        self._reference = self._reference_arrival = None
        self._suspect = self._suspect_arrival = None

    def check(
        self, stamp_ns: int, arrival_ns: int | None = None, *, commit: bool = True
    ) -> ClockJump | None:
        """Classify ``stamp_ns``; None when in order, a :class:`ClockJump` after a jump.

        Args:
            stamp_ns: the sample's stamp, integer ns.
            arrival_ns: when the sample arrived, integer ns of a monotonic
                clock; lets a long silence pass as in order. None: stamps only.
            commit: make an in-order stamp the reference now; False leaves
                that to :meth:`adopt`, for a caller that may still refuse the
                sample for another reason (a jump is always committed).

        Returns:
            None for a stamp in order (it is now the reference); a
            :class:`ClockJump` when the stream jumped (the caller resets
            the state it keeps over time; the stamp is the new reference).

        Raises:
            FutureStampError: ahead of the reference by more than the forward
                tolerance, not yet confirmed: drop the sample.
            StampOrderError: at or before the reference within the back
                tolerance: drop the sample.
        """
        stamp_ns = int(stamp_ns)
        reference = self._reference
        if reference is None:
            if commit:
                self.adopt(stamp_ns, arrival_ns)
            return None
        ahead_ns = stamp_ns - reference
        if ahead_ns > 0:
            if ahead_ns <= self.forward_tolerance_ns or self._silence(
                ahead_ns, arrival_ns, self._reference_arrival
            ):
                if commit:
                    self.adopt(stamp_ns, arrival_ns)
                return None
            if self._continues_suspect(stamp_ns, arrival_ns):
                return self._jump(reference, stamp_ns, arrival_ns)
            self._suspect, self._suspect_arrival = stamp_ns, arrival_ns
            raise FutureStampError(
                f"stamp {stamp_ns} ns is {ahead_ns / NS_PER_S:.3f} s after the stream's newest "
                f"{reference} ns; dropped until the next sample confirms a clock jump"
            )
        if -ahead_ns > self.back_tolerance_ns:
            return self._jump(reference, stamp_ns, arrival_ns)
        if ahead_ns < 0:
            if self._continues_suspect(stamp_ns, arrival_ns):
                return self._jump(reference, stamp_ns, arrival_ns)
            self._suspect, self._suspect_arrival = stamp_ns, arrival_ns
        raise StampOrderError(
            f"stamp {stamp_ns} ns is {-ahead_ns} ns before or at the newest {reference} ns"
        )

    def _silence(self, ahead_ns: int, arrival_ns: int | None, since_ns: int | None) -> bool:
        """True when the arrival gap explains the stamp gap (a pause, not a jump)."""
        if arrival_ns is None or since_ns is None:
            return False
        return abs(ahead_ns - (arrival_ns - since_ns)) <= self.forward_tolerance_ns

    def _continues_suspect(self, stamp_ns: int, arrival_ns: int | None) -> bool:
        suspect = self._suspect
        if suspect is None:
            return False
        after_ns = stamp_ns - suspect
        return after_ns > 0 and (
            after_ns <= self.forward_tolerance_ns
            or self._silence(after_ns, arrival_ns, self._suspect_arrival)
        )

    def _jump(self, previous_ns: int, stamp_ns: int, arrival_ns: int | None) -> ClockJump:
        self.adopt(stamp_ns, arrival_ns)
        self.jumps += 1
        return ClockJump(previous_ns, stamp_ns)

    def adopt(self, stamp_ns: int, arrival_ns: int | None = None) -> None:
        """Make ``stamp_ns`` the reference (after ``check(..., commit=False)`` passed it)."""
        self._reference, self._reference_arrival = int(stamp_ns), arrival_ns
        self._suspect = self._suspect_arrival = None
