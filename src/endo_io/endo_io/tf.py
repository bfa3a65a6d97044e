"""Transforms of the endo3d frame tree, and ``tf2_msgs/msg/TFMessage`` for recordings.

No tf2 package is needed: :func:`tf_message_definition` gives the complete
``ros2msg`` schema text of ``tf2_msgs/msg/TFMessage`` (its one-line ``.msg``
followed by the installed ``geometry_msgs/TransformStamped`` definition and
its dependencies, as rosbag2 writes it) and :func:`serialize_tf_message` its
canonical CDR bytes (little-endian XCDR1, every padding byte zero, padded to
4 bytes as DDS delivers a sample), so :class:`endo_io.bag.BagWriter` can
record ``/tf`` and ``/tf_static`` that Foxglove, ``rosbags``, ``ros2 bag`` and
mcap-ros2-support decode.

The frame tree (REP 103 frames of :mod:`endo_io.topics`)::

    world ──T_world_camera (per frame, /tf)──▶ endoscope_optical_frame
      │                                            │
      └─T_world_tracker (/tf_static)─▶ tracker     └─T_camera_marker (/tf_static)─▶ endoscope_marker

A tf tree gives every frame one parent. The camera's parent is ``world``
(its pose is what the graph publishes), so the hand–eye transform is
recorded from the optical frame to the marker, ``T_camera_marker =
inverse(T_marker_camera)``: the same rigid link, drawn from the side that
keeps the tree a tree.

A :class:`StampedTransform` maps points from ``child_frame`` into
``parent_frame`` (``p_parent = R @ p_child + t``, metres), which is what a
``TransformStamped`` with ``header.frame_id = parent`` and ``child_frame_id
= child`` means, and what Foxglove's ``FrameTransform`` means.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from endo_io.errors import Endo3dError
from endo_io.pose import invert_transform, matrix_to_quaternion, quaternion_to_matrix
from endo_io.stamp import NS_PER_S
from endo_io.topics import MARKER_FRAME, OPTICAL_FRAME, TF_STATIC, TRACKER_FRAME, WORLD_FRAME

if TYPE_CHECKING:
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import QoSProfile

    from endo_io.bag.msgdef import MessageDefinition
    from endo_io.bag.writer import BagWriter

#: Type name of a tf message.
TF_MESSAGE_TYPE = "tf2_msgs/msg/TFMessage"
#: ``tf2_msgs/msg/TFMessage.msg`` as the Jazzy package installs it.
TF_MESSAGE_MSG_TEXT = "geometry_msgs/TransformStamped[] transforms\n"
_TRANSFORM_STAMPED = "geometry_msgs/TransformStamped"  # as the .msg field names it

_CDR_LITTLE_ENDIAN_HEADER = b"\x00\x01\x00\x00"
_INT32_MAX = 2**31 - 1


class TransformError(Endo3dError, ValueError):
    """A transform cannot be recorded: not rigid, not finite, empty frame or bad stamp."""


@dataclass(frozen=True)
class StampedTransform:
    """One edge of the frame tree at one instant.

    Attributes:
        stamp_ns: Integer nanoseconds, 0 <= stamp < 2**31 s (int32 seconds of
            ``builtin_interfaces/Time``).
        parent_frame: ``header.frame_id``.
        child_frame: ``child_frame_id``.
        translation: (3,) float64 metres, the child origin in the parent frame.
        rotation: (4,) float64 unit quaternion x, y, z, w (w >= 0), child to parent.
    """

    stamp_ns: int
    parent_frame: str
    child_frame: str
    translation: np.ndarray
    rotation: np.ndarray

    @classmethod
    def from_matrix(
        cls, T_parent_child: np.ndarray, stamp_ns: int, parent_frame: str, child_frame: str
    ) -> StampedTransform:
        """Build an edge from a (4, 4) rigid transform (child → parent, metres).

        Raises:
            TransformError: not a finite rigid (4, 4) transform, an empty or
                equal frame name, or a stamp outside int32 seconds.
        """
        T = np.asarray(T_parent_child, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise TransformError(
                f"{parent_frame} -> {child_frame}: transform must be a finite (4, 4) matrix"
            )
        if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
            raise TransformError(
                f"{parent_frame} -> {child_frame}: bottom row must be [0, 0, 0, 1], "
                f"got {T[3].tolist()}"
            )
        try:
            rotation = matrix_to_quaternion(T[:3, :3])
        except ValueError as error:  # PoseError: not a rotation
            raise TransformError(f"{parent_frame} -> {child_frame}: {error}") from None
        edge = cls(int(stamp_ns), parent_frame, child_frame, T[:3, 3].copy(), rotation)
        edge.check()
        return edge

    def matrix(self) -> np.ndarray:
        """The (4, 4) float64 transform child → parent."""
        T = np.eye(4)
        T[:3, :3] = quaternion_to_matrix(self.rotation)
        T[:3, 3] = self.translation
        return T

    def check(self) -> None:
        """Raise :class:`TransformError` unless this edge can be recorded."""
        name = f"{self.parent_frame!r} -> {self.child_frame!r}"
        if not self.parent_frame or not self.child_frame:
            raise TransformError(f"transform {name}: frame names must not be empty")
        if self.parent_frame == self.child_frame:
            raise TransformError(f"transform {name}: a frame cannot be its own parent")
        if not 0 <= self.stamp_ns <= _INT32_MAX * NS_PER_S + NS_PER_S - 1:
            raise TransformError(f"transform {name}: stamp {self.stamp_ns} ns out of range")
        values = np.concatenate([np.ravel(self.translation), np.ravel(self.rotation)])
        if values.shape != (7,) or not np.all(np.isfinite(values)):
            raise TransformError(f"transform {name}: translation (3) and rotation (4) not finite")
        if abs(float(np.linalg.norm(self.rotation)) - 1.0) > 1e-6:
            raise TransformError(f"transform {name}: rotation is not a unit quaternion")


@dataclass(frozen=True)
class FrameNames:
    """The names of the frame tree's four frames (module docstring).

    The defaults are :mod:`endo_io.topics`' REP 103 frames; a node whose
    frame ids are parameters (the tracker bridge's ``world_frame``,
    ``tracker_frame``, ``camera_frame``) passes its own, and the tree's
    shape stays the one defined here.

    Attributes:
        world: root of the tree, the frame of ``/endoscope/pose``.
        tracker: the optical tracker's frame.
        camera: the camera's optical frame, the images' ``frame_id``.
        marker: the marker (rigid body) on the endoscope.
    """

    world: str = WORLD_FRAME
    tracker: str = TRACKER_FRAME
    camera: str = OPTICAL_FRAME
    marker: str = MARKER_FRAME


def camera_transform(
    T_world_camera: np.ndarray, stamp_ns: int, *, frames: FrameNames = FrameNames()
) -> StampedTransform:
    """``world → endoscope_optical_frame`` at ``stamp_ns``, the per-frame edge of ``/tf``.

    Args:
        T_world_camera: (4, 4) float64 camera optical frame → world, metres.
        stamp_ns: integer nanoseconds, the camera pose's stamp.
        frames: the frame names (``frames.world → frames.camera``).

    Raises:
        TransformError: see :meth:`StampedTransform.from_matrix`.
    """
    return StampedTransform.from_matrix(T_world_camera, stamp_ns, frames.world, frames.camera)


def static_transforms(
    *,
    T_world_tracker: np.ndarray | None,
    T_marker_camera: np.ndarray | None,
    stamp_ns: int = 0,
    frames: FrameNames = FrameNames(),
) -> list[StampedTransform]:
    """The static edges of ``/tf_static`` that are known.

    Args:
        T_world_tracker: (4, 4) tracker → world (the tracker bridge's
            ``T_world_tracker``), or None if unknown.
        T_marker_camera: (4, 4) camera optical frame → marker (the hand–eye
            calibration), or None if unknown. Recorded as the edge
            ``endoscope_optical_frame → endoscope_marker`` (module docstring).
        stamp_ns: stamp of the static transforms (tf ignores it; 0 is usual).
        frames: the frame names (``world``, ``tracker``, ``camera``, ``marker``).

    Returns:
        ``world → tracker`` and ``endoscope_optical_frame → endoscope_marker``,
        the ones that were given, in that order.
    """
    edges = []
    if T_world_tracker is not None:
        edges.append(
            StampedTransform.from_matrix(T_world_tracker, stamp_ns, frames.world, frames.tracker)
        )
    if T_marker_camera is not None:
        T = np.asarray(T_marker_camera, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise TransformError("T_marker_camera must be a finite (4, 4) matrix")
        T_camera_marker = invert_transform(T)
        edges.append(
            StampedTransform.from_matrix(T_camera_marker, stamp_ns, frames.camera, frames.marker)
        )
    return edges


def tf_message_definition() -> MessageDefinition:
    """Complete ``ros2msg`` definition of ``tf2_msgs/msg/TFMessage`` (MCAP schema text).

    Built the way rosbag2 builds it: the root text, then each dependency once
    after a separator line; the one dependency's own text (with its
    dependencies) comes from the installed geometry_msgs.

    Raises:
        TransformError: geometry_msgs' interface files are not installed.
    """
    # endo_io.bag loads rclpy (its serialiser); the definitions are only files.
    from endo_io.bag.msgdef import DEFINITION_SEPARATOR, MessageDefinition, message_definition

    dependency = message_definition("geometry_msgs/msg/TransformStamped")
    if dependency.encoding != "ros2msg":
        raise TransformError("geometry_msgs/msg/TransformStamped.msg is not installed")
    text = (
        f"{TF_MESSAGE_MSG_TEXT}\n{DEFINITION_SEPARATOR}\nMSG: {_TRANSFORM_STAMPED}\n"
        f"{dependency.text}"
    )
    return MessageDefinition("ros2msg", text)


def _cdr_string(text: str) -> bytes:
    data = text.encode("utf-8")
    if b"\x00" in data:
        raise TransformError(f"frame name {text!r} contains a NUL byte")
    return struct.pack("<I", len(data) + 1) + data + b"\x00"


def serialize_tf_message(transforms: Sequence[StampedTransform]) -> bytes:
    """Canonical CDR bytes of a ``tf2_msgs/msg/TFMessage`` holding ``transforms``.

    Layout (alignment counted from the end of the 4-byte encapsulation
    header): uint32 count; per transform int32 sec, uint32 nanosec, the two
    strings (uint32 length with the NUL, bytes, NUL), zero padding to 8, then
    seven float64 (translation x, y, z, rotation x, y, z, w). The whole is
    zero-padded to a multiple of 4 bytes.

    Raises:
        TransformError: a transform fails :meth:`StampedTransform.check`.
    """
    body = bytearray(struct.pack("<I", len(transforms)))
    for edge in transforms:
        edge.check()
        body += bytes(-len(body) % 4)
        sec, nanosec = divmod(edge.stamp_ns, NS_PER_S)
        body += struct.pack("<iI", sec, nanosec)
        body += _cdr_string(edge.parent_frame)
        body += bytes(-len(body) % 4)
        body += _cdr_string(edge.child_frame)
        body += bytes(-len(body) % 8)
        body += struct.pack("<7d", *np.ravel(edge.translation), *np.ravel(edge.rotation))
    body += bytes(-len(body) % 4)
    return _CDR_LITTLE_ENDIAN_HEADER + bytes(body)


def tf_qos(*, static: bool) -> QoSProfile:
    """The QoS of tf2_ros's broadcasters, for a live ``/tf`` or ``/tf_static`` publisher.

    ``/tf`` reliable keep-last 100 volatile, ``/tf_static`` reliable
    keep-last 1 transient-local (a late listener still gets the static tree).
    """
    from endo_io.qos import reliable_qos  # rclpy: only where a profile is wanted

    return reliable_qos(1, latched=True) if static else reliable_qos(100)


def tf_qos_yaml(*, static: bool) -> str:
    """Offered-QoS YAML of a tf publisher (:func:`tf_qos`), as rosbag2 records it.

    ``/tf_static``'s transient-local durability makes a replay latch it.
    """
    from endo_io.bag.qos_yaml import qos_profiles_to_yaml  # rclpy QoS types

    return qos_profiles_to_yaml([tf_qos(static=static)])


def transform_stamped(edge: StampedTransform) -> TransformStamped:
    """The ``geometry_msgs/msg/TransformStamped`` of one edge, as a tf broadcaster sends it.

    ``header.frame_id`` is the parent, ``child_frame_id`` the child; the
    stamp is ``edge.stamp_ns`` (sec, nanosec), translation in metres,
    rotation the unit quaternion x, y, z, w. The values are copied as
    float64, unchanged.

    Raises:
        TransformError: the edge fails :meth:`StampedTransform.check`.
    """
    from geometry_msgs.msg import TransformStamped  # the ROS message, only where one is built

    edge.check()
    msg = TransformStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(edge.stamp_ns, NS_PER_S)
    msg.header.frame_id = edge.parent_frame
    msg.child_frame_id = edge.child_frame
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = (float(v) for v in np.ravel(edge.translation))
    q.x, q.y, q.z, q.w = (float(v) for v in np.ravel(edge.rotation))
    return msg


def add_tf_topic(writer: BagWriter, topic: str) -> None:
    """Declare ``topic`` (``/tf`` or ``/tf_static``) as ``tf2_msgs/msg/TFMessage`` in a bag.

    The schema is :func:`tf_message_definition`, the offered QoS the tf
    broadcasters' (``/tf_static`` latched). Declaring it again does nothing.
    """
    writer.add_topic(
        topic,
        TF_MESSAGE_TYPE,
        tf_qos_yaml(static=topic == TF_STATIC),
        message_definition_override=tf_message_definition(),
    )


def write_tf(
    writer: BagWriter, topic: str, transforms: Sequence[StampedTransform], log_time_ns: int
) -> None:
    """Record one ``TFMessage`` on ``topic`` (``/tf`` or ``/tf_static``) of a bag being written.

    The topic is declared on first use (:func:`add_tf_topic`).

    Args:
        writer: an open :class:`endo_io.bag.BagWriter`.
        topic: :data:`endo_io.topics.TF` or :data:`endo_io.topics.TF_STATIC`.
        transforms: the edges of this message (at least one).
        log_time_ns: receive time of the message, integer ns.

    Raises:
        TransformError: no transforms, or one that cannot be recorded.
    """
    if not transforms:
        raise TransformError(f"{topic}: a tf message needs at least one transform")
    data = serialize_tf_message(transforms)
    add_tf_topic(writer, topic)
    writer.write(topic, data, log_time_ns)


__all__ = [
    "TF_MESSAGE_MSG_TEXT",
    "TF_MESSAGE_TYPE",
    "FrameNames",
    "StampedTransform",
    "TransformError",
    "add_tf_topic",
    "camera_transform",
    "serialize_tf_message",
    "static_transforms",
    "tf_message_definition",
    "tf_qos",
    "tf_qos_yaml",
    "transform_stamped",
    "write_tf",
]
