"""Rejection of bad tracker samples.

Two kinds of checks:

* checks of one raw measurement (:func:`check_finite`,
  :func:`check_unit_quaternion`, :func:`check_rotation_matrix`), run by the
  sources while converting, before a quaternion or matrix is trusted;
* checks against the stream's history (:class:`SampleGate`): the tool must be
  visible, time must go forwards, and the marker must not move faster than a
  hand can move an endoscope. A jump beyond that speed is a tracking glitch
  (a reflection taken for a marker sphere, a swapped tool), not motion.
  Time is checked per tool by :class:`endo_io.clock_jump.ClockJumpDetector`:
  a step back of any size (a looped recording, a restarted driver; see
  :data:`endo_io.pose_buffer.POSE_JUMP_TOLERANCE_NS`) or a confirmed jump
  forward forgets the tool's history and the sample is accepted, reported
  as a :class:`~endo_io.clock_jump.ClockJump`; a repeat of the newest stamp
  is dropped; one sample stamped far in the future is dropped and locks
  nothing out.

Each failure raises its own :mod:`endo_tracker_bridge.errors` class with a
one-line message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from endo_io.clock_jump import DEFAULT_FORWARD_TOLERANCE_NS, ClockJump, ClockJumpDetector
from endo_io.errors import FutureStampError, PoseError, StampOrderError
from endo_io.pose import DEFAULT_TOLERANCE, check_rotation, rotation_angle, unit_quaternion
from endo_io.pose_buffer import POSE_JUMP_TOLERANCE_NS
from endo_tracker_bridge.errors import (
    NonFinitePoseError,
    NonOrthonormalRotationError,
    NonUnitQuaternionError,
    SpeedLimitError,
    TimeWentBackwardsError,
    ToolNotVisibleError,
)
from endo_tracker_bridge.sample import ToolStatus, TrackerSample

#: Tolerance on | |q| - 1 | and on the orthonormality of rotation matrices:
#: endo_io's one constant. Trackers send float32 (OpenIGTLink) or 4-decimal
#: text (NDI TX), which is good to ~1e-4; a real fault is far larger.
DEFAULT_ROTATION_TOLERANCE = DEFAULT_TOLERANCE


def check_finite(values: np.ndarray, what: str) -> None:
    """Raise :class:`NonFinitePoseError` when ``values`` (any shape) holds NaN or inf."""
    array = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise NonFinitePoseError(
            f"{what} is not finite: {np.array2string(array.ravel(), precision=4)}"
        )


def check_unit_quaternion(q: np.ndarray, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """Check a quaternion (4,) (any component order) and return it normalised.

    :func:`endo_io.pose.unit_quaternion` with the bridge's error classes, so
    that each rejected sample is counted under its own name.

    Args:
        q: (4,) quaternion, any component order.
        tolerance: allowed ``| |q| - 1 |``.

    Returns:
        (4,) float64 with norm 1, same component order.

    Raises:
        NonFinitePoseError: NaN or inf.
        NonUnitQuaternionError: ``| |q| - 1 | > tolerance``.
    """
    quaternion = np.asarray(q, dtype=np.float64).reshape(4)
    check_finite(quaternion, "quaternion")
    try:
        return unit_quaternion(quaternion, tolerance)
    except PoseError as error:
        raise NonUnitQuaternionError(str(error)) from None


def check_rotation_matrix(R: np.ndarray, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """Check a rotation matrix (3,3) and return the nearest exact rotation.

    :func:`endo_io.pose.check_rotation` with the bridge's error classes.

    Args:
        R: (3, 3) matrix.
        tolerance: allowed ``max |RᵀR − I|``.

    Returns:
        (3, 3) float64, the SVD projection of ``R`` onto SO(3).

    Raises:
        NonFinitePoseError: NaN or inf.
        NonOrthonormalRotationError: not orthonormal within ``tolerance``, or
            ``det R <= 0``.
    """
    rotation = np.asarray(R, dtype=np.float64).reshape(3, 3)
    check_finite(rotation, "rotation matrix")
    try:
        check_rotation(rotation, tolerance)
    except PoseError as error:
        raise NonOrthonormalRotationError(str(error)) from None
    u, _, vt = np.linalg.svd(rotation)
    return u @ vt


#: A tracked tool this far from the tracker's origin, in metres, is no
#: tracker's working volume (optical trackers reach ~3 m, motion capture rooms
#: ~10 m): its positions are millimetres read as metres.
MILLIMETRE_SUSPECT_M = 20.0


def millimetres_hint(translation_m: np.ndarray) -> str:
    """A clause naming the unit setting when a position looks like millimetres, else "".

    Args:
        translation_m: (3,) float64, the tool's position as read, metres.

    Returns:
        ``"; the tool is 1312 m from the tracker: millimetres read as metres?
        (the bridge's ros_unit / igtl_unit / csv_unit: mm)"`` when the position
        is beyond :data:`MILLIMETRE_SUSPECT_M`, else ``""``.
    """
    distance_m = float(np.linalg.norm(translation_m))
    if not distance_m > MILLIMETRE_SUSPECT_M:
        return ""
    return (f"; the tool is {distance_m:.0f} m from the tracker: millimetres read as metres? "
            "(the bridge's ros_unit / igtl_unit / csv_unit: mm)")


@dataclass(frozen=True)
class SpeedLimits:
    """Largest plausible motion of the marker between two accepted samples.

    ``linear_m_s`` is in metres per second, ``angular_deg_s`` in degrees per
    second; ``math.inf`` disables a limit.
    """

    linear_m_s: float = 2.0
    angular_deg_s: float = 720.0


@dataclass(frozen=True)
class GateResult:
    """An accepted sample, and the clock jump that reset its tool's history (or None)."""

    sample: TrackerSample
    clock_jump: ClockJump | None = None


class SampleGate:
    """Stateful acceptance of a tool's sample stream.

    :meth:`check` raises a named error for a sample that must be dropped and
    remembers each accepted one (per tool) as the reference for the next.

    Args:
        limits: the speed limits.
        back_tolerance_ns: a stamp more than this before its tool's newest is
            a clock jump (history reset); less is out of order (dropped).
            Default :data:`~endo_io.pose_buffer.POSE_JUMP_TOLERANCE_NS` (0: any
            step back is a restart; only a repeat of the newest stamp is dropped).
        forward_tolerance_ns: a stamp more than this after its tool's newest,
            without an equally long silence on the arrival clock, is dropped
            until the next sample confirms the jump.
    """

    def __init__(
        self,
        limits: SpeedLimits | None = None,
        *,
        back_tolerance_ns: int = POSE_JUMP_TOLERANCE_NS,
        forward_tolerance_ns: int = DEFAULT_FORWARD_TOLERANCE_NS,
    ) -> None:
        self.limits = limits or SpeedLimits()
        self.back_tolerance_ns = back_tolerance_ns
        self.forward_tolerance_ns = forward_tolerance_ns
        self._last: dict[str, TrackerSample] = {}
        self._clocks: dict[str, ClockJumpDetector] = {}

    def reset(self) -> None:
        """Forget the history (e.g. after a reconnection to a restarted tracker)."""
        self._last.clear()
        self._clocks.clear()

    def check(self, sample: TrackerSample, arrival_ns: int | None = None) -> TrackerSample:
        """Return ``sample`` if it is acceptable, else raise (see :meth:`admit`)."""
        return self.admit(sample, arrival_ns).sample

    def admit(self, sample: TrackerSample, arrival_ns: int | None = None) -> GateResult:
        """Accept ``sample`` (with the clock jump it revealed, if any), or raise.

        Args:
            sample: the tracker sample.
            arrival_ns: ``time.monotonic_ns()`` when it arrived; None: judge
                by stamps alone.

        Raises:
            ToolNotVisibleError, NonFinitePoseError, SpeedLimitError;
            TimeWentBackwardsError: at the tool's newest stamp (or before it within
                a non-zero ``back_tolerance_ns``);
            FutureStampError: far after it, not yet confirmed by a later sample.
        """
        if sample.status is not ToolStatus.VISIBLE:
            raise ToolNotVisibleError(f"tool '{sample.tool_id}' reported {sample.status.value}")
        check_finite(sample.T_tracker_marker, f"pose of tool '{sample.tool_id}'")
        clock = self._clocks.get(sample.tool_id)
        if clock is None:
            clock = self._clocks[sample.tool_id] = ClockJumpDetector(
                back_tolerance_ns=self.back_tolerance_ns,
                forward_tolerance_ns=self.forward_tolerance_ns,
            )
        try:
            # committed below, once the speed check has passed too
            jump = clock.check(sample.stamp_ns, arrival_ns, commit=False)
        except FutureStampError as error:
            raise FutureStampError(f"tool '{sample.tool_id}' {error}") from None
        except StampOrderError as error:
            raise TimeWentBackwardsError(f"tool '{sample.tool_id}' {error}") from None
        previous = None if jump is not None else self._last.get(sample.tool_id)
        if previous is not None and sample.stamp_ns > previous.stamp_ns:
            dt_s = (sample.stamp_ns - previous.stamp_ns) * 1e-9
            distance_m = float(np.linalg.norm(sample.translation_m - previous.translation_m))
            if distance_m / dt_s > self.limits.linear_m_s:
                raise SpeedLimitError(
                    f"tool '{sample.tool_id}' moved {distance_m * 1e3:.1f} mm "
                    f"in {dt_s * 1e3:.1f} ms "
                    f"({distance_m / dt_s:.2f} m/s > limit {self.limits.linear_m_s:g} m/s)"
                    + millimetres_hint(sample.translation_m)
                )
            angle_deg = math.degrees(rotation_angle(previous.rotation.T @ sample.rotation))
            if angle_deg / dt_s > self.limits.angular_deg_s:
                raise SpeedLimitError(
                    f"tool '{sample.tool_id}' turned {angle_deg:.1f}° in {dt_s * 1e3:.1f} ms "
                    f"({angle_deg / dt_s:.0f}°/s > limit {self.limits.angular_deg_s:g}°/s)"
                )
        clock.adopt(sample.stamp_ns, arrival_ns)
        self._last[sample.tool_id] = sample
        return GateResult(sample, jump)
