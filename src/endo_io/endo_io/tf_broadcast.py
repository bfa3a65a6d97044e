"""Live ``/tf`` and ``/tf_static`` over DDS, where ``tf2_msgs`` is importable.

:mod:`endo_io.tf` defines the frame tree and its edges; this module sends
them as a tf2 broadcaster does: ``tf2_msgs/msg/TFMessage`` of
``geometry_msgs/msg/TransformStamped`` (:func:`endo_io.tf.transform_stamped`),
``/tf`` reliable keep-last 100 and ``/tf_static`` reliable transient-local
keep-last 1 (:func:`endo_io.tf.tf_qos`), so RViz2, ``tf2_ros`` listeners and
``ros2 bag record`` see the camera move in ``world``.

rclpy can only publish a type whose Python package (with its compiled type
support) is installed. A full ROS install has ``tf2_msgs``; the pip-only
install does not (there is no ``tf2_msgs`` wheel, docs/viewers.md). There a
:class:`TfBroadcaster` logs one info line saying where the transforms are
served instead (endo-foxglove's FrameTransforms, ``/tf`` in recordings) and
sends nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rclpy.node import Node
from rclpy.publisher import Publisher

from endo_io.bag.errors import UnknownMessageTypeError
from endo_io.bag.serde import message_class
from endo_io.tf import TF_MESSAGE_TYPE, StampedTransform, tf_qos, transform_stamped
from endo_io.topics import TF, TF_STATIC

#: The line a broadcaster logs (once) where ``tf2_msgs`` is not importable.
NO_TF2_MSGS = (
    f"{TF} and {TF_STATIC} are not published over DDS: {TF_MESSAGE_TYPE} is not importable "
    "(pip-only install, no tf2_msgs wheel); live transforms are served by endo-foxglove's "
    "FrameTransforms, and recordings made by endo-process carry /tf and /tf_static"
)


def tf_message_class() -> type | None:
    """The installed ``tf2_msgs.msg.TFMessage`` class, or None where it is not importable."""
    try:
        return message_class(TF_MESSAGE_TYPE)
    except UnknownMessageTypeError:
        return None


def tf_message(tf_message_type: type, edges: Sequence[StampedTransform]) -> Any:
    """A ``TFMessage`` instance (of the class given) holding one ``TransformStamped`` per edge.

    Raises:
        TransformError: an edge that cannot be sent (:meth:`StampedTransform.check`).
    """
    return tf_message_type(transforms=[transform_stamped(edge) for edge in edges])


class TfBroadcaster:
    """Sends edges of the frame tree on ``/tf`` and ``/tf_static`` (module docstring).

    Attributes:
        available: True when ``tf2_msgs`` is importable and the two
            publishers exist; False: every send does nothing (one info
            line was logged at construction).
    """

    def __init__(self, node: Node) -> None:
        self._node = node
        self._class = tf_message_class()
        self._tf: Publisher | None = None
        self._static: Publisher | None = None
        if self._class is None:
            node.get_logger().info(NO_TF2_MSGS)
            return
        self._tf = node.create_publisher(self._class, TF, tf_qos(static=False))
        self._static = node.create_publisher(self._class, TF_STATIC, tf_qos(static=True))

    @property
    def available(self) -> bool:
        """True when the transforms go out over DDS."""
        return self._tf is not None

    def send(self, edges: Sequence[StampedTransform]) -> None:
        """Publish edges that change (the camera pose) on ``/tf``; no-op where unavailable.

        Raises:
            TransformError: an edge that cannot be sent.
        """
        if self._tf is not None and self._class is not None and edges:
            self._tf.publish(tf_message(self._class, edges))

    def send_static(self, edges: Sequence[StampedTransform]) -> None:
        """Publish the complete set of static edges on ``/tf_static``; no-op where unavailable.

        The topic is transient-local with depth 1, so every call must carry
        all static edges of this publisher (as tf2_ros's static broadcaster
        does): the last message is what a late listener gets.

        Raises:
            TransformError: an edge that cannot be sent.
        """
        if self._static is not None and self._class is not None and edges:
            self._static.publish(tf_message(self._class, edges))

    def close(self) -> None:
        """Destroy the publishers (the node stays)."""
        for publisher in (self._tf, self._static):
            if publisher is not None:
                self._node.destroy_publisher(publisher)
        self._tf = self._static = None


__all__ = ["NO_TF2_MSGS", "TfBroadcaster", "tf_message", "tf_message_class"]
