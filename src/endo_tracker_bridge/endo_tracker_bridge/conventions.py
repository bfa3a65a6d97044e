"""Units and quaternion orders trackers use, and conversion to the bridge's own.

The bridge's convention (REP 103, geometry_msgs): metres, quaternions as
(x, y, z, w), 4x4 homogeneous transforms with the translation in the last
column. Trackers differ:

* NDI Polaris/Vega (and scikit-surgerynditracker): millimetres, quaternions
  w-first (q0, qx, qy, qz);
* OpenIGTLink TRANSFORM (PLUS, 3D Slicer): a 3x4 matrix in millimetres;
* ROS drivers: PoseStamped in metres or, for some, millimetres.
"""

from __future__ import annotations

import enum

import numpy as np

from endo_io.pose import quaternion_to_matrix
from endo_tracker_bridge.errors import TrackerSourceError
from endo_tracker_bridge.validation import (
    DEFAULT_ROTATION_TOLERANCE,
    check_finite,
    check_rotation_matrix,
    check_unit_quaternion,
)


class LengthUnit(enum.Enum):
    """Length unit of a tracker's translations."""

    METRE = "m"
    MILLIMETRE = "mm"

    @property
    def metres_per_unit(self) -> float:
        """Factor that turns a length in this unit into metres."""
        return 1.0 if self is LengthUnit.METRE else 1e-3

    @classmethod
    def parse(cls, text: str) -> LengthUnit:
        """``"m"`` or ``"mm"`` (case-insensitive) → unit; else :class:`TrackerSourceError`."""
        try:
            return cls(text.strip().lower())
        except ValueError:
            raise TrackerSourceError(
                f"unknown length unit '{text}' (expected 'm' or 'mm')"
            ) from None


def quaternion_wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    """Reorder a w-first quaternion (..., 4) (w, x, y, z) to (x, y, z, w)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def quaternion_xyzw_to_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """Reorder an (x, y, z, w) quaternion (..., 4) to w-first (w, x, y, z)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def transform_from_quaternion(
    q_xyzw: np.ndarray,
    translation: np.ndarray,
    unit: LengthUnit,
    tolerance: float = DEFAULT_ROTATION_TOLERANCE,
) -> np.ndarray:
    """Build a (4,4) float64 transform in metres from a quaternion and a translation.

    ``q_xyzw`` (4,) in (x, y, z, w) order must be unit within ``tolerance``
    (it is then normalised); ``translation`` (3,) is in ``unit``.
    Raises NonFinitePoseError / NonUnitQuaternionError.
    """
    t = np.asarray(translation, dtype=np.float64).reshape(3)
    check_finite(t, "translation")
    q = check_unit_quaternion(q_xyzw, tolerance)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q)
    T[:3, 3] = t * unit.metres_per_unit
    return T


def transform_from_matrix(
    matrix: np.ndarray, unit: LengthUnit, tolerance: float = DEFAULT_ROTATION_TOLERANCE
) -> np.ndarray:
    """Convert a (4,4) or (3,4) homogeneous matrix with translation in ``unit`` to metres.

    The rotation block must be orthonormal within ``tolerance`` (it is then
    projected exactly onto SO(3)). Returns (4,4) float64.
    Raises NonFinitePoseError / NonOrthonormalRotationError.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape not in ((4, 4), (3, 4)):
        raise TrackerSourceError(f"transform must be 4x4 or 3x4, got shape {m.shape}")
    check_finite(m, "transform")
    T = np.eye(4)
    T[:3, :3] = check_rotation_matrix(m[:3, :3], tolerance)
    T[:3, 3] = m[:3, 3] * unit.metres_per_unit
    return T
