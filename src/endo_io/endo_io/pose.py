"""Rigid transforms: ``geometry_msgs/PoseStamped`` <-> 4x4 matrices, quaternions, SLERP.

Conventions:

* Quaternions are ``(x, y, z, w)`` (the ROS message order, and scipy's
  ``Rotation.as_quat`` order). A rotation has two quaternions, ``q`` and
  ``-q``; functions here return the canonical one with ``w >= 0`` (and, when
  ``w == 0``, the first non-zero component positive).
* A transform ``T`` (4, 4) float64 maps points from the pose's child frame into
  ``header.frame_id``: ``p_parent = T[:3, :3] @ p_child + T[:3, 3]``, metres.
* Time is integer nanoseconds (:mod:`endo_io.stamp`).

Every input rotation is checked: a NaN, a quaternion whose norm is further
than ``tolerance`` from 1, or a matrix that is not a rotation raises
:class:`PoseError`. Accepted quaternions are normalised before use.

Interpolation between stamped transforms (linear translation, SLERP rotation)
has one vectorised core, shared by :func:`slerp`, the scalar
:func:`interpolate_transform` and the batched :func:`interpolate_transforms`.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseStamped
from numpy.typing import ArrayLike
from std_msgs.msg import Header

from endo_io.cdr import LITTLE_ENDIAN_ENCAPSULATION, CdrReader, cdr_string, decode_plain_cdr
from endo_io.errors import PoseError
from endo_io.stamp import NS_PER_S, ns_to_stamp, stamp_to_ns

#: Default allowed deviation of a quaternion's norm from 1, and of a rotation
#: matrix's ``R.T @ R`` from the identity (max abs element).
DEFAULT_TOLERANCE = 1e-3

# Below this angle between two quaternions SLERP's sin(theta) denominator loses
# precision; linear interpolation is then exact to O(theta^2) ~ 1e-18.
_SLERP_LINEAR_BELOW_RAD = 1e-9


def unit_quaternion(q_xyzw: np.ndarray, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """Validate (..., 4) quaternions x, y, z, w and return them normalised.

    Args:
        q_xyzw: (..., 4) quaternions.
        tolerance: allowed deviation of each norm from 1.

    Returns:
        (..., 4) float64 unit quaternions, same sign and component order.

    Raises:
        PoseError: wrong shape, NaN/inf, or a norm further than ``tolerance``
            from 1.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise PoseError(f"quaternion must have shape (..., 4) x,y,z,w, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise PoseError("quaternion contains NaN or infinity")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    deviation = np.abs(norm - 1.0)
    worst = int(np.argmax(deviation)) if norm.size else 0
    if norm.size and deviation.flat[worst] > tolerance:
        raise PoseError(
            f"quaternion norm deviates from 1 by {deviation.flat[worst]:.3g} > tolerance "
            f"{tolerance:g} (norm {norm.flat[worst]:.6f})"
        )
    return q / norm


def canonical_quaternion(q_xyzw: np.ndarray) -> np.ndarray:
    """Return (..., 4) quaternions flipped to the sign with ``w >= 0``.

    When ``w == 0`` (a half turn) the first non-zero of x, y, z is made
    positive, so that equal rotations always give equal quaternions.
    """
    q = np.array(q_xyzw, dtype=np.float64)
    w = q[..., 3:4]
    if np.all(w != 0.0):  # the usual case: the sign of w decides
        return q * np.where(w < 0.0, -1.0, 1.0)
    # index of the first non-zero component in the order w, x, y, z
    ordered = np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)
    first = np.argmax(ordered != 0.0, axis=-1)[..., None]
    sign = np.where(np.take_along_axis(ordered, first, axis=-1) < 0.0, -1.0, 1.0)
    return q * sign


