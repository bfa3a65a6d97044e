"""A bounded, time-ordered buffer of stamped rigid transforms, queried by interpolation.

The tracker bridge publishes ``T_world_camera`` at tracker rate; a consumer
needs the pose at each image's stamp. :class:`PoseBuffer` keeps the most
recent poses (a fixed capacity, so memory is bounded when nobody asks) and
answers a query by :func:`endo_io.pose.interpolate_rigid` (linear
translation, SLERP rotation; the core of ``interpolate_transform``) between
the two poses around the stamp, found by a binary search. It
never extrapolates and never hands out a stale pose: a query it cannot
answer raises why, so the caller can wait (:class:`PoseNotYetError`) or
give up (:class:`PoseTooOldError`, :class:`PoseGapError`).

Stamps are checked by :class:`endo_io.clock_jump.ClockJumpDetector`. A pose
stream does not go backwards: a pose stamped before the newest one, by any
amount (:data:`POSE_JUMP_TOLERANCE_NS`), means the stream restarted (a bag
that loops, a tracker that restarts), and so does a forward jump confirmed by the
next pose. Either clears the buffer, keeps the new pose and raises
:class:`ClockJumpError` so that the caller logs and counts the reset (a
warning, not a dropped pose). A pose at the newest stamp again is a duplicate
(:class:`PoseOrderError`). One pose stamped far in the future is refused
(:class:`FutureStampError`) and locks nothing out.

A stamp older than every pose held is answered by why: before the stream's
first pose (nothing held was evicted since it started or restarted) it is
:class:`PoseBeforeStreamError`, the normal start of a stream (a camera's
first frame before the tracker's first pose, at each loop of a replay);
after evictions it is :class:`PoseTooOldError`.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

from endo_io.clock_jump import DEFAULT_FORWARD_TOLERANCE_NS, ClockJumpDetector
from endo_io.errors import (
    ClockJumpError,
    FutureStampError,
    PoseBeforeStreamError,
    PoseError,
    PoseGapError,
    PoseNotYetError,
    PoseOrderError,
    PoseTooOldError,
    StampOrderError,
)
from endo_io.pose import DEFAULT_TOLERANCE, check_rotation, interpolate_rigid
from endo_io.stamp import NS_PER_S

#: How far a pose may be stamped before its stream's newest without the stream
#: counting as restarted: none. Tracker drivers stamp in order and DDS keeps one
#: writer's order, so a step back, of any size, is a loop or a driver restart
#: (a bridge respawned under load saw a loop as a 0.7 s step back); the
#: stream's state is reset (and counted as a clock jump), never the sample
#: dropped as an error.
POSE_JUMP_TOLERANCE_NS = 0


class PoseBuffer:
    """Stamped (4, 4) rigid transforms in stamp order, at most ``capacity`` of them.

    Args:
        capacity: Poses kept; the oldest go first (at 60 Hz, 600 is ten seconds).
        max_gap_ns: Longest interval between the two poses around a query that is
            bridged by interpolation, integer nanoseconds.
        jump_tolerance_ns: A pose stamped more than this before the newest one is taken for a
            clock jump (the buffer resets); one stamped less before it, or at the
            same stamp, is out of order and refused. Default
            :data:`POSE_JUMP_TOLERANCE_NS` (0: any step back resets).
        forward_tolerance_ns: A pose stamped more than this after the newest one (and not
            arriving after an equally long silence) is refused until the next pose
            confirms the jump.
        rotation_tolerance: Allowed deviation of each rotation from orthonormal.
    """

    def __init__(
        self,
        *,
        capacity: int = 600,
        max_gap_ns: int = NS_PER_S // 10,
        jump_tolerance_ns: int = POSE_JUMP_TOLERANCE_NS,
        forward_tolerance_ns: int = DEFAULT_FORWARD_TOLERANCE_NS,
        rotation_tolerance: float = DEFAULT_TOLERANCE,
    ) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be at least 2, got {capacity}")
        if max_gap_ns < 0 or jump_tolerance_ns < 0:
            raise ValueError("max_gap_ns and jump_tolerance_ns must be >= 0")
        self.capacity = capacity
        self.max_gap_ns = int(max_gap_ns)
        self.jump_tolerance_ns = int(jump_tolerance_ns)
        self.rotation_tolerance = rotation_tolerance
        self._stamps: deque[int] = deque(maxlen=capacity)
        self._poses: deque[np.ndarray] = deque(maxlen=capacity)
        #: a pose was evicted (capacity) since the stream started or restarted
        self._evicted = False
        self._clock = ClockJumpDetector(
            back_tolerance_ns=self.jump_tolerance_ns, forward_tolerance_ns=forward_tolerance_ns
        )

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def oldest_ns(self) -> int | None:
        """Stamp of the oldest pose held, or None when empty."""
        return self._stamps[0] if self._stamps else None

    @property
    def newest_ns(self) -> int | None:
        """Stamp of the newest pose held, or None when empty."""
        return self._stamps[-1] if self._stamps else None

    def clear(self) -> None:
        """Forget every pose (and the stream's timeline)."""
        self._stamps.clear()
        self._poses.clear()
        self._evicted = False
        self._clock.reset()

    def insert(self, stamp_ns: int, T: np.ndarray, *, arrival_ns: int | None = None) -> None:
        """Add the (4, 4) transform ``T`` at ``stamp_ns`` (integer ns).

        ``arrival_ns`` (``time.monotonic_ns()`` when the pose arrived) lets a
        pose after a long tracker silence in without a confirmation.

        Raises:
            PoseError: ``T`` is not a finite rigid transform (nothing stored).
            PoseOrderError: ``stamp_ns`` is the newest pose's again (a duplicate), or
                before it within a non-zero jump tolerance (nothing stored).
            FutureStampError: ``stamp_ns`` is far after the newest pose and not
                yet confirmed by a later one (nothing stored).
            ClockJumpError: time jumped (back by more than the jump tolerance,
                by default any step back, or a confirmed forward jump); the
                buffer was cleared and now holds this pose.
        """
        mat = np.array(T, dtype=np.float64)
        if mat.shape != (4, 4) or not np.all(np.isfinite(mat)):
            raise PoseError(f"pose at {stamp_ns} ns is not a finite (4, 4) transform")
        check_rotation(mat[:3, :3], self.rotation_tolerance)
        try:
            jump = self._clock.check(stamp_ns, arrival_ns)
        except FutureStampError:
            raise
        except StampOrderError as error:
            raise PoseOrderError(f"pose {error}") from None
        if jump is not None:
            self._stamps.clear()
            self._poses.clear()
            self._evicted = False
            self._append(stamp_ns, mat)
            raise ClockJumpError(f"{jump.describe('pose time')}; pose buffer reset")
        self._append(stamp_ns, mat)

    def _append(self, stamp_ns: int, mat: np.ndarray) -> None:
        self._evicted |= len(self._stamps) == self.capacity
        self._stamps.append(int(stamp_ns))
        self._poses.append(mat)

    def query(self, stamp_ns: int, *, tolerance_ns: int = 0) -> np.ndarray:
        """The (4, 4) float64 transform at ``stamp_ns``, interpolated.

        A stamp equal to a held pose's gives that pose; one between two held
        poses at most ``max_gap_ns`` apart gives their interpolation. A stamp
        within ``tolerance_ns`` outside the held span gives the end pose
        (a zero-order hold that short, never longer).

        Raises:
            PoseNotYetError: the stamp is newer than the newest pose, or the
                buffer is empty (the poses may not have arrived yet).
            PoseBeforeStreamError: the stamp is before the stream's first pose
                (nothing was evicted since the stream started or restarted):
                no pose will come for it.
            PoseTooOldError: the stamp is older than the oldest pose held, and
                older poses were evicted.
            PoseGapError: the poses around the stamp are too far apart.
        """
        if not self._stamps:
            raise PoseNotYetError(f"no pose yet for the stamp {stamp_ns} ns")
        oldest, newest = self._stamps[0], self._stamps[-1]
        if stamp_ns > newest:
            if stamp_ns - newest <= tolerance_ns:
                return self._poses[-1].copy()
            raise PoseNotYetError(
                f"stamp {stamp_ns} ns is {(stamp_ns - newest) / 1e6:.1f} ms after the "
                "newest pose"
            )
        if stamp_ns < oldest:
            if oldest - stamp_ns <= tolerance_ns:
                return self._poses[0].copy()
            if not self._evicted:
                raise PoseBeforeStreamError(
                    f"stamp {stamp_ns} ns is {(oldest - stamp_ns) / 1e6:.1f} ms before the "
                    f"pose stream's first pose ({oldest} ns, where it started or restarted): "
                    "no pose will come for it"
                )
            raise PoseTooOldError(
                f"stamp {stamp_ns} ns is {(oldest - stamp_ns) / 1e6:.1f} ms before the "
                f"oldest pose held (older ones were evicted: capacity {self.capacity})"
            )
        # a binary search over the deque (no copy of its stamps: at capacity
        # 6000 the copy was most of a query's cost)
        after = bisect.bisect_right(self._stamps, stamp_ns)
        before_ns = self._stamps[after - 1]
        if before_ns == stamp_ns:
            return self._poses[after - 1].copy()
        after_ns = self._stamps[after]
        gap_ns = after_ns - before_ns
        if gap_ns > self.max_gap_ns:
            raise PoseGapError(
                f"stamp {stamp_ns} ns falls in a {gap_ns / 1e6:.1f} ms gap between "
                f"poses (longest bridged {self.max_gap_ns / 1e6:.1f} ms)"
            )
        # interpolate_transforms' fraction and interpolation, without re-validating
        # the two poses (insert did, with the same tolerance): the same bits
        ends = np.array([before_ns, after_ns, stamp_ns], dtype=np.int64)
        alpha = (ends[2:] - ends[:1]) / (ends[1:2] - ends[:1])
        return interpolate_rigid(
            self._poses[after - 1][None], self._poses[after][None], alpha
        )[0]
