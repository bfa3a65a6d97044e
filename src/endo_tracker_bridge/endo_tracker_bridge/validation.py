"""Rejection of bad tracker samples.

Two kinds of checks:

* checks of one raw measurement (:func:`check_finite`,
  :func:`check_unit_quaternion`, :func:`check_rotation_matrix`), run by the
  sources while converting, before a quaternion or matrix is trusted;
* checks against the stream's history (:class:`SampleGate`): the tool must be
  visible, time must go forwards, and the marker must not move faster than a
  hand can move an endoscope. A jump beyond that speed is a tracking glitch
  (a reflection taken for a marker sphere, a swapped tool), not motion.

Each failure raises its own :mod:`endo_tracker_bridge.errors` class with a
one-line message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from endo_io.errors import PoseError
from endo_io.pose import DEFAULT_TOLERANCE, check_rotation, rotation_angle, unit_quaternion
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


@dataclass(frozen=True)
class SpeedLimits:
    """Largest plausible motion of the marker between two accepted samples.

    ``linear_m_s`` is in metres per second, ``angular_deg_s`` in degrees per
    second; ``math.inf`` disables a limit.
    """

    linear_m_s: float = 2.0
    angular_deg_s: float = 720.0


class SampleGate:
    """Stateful acceptance of a tool's sample stream.

    :meth:`check` raises a named error for a sample that must be dropped and
    remembers each accepted one (per tool) as the reference for the next.
    """

    def __init__(self, limits: SpeedLimits | None = None) -> None:
        self.limits = limits or SpeedLimits()
        self._last: dict[str, TrackerSample] = {}

    def reset(self) -> None:
        """Forget the history (e.g. after a reconnection to a restarted tracker)."""
        self._last.clear()

    def check(self, sample: TrackerSample) -> TrackerSample:
        """Return ``sample`` if it is acceptable, else raise.

        Raises :class:`ToolNotVisibleError`, :class:`NonFinitePoseError`,
        :class:`TimeWentBackwardsError` or :class:`SpeedLimitError`.
        """
        if sample.status is not ToolStatus.VISIBLE:
            raise ToolNotVisibleError(f"tool '{sample.tool_id}' reported {sample.status.value}")
        check_finite(sample.T_tracker_marker, f"pose of tool '{sample.tool_id}'")
        previous = self._last.get(sample.tool_id)
        if previous is not None:
            dt_ns = sample.stamp_ns - previous.stamp_ns
            if dt_ns <= 0:
                raise TimeWentBackwardsError(
                    f"tool '{sample.tool_id}' stamp {sample.stamp_ns} ns is {-dt_ns} ns "
                    f"before or at the previous {previous.stamp_ns} ns"
                )
            dt_s = dt_ns * 1e-9
            distance_m = float(np.linalg.norm(sample.translation_m - previous.translation_m))
            if distance_m / dt_s > self.limits.linear_m_s:
                raise SpeedLimitError(
                    f"tool '{sample.tool_id}' moved {distance_m * 1e3:.1f} mm "
                    f"in {dt_s * 1e3:.1f} ms "
                    f"({distance_m / dt_s:.2f} m/s > limit {self.limits.linear_m_s:g} m/s)"
                )
            angle_deg = math.degrees(rotation_angle(previous.rotation.T @ sample.rotation))
            if angle_deg / dt_s > self.limits.angular_deg_s:
                raise SpeedLimitError(
                    f"tool '{sample.tool_id}' turned {angle_deg:.1f}° in {dt_s * 1e3:.1f} ms "
                    f"({angle_deg / dt_s:.0f}°/s > limit {self.limits.angular_deg_s:g}°/s)"
                )
        self._last[sample.tool_id] = sample
        return sample