def quaternion_to_matrix(q_xyzw: np.ndarray, *, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """Return the rotation matrix of a unit quaternion.

    Args:
        q_xyzw: (4,) or (..., 4) quaternion(s) x, y, z, w.
        tolerance: allowed deviation of the norm from 1.

    Returns:
        (3, 3) or (..., 3, 3) float64 rotation matrix.

    Raises:
        PoseError: NaN/inf or a norm further than ``tolerance`` from 1.
    """
    return _rotation_of_unit_quaternion(unit_quaternion(q_xyzw, tolerance))


def _rotation_of_unit_quaternion(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions x, y, z, w (not checked) -> (..., 3, 3) rotations."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    # filled element by element: a third of stacking the rows for one quaternion (a
    # tracker pose at a time), half for a batch; the same operations, the same bits
    R = np.empty((*q.shape[:-1], 3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (yy + zz)
    R[..., 0, 1] = 2.0 * (xy - wz)
    R[..., 0, 2] = 2.0 * (xz + wy)
    R[..., 1, 0] = 2.0 * (xy + wz)
    R[..., 1, 1] = 1.0 - 2.0 * (xx + zz)
    R[..., 1, 2] = 2.0 * (yz - wx)
    R[..., 2, 0] = 2.0 * (xz - wy)
    R[..., 2, 1] = 2.0 * (yz + wx)
    R[..., 2, 2] = 1.0 - 2.0 * (xx + yy)
    return R


def check_rotation(R: np.ndarray, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """Validate (..., 3, 3) rotation matrices and return them as float64.

    Raises:
        PoseError: wrong shape, NaN/inf, ``max |RᵀR − I| > tolerance``, or a
            reflection (det <= 0).
    """
    rot = np.asarray(R, dtype=np.float64)
    if rot.shape[-2:] != (3, 3):
        raise PoseError(f"rotation matrix must have shape (..., 3, 3), got {rot.shape}")
    if not np.all(np.isfinite(rot)):
        raise PoseError("rotation matrix contains NaN or infinity")
    gram = np.swapaxes(rot, -1, -2) @ rot
    off = float(np.max(np.abs(gram - np.eye(3)))) if rot.size else 0.0
    if off > tolerance:
        raise PoseError(f"matrix is not orthonormal: |R^T R - I| = {off:.3g} > {tolerance:g}")
    if rot.size and float(np.min(np.linalg.det(rot))) <= 0.0:
        raise PoseError("matrix is a reflection (determinant <= 0), not a rotation")
    return rot


def matrix_to_quaternion(R: np.ndarray, *, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """Return the canonical unit quaternion of a rotation matrix.

    Args:
        R: (3, 3) or (..., 3, 3) rotation matrix (a 4x4 transform's
            ``T[:3, :3]``).
        tolerance: allowed max abs deviation of ``R.T @ R`` from identity.

    Returns:
        (4,) or (..., 4) float64 quaternion x, y, z, w with ``w >= 0``.

    Raises:
        PoseError: NaN/inf, not orthonormal within ``tolerance``, or det <= 0.
    """
    return _quaternion_of_rotation(check_rotation(R, tolerance))


def _quaternion_of_rotation(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations (not checked) -> (..., 4) canonical quaternions x, y, z, w."""
    m00, m01, m02 = rot[..., 0, 0], rot[..., 0, 1], rot[..., 0, 2]
    m10, m11, m12 = rot[..., 1, 0], rot[..., 1, 1], rot[..., 1, 2]
    m20, m21, m22 = rot[..., 2, 0], rot[..., 2, 1], rot[..., 2, 2]
    # Shepperd's method: build the quaternion from whichever of 4w^2, 4x^2,
    # 4y^2, 4z^2 is largest, so the divisor is never close to zero.
    t0 = 1.0 + m00 - m11 - m22
    t1 = 1.0 - m00 + m11 - m22
    t2 = 1.0 - m00 - m11 + m22
    t3 = 1.0 + m00 + m11 + m22
    s01, s02, s12 = m01 + m10, m02 + m20, m12 + m21
    d21, d02, d10 = m21 - m12, m02 - m20, m10 - m01
    # the four candidates as rows of one (..., 4, 4) array, built by one stack
    candidates = np.stack(
        [t0, s01, s02, d21, s01, t1, s12, d02, s02, s12, t2, d10, d21, d02, d10, t3], axis=-1
    ).reshape(*rot.shape[:-2], 4, 4)
    best = np.argmax(candidates[..., (0, 1, 2, 3), (0, 1, 2, 3)], axis=-1)[..., None, None]
    q = np.take_along_axis(candidates, best, axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return canonical_quaternion(q)


def _check_transform(T: np.ndarray, tolerance: float, name: str = "transform") -> np.ndarray:
    mat = np.asarray(T, dtype=np.float64)
    if mat.shape != (4, 4):
        raise PoseError(f"{name} must have shape (4, 4), got {mat.shape}")
    if not np.all(np.isfinite(mat)):
        raise PoseError(f"{name} contains NaN or infinity")
    if not np.array_equal(mat[3], [0.0, 0.0, 0.0, 1.0]):
        raise PoseError(f"{name} bottom row must be [0, 0, 0, 1], got {mat[3].tolist()}")
    check_rotation(mat[:3, :3], tolerance)
    return mat


@dataclass(frozen=True)
class PoseView:
    """A ``geometry_msgs/PoseStamped`` read from its CDR bytes (:func:`pose_stamped_from_cdr`).

    Attributes:
        header: the message's header (stamp, frame_id).
        position: (x, y, z), metres, as the message holds them.
        orientation: (x, y, z, w), the quaternion as the message holds it
            (not checked nor normalised: :func:`pose_to_matrix` does that).
    """

    header: Header
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]


def pose_stamped_from_cdr(data: bytes) -> PoseStamped | PoseView:
    """Decode a serialized ``geometry_msgs/PoseStamped`` without rclpy's message objects.

    The same values as rclpy's ``deserialize_message(data, PoseStamped)``
    (tested against it), read with :class:`endo_io.cdr.CdrReader`: about a
    quarter of its cost (0.009 against 0.034 ms here). Layout:
    the header, padding to 8, seven float64 (position x, y, z, orientation
    x, y, z, w). :func:`pose_to_matrix` takes the result as it takes a
    message, with the same checks.

    Args:
        data: the serialized message, its 4-byte encapsulation header first.

    Returns:
        A :class:`PoseView`, or a ``PoseStamped`` for another encapsulation
        than plain CDR (given to rclpy, :func:`endo_io.cdr.decode_plain_cdr`).

    Raises:
        UndecodableMessageError: not CDR, or the bytes end before a field does.
    """
    return decode_plain_cdr(data, PoseStamped, _read_pose)


def _read_pose(cdr: CdrReader) -> PoseView:
    header = cdr.header()
    values = cdr.float64s(7, "pose")
    return PoseView(header, values[:3], values[3:])  # type: ignore[arg-type]


def pose_to_matrix(
    msg: PoseStamped | PoseView, *, tolerance: float = DEFAULT_TOLERANCE
) -> tuple[np.ndarray, int]:
    """Return a ``PoseStamped`` as a (4, 4) float64 transform and its stamp in ns.

    The quaternion is normalised before conversion; positions are metres.

    Args:
        msg: the message, or a :class:`PoseView` of its bytes.
        tolerance: allowed deviation of the quaternion's norm from 1.

    Raises:
        PoseError: NaN/inf in position or orientation, or a quaternion whose
            norm is further than ``tolerance`` from 1.
    """
    if isinstance(msg, PoseView):
        position = np.array(msg.position, dtype=np.float64)
        q = np.array(msg.orientation, dtype=np.float64)
    else:
        p, o = msg.pose.position, msg.pose.orientation
        position = np.array([p.x, p.y, p.z], dtype=np.float64)
        q = np.array([o.x, o.y, o.z, o.w])
    if not np.all(np.isfinite(position)):
        raise PoseError(f"pose position is not finite: {position.tolist()}")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q, tolerance=tolerance)
    T[:3, 3] = position
    return T, stamp_to_ns(msg.header.stamp)


def matrix_to_pose(
    T: np.ndarray, stamp_ns: int, frame_id: str, *, tolerance: float = DEFAULT_TOLERANCE
) -> PoseStamped:
    """Return a (4, 4) rigid transform as a ``PoseStamped``.

    Args:
        T: (4, 4) transform, child frame to ``frame_id``, metres.
        stamp_ns: header stamp, integer nanoseconds (>= 0).
        frame_id: header frame id (the parent frame).
        tolerance: allowed deviation of ``T[:3, :3]`` from a rotation.

    Raises:
        PoseError: wrong shape, NaN/inf, bottom row not [0, 0, 0, 1], not a
            rotation, or a negative stamp.
    """
    mat = _check_transform(T, tolerance)
    if stamp_ns < 0:
        raise PoseError(f"stamp must be non-negative, got {stamp_ns} ns")
    q = matrix_to_quaternion(mat[:3, :3], tolerance=tolerance)
    msg = PoseStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    position, orientation = msg.pose.position, msg.pose.orientation
    position.x, position.y, position.z = (float(v) for v in mat[:3, 3])
    orientation.x, orientation.y, orientation.z, orientation.w = (float(v) for v in q)
    return msg


def transforms_to_pose_stamped_cdr(
    T: np.ndarray, stamps_ns: Sequence[int], frame_id: str, *, tolerance: float = DEFAULT_TOLERANCE
) -> tuple[list[bytes], np.ndarray]:
    """Many transforms as serialised ``PoseStamped`` messages at once, and what a reader gets back.

    For each ``T[k]``: the bytes :func:`endo_io.bag.serde.serialize` gives for
    ``matrix_to_pose(T[k], stamps_ns[k], frame_id)`` (little-endian CDR, every
    padding byte zero), and the transform :func:`pose_to_matrix` makes of that
    message, equal bit for bit (tested): the quaternions come from one batched
    :func:`matrix_to_quaternion` instead of one call per pose, which is most of
    the cost of converting a tracker stream pose by pose.

    Layout (alignment counted from the end of the 4-byte encapsulation
    header): int32 sec, uint32 nanosec, frame_id (uint32 length with the NUL,
    bytes, NUL), zero padding to 8, seven float64 (position x, y, z,
    orientation x, y, z, w).

    Args:
        T: (K, 4, 4) rigid transforms, child frame to ``frame_id``, metres.
        stamps_ns: K header stamps, integer ns (>= 0).
        frame_id: the header frame of every message.
        tolerance: as :func:`matrix_to_pose`.

    Returns:
        (K messages' bytes, (K, 4, 4) float64 transforms as read back).

    Raises:
        PoseError: as :func:`matrix_to_pose` for any of the transforms.
    """
    mat = _check_transforms(T, tolerance, "transforms")
    stamps = [int(stamp) for stamp in stamps_ns]
    if len(stamps) != len(mat):
        raise PoseError(f"{len(stamps)} stamps but {len(mat)} transforms")
    if any(stamp < 0 for stamp in stamps):
        raise PoseError(f"stamps must be non-negative, got {min(stamps)} ns")
    q = _quaternion_of_rotation(mat[:, :3, :3])
    position = mat[:, :3, 3]
    read_back = np.zeros_like(mat)
    read_back[:, :3, :3] = quaternion_to_matrix(q, tolerance=tolerance)
    read_back[:, :3, 3] = position
    read_back[:, 3, 3] = 1.0
    head = cdr_string(frame_id, 8)  # after the stamp: 4-aligned already
    head += bytes(-(8 + len(head)) % 8)
    values = np.concatenate([position, q], axis=1).tolist()
    data = [
        b"".join((LITTLE_ENDIAN_ENCAPSULATION, struct.pack("<iI", *divmod(stamp, NS_PER_S)), head,
                  struct.pack("<7d", *row)))
        for stamp, row in zip(stamps, values, strict=True)
    ]  # fmt: skip
    return data, read_back


def slerp(
    q0_xyzw: np.ndarray,
    q1_xyzw: np.ndarray,
    alpha: float | np.ndarray,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
) -> np.ndarray:
    """Spherical linear interpolation between two rotations, shortest path.

    Args:
        q0_xyzw: (4,) start quaternion x, y, z, w (``alpha = 0``).
        q1_xyzw: (4,) end quaternion (``alpha = 1``); ``q1`` and ``-q1`` give
            the same result (the shorter arc is always taken).
        alpha: scalar or (N,) interpolation fraction; values outside [0, 1]
            extrapolate along the same great circle.
        tolerance: allowed deviation of the input norms from 1.

    Returns:
        (4,) or (N, 4) float64 canonical unit quaternion(s), ``w >= 0``.

    Raises:
        PoseError: NaN/inf or a non-unit input quaternion.
    """
    q0 = unit_quaternion(q0_xyzw, tolerance)
    q1 = unit_quaternion(q1_xyzw, tolerance)
    if q0.shape != (4,) or q1.shape != (4,):
        raise PoseError(f"slerp needs two (4,) quaternions, got {q0.shape} and {q1.shape}")
    return _slerp_unit(q0, q1, alpha)


def _slerp_unit(q0: np.ndarray, q1: np.ndarray, alpha: float | np.ndarray) -> np.ndarray:
    """SLERP of unit quaternions (not checked), broadcast over leading axes.

    ``q0``, ``q1``: (..., 4) x, y, z, w; ``alpha``: scalar or (...,)
    fractions broadcastable with their leading axes. Each pair takes its own
    shorter arc. Returns (..., 4) canonical unit quaternions. The one SLERP
    of this module: :func:`slerp` and both interpolations call it.
    """
    a = np.asarray(alpha, dtype=np.float64)[..., None]
    q1 = np.where(np.sum(q0 * q1, axis=-1, keepdims=True) < 0.0, -q1, q1)
    # The angle between the two quaternions (half the rotation between them);
    # atan2 of chord lengths stays accurate for nearly identical quaternions,
    # where acos(dot) does not.
    theta = 2.0 * np.arctan2(
        np.linalg.norm(q1 - q0, axis=-1, keepdims=True),
        np.linalg.norm(q1 + q0, axis=-1, keepdims=True),
    )
    linear = theta < _SLERP_LINEAR_BELOW_RAD
    sin_theta = np.where(linear, 1.0, np.sin(theta))  # no 0/0 where it is not used
    spherical = (np.sin((1.0 - a) * theta) * q0 + np.sin(a * theta) * q1) / sin_theta
    q = np.where(linear, (1.0 - a) * q0 + a * q1, spherical)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return canonical_quaternion(q)


def interpolate_rigid(T0: np.ndarray, T1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Transforms at fraction ``alpha`` between rigid transforms already checked.

    Linear translation, SLERP rotation; ``alpha`` outside [0, 1] extrapolates.
    The core of :func:`interpolate_transform` and :func:`interpolate_transforms`,
    for a caller that validated its transforms once (a pose buffer at insert).

    Args:
        T0, T1: (N, 4, 4) float64 rigid transforms (not checked), metres.
        alpha: (N,) float64 fractions (0 gives ``T0``'s pose, 1 ``T1``'s).

    Returns:
        (N, 4, 4) float64 transforms.
    """
    q = _slerp_unit(
        _quaternion_of_rotation(T0[:, :3, :3]), _quaternion_of_rotation(T1[:, :3, :3]), alpha
    )
    a = alpha[:, None]
    T = np.zeros((len(alpha), 4, 4))
    T[:, :3, :3] = _rotation_of_unit_quaternion(q)
    T[:, :3, 3] = (1.0 - a) * T0[:, :3, 3] + a * T1[:, :3, 3]
    T[:, 3, 3] = 1.0
    return T


def interpolate_transform(
    T0: np.ndarray,
    t0_ns: int,
    T1: np.ndarray,
    t1_ns: int,
    t_ns: int,
    *,
    extrapolate: bool = False,
    tolerance: float = DEFAULT_TOLERANCE,
) -> np.ndarray:
    """Interpolate a rigid transform at time ``t_ns`` between two stamped ones.

    Translation is interpolated linearly, rotation by SLERP (shortest arc),
    both with the fraction ``(t_ns - t0_ns) / (t1_ns - t0_ns)``.

    Args:
        T0, T1: (4, 4) rigid transforms (metres) at ``t0_ns`` and ``t1_ns``.
        t0_ns, t1_ns, t_ns: integer nanoseconds, ``t0_ns != t1_ns``.
        extrapolate: allow ``t_ns`` outside [t0_ns, t1_ns] (default: error).
        tolerance: allowed deviation of the rotations from orthonormal.

    Returns:
        (4, 4) float64 transform; exactly ``T0`` at ``t0_ns`` and ``T1`` at
        ``t1_ns``.

    Raises:
        PoseError: invalid transforms, ``t0_ns == t1_ns``, or ``t_ns`` outside
            the interval without ``extrapolate``.
    """
    A = _check_transform(T0, tolerance, "T0")
    B = _check_transform(T1, tolerance, "T1")
    if t0_ns == t1_ns:
        raise PoseError(f"cannot interpolate between two transforms at the same time {t0_ns} ns")
    if not extrapolate and not min(t0_ns, t1_ns) <= t_ns <= max(t0_ns, t1_ns):
        raise PoseError(f"time {t_ns} ns is outside [{t0_ns}, {t1_ns}] ns; extrapolate=False")
    if t_ns == t0_ns:
        return A.copy()
    if t_ns == t1_ns:
        return B.copy()
    alpha = (int(t_ns) - int(t0_ns)) / (int(t1_ns) - int(t0_ns))  # exact int difference
    return interpolate_rigid(A[None], B[None], np.array([alpha]))[0]


def _check_transforms(T: np.ndarray, tolerance: float, name: str) -> np.ndarray:
    """Validate (M, 4, 4) rigid transforms; return them as float64."""
    mat = np.asarray(T, dtype=np.float64)
    if mat.ndim != 3 or mat.shape[1:] != (4, 4):
        raise PoseError(f"{name} must have shape (M, 4, 4), got {mat.shape}")
    if not np.all(np.isfinite(mat)):
        raise PoseError(f"{name} contain NaN or infinity")
    if not np.array_equal(mat[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(mat), 4))):
        raise PoseError(f"{name}: every bottom row must be [0, 0, 0, 1]")
    check_rotation(mat[:, :3, :3], tolerance)
    return mat


def _integer_stamps(stamps: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(stamps)
    if array.ndim != 1:
        raise PoseError(f"{name} must have shape (N,), got {array.shape}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise PoseError(f"{name} must be integer nanoseconds, got dtype {array.dtype}")
    return array.astype(np.int64)


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (...,4,4) float64 (Rᵀ, −Rᵀt), without a general inverse."""
    T = np.asarray(T, dtype=np.float64)
    inverse = np.zeros_like(T)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    inverse[..., :3, :3] = R_t
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def interpolate_transforms(
    stamps_ns: np.ndarray,
    poses: np.ndarray,
    query_ns: np.ndarray,
    max_gap_ns: int,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate a stamped stream of rigid transforms at many times at once.

    Each query is interpolated between the last sample at or before it and
    the first sample after it, exactly as :func:`interpolate_transform` does
    for one pair (linear translation, shortest-arc SLERP rotation).

    Args:
        stamps_ns: (M,) integer nanoseconds, sorted (non-decreasing; of equal
            stamps the last sample counts).
        poses: (M, 4, 4) rigid transforms (metres) at ``stamps_ns``.
        query_ns: (N,) integer nanoseconds, any order.
        max_gap_ns: longest interval between the two samples around a query
            that is bridged, ns (>= 0).
        tolerance: allowed deviation of the rotations from orthonormal.

    Returns:
        ((N, 4, 4) float64 transforms, NaN where invalid; (N,) bool valid).
        A query is valid when it equals a sample's stamp (then the result is
        that sample's transform exactly) or lies between two samples at most
        ``max_gap_ns`` apart; queries outside the stream or in a longer gap
        are invalid (never extrapolated).

    Raises:
        PoseError: wrong shapes or dtypes, unsorted stamps, a negative
            ``max_gap_ns``, or invalid transforms.
    """
    stamps = _integer_stamps(stamps_ns, "stamps_ns")
    query = _integer_stamps(query_ns, "query_ns")
    samples = _check_transforms(poses, tolerance, "poses")
    if len(samples) != len(stamps):
        raise PoseError(f"{len(stamps)} stamps but {len(samples)} poses")
    if np.any(np.diff(stamps) < 0):
        raise PoseError("stamps_ns must be sorted (non-decreasing)")
    if max_gap_ns < 0:
        raise PoseError(f"max_gap_ns must be >= 0, got {max_gap_ns}")
    result = np.full((len(query), 4, 4), np.nan)
    if len(stamps) == 0:
        return result, np.zeros(len(query), dtype=bool)
    after = np.searchsorted(stamps, query, side="right")
    before = after - 1
    b, a = np.clip(before, 0, len(stamps) - 1), np.clip(after, 0, len(stamps) - 1)
    exact = (before >= 0) & (stamps[b] == query)
    between = ~exact & (before >= 0) & (after < len(stamps))
    between[between] = (stamps[a[between]] - stamps[b[between]]) <= max_gap_ns
    result[exact] = samples[b[exact]]
    if np.any(between):
        b, a, t = b[between], a[between], query[between]
        alpha = (t - stamps[b]) / (stamps[a] - stamps[b])  # exact int64 differences
        result[between] = interpolate_rigid(samples[b], samples[a], alpha)
    return result, exact | between


def rigid_transform(rotvec: ArrayLike, translation: ArrayLike) -> np.ndarray:
    """Build a rigid transform from a rotation vector and a translation.

    Args:
        rotvec: (3,) axis × angle, radians (scipy's ``Rotation.from_rotvec``).
        translation: (3,) metres (or whatever unit the caller's points use).

    Returns:
        (4, 4) float64 transform ``[[R, t], [0, 0, 0, 1]]``.

    Raises:
        PoseError: a wrong shape or a non-finite value.
    """
    axis_angle = np.asarray(rotvec, dtype=np.float64)
    offset = np.asarray(translation, dtype=np.float64)
    if axis_angle.shape != (3,) or offset.shape != (3,):
        raise PoseError(
            f"rotvec and translation must have shape (3,), got {axis_angle.shape} "
            f"and {offset.shape}"
        )
    if not (np.all(np.isfinite(axis_angle)) and np.all(np.isfinite(offset))):
        raise PoseError("rotvec or translation contains NaN or infinity")
    T = np.eye(4)
    # Rodrigues' formula; below 1e-12 rad the rotation is the identity to
    # double precision.
    angle = float(np.linalg.norm(axis_angle))
    if angle > 1e-12:
        k = axis_angle / angle
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        T[:3, :3] = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)
    T[:3, 3] = offset
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a rigid transform to points: ``R @ p + t`` for every point.

    Args:
        T: (4, 4) rigid transform from the points' frame to the target frame.
        points: (..., 3) points, e.g. (N, 3) or an (H, W, 3) image of points;
            NaN points stay NaN.

    Returns:
        (..., 3) float64 points in the target frame (a float32 input gives a
        float64 output; cast back where the memory matters).

    Raises:
        PoseError: ``T`` not (4, 4) or ``points`` not (..., 3).
    """
    mat = np.asarray(T, dtype=np.float64)
    if mat.shape != (4, 4):
        raise PoseError(f"transform must have shape (4, 4), got {mat.shape}")
    xyz = np.asarray(points)
    if xyz.shape[-1:] != (3,):
        raise PoseError(f"points must have shape (..., 3), got {xyz.shape}")
    return xyz @ mat[:3, :3].T + mat[:3, 3]


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle of (..., 3, 3) rotation matrices, radians in [0, π].

    Computed as ``atan2(|vee(R − Rᵀ)| / 2, (tr R − 1) / 2)``, which stays
    accurate for angles near 0 and near π, where ``acos`` of the trace does
    not. Returns a float64 scalar array for one matrix, (...,) for many.
    The matrices are not checked (:func:`check_rotation` does that).
    """
    rot = np.asarray(R, dtype=np.float64)
    if rot.shape[-2:] != (3, 3):
        raise PoseError(f"rotation matrix must have shape (..., 3, 3), got {rot.shape}")
    skew = np.stack(
        [
            rot[..., 2, 1] - rot[..., 1, 2],
            rot[..., 0, 2] - rot[..., 2, 0],
            rot[..., 1, 0] - rot[..., 0, 1],
        ],
        axis=-1,
    )
    sin_angle = 0.5 * np.linalg.norm(skew, axis=-1)
    cos_angle = 0.5 * (np.trace(rot, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin_angle, cos_angle)


def motion_onset(positions: np.ndarray, distance_m: float) -> int | None:
    """Index of the first position at least ``distance_m`` from the first one.

    Args:
        positions: (K, 3) positions along a trajectory, metres, in time order
            (e.g. ``T_world_camera[:, :3, 3]``).
        distance_m: the straight-line distance from ``positions[0]``, metres.

    Returns:
        The index, or None when the trajectory never gets that far (or is empty).

    Raises:
        PoseError: ``positions`` not (K, 3), or ``distance_m`` negative or not finite.
    """
    xyz = np.asarray(positions, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise PoseError(f"positions must have shape (K, 3), got {xyz.shape}")
    if not np.isfinite(distance_m) or distance_m < 0.0:
        raise PoseError(f"distance must be finite and >= 0, got {distance_m}")
    if len(xyz) == 0:
        return None
    far = np.linalg.norm(xyz - xyz[0], axis=1) >= distance_m
    return int(np.argmax(far)) if far.any() else None
