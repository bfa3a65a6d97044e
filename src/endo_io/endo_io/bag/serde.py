"""CDR (de)serialisation of recorded messages with rclpy's own type support.

Bags store messages as CDR bytes; decoding uses the installed Python message
classes (``sensor_msgs/msg/Image`` -> ``sensor_msgs.msg.Image``) through
``rclpy.serialization``, i.e. the very code a live subscription runs. Types
that are not installed are never guessed from the schema text: they stay raw
bytes, and asking to decode them raises :class:`UnknownMessageTypeError`.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message

from endo_io.bag.errors import MessageDeserializationError, UnknownMessageTypeError
from endo_io.bag.interfaces import BagMessage
from endo_io.bag.msgdef import split_msgtype
from endo_io.image import image_from_cdr


@functools.lru_cache(maxsize=512)
def message_class(msgtype: str) -> type:
    """The installed Python class of a ROS 2 type, e.g. ``sensor_msgs/msg/Image``.

    The short form ``pkg/Name`` means ``pkg/msg/Name``.

    Raises:
        UnknownMessageTypeError: the name is malformed, the package or type is
            not installed, or the attribute found is not a ROS message class.
    """
    package, namespace, name = split_msgtype(msgtype)
    try:
        module = importlib.import_module(f"{package}.{namespace}")
    except ImportError as exc:
        raise UnknownMessageTypeError(f"message type {msgtype} is not installed") from exc
    cls = getattr(module, name, None)
    if not isinstance(cls, type) or not hasattr(cls, "_fields_and_field_types"):
        raise UnknownMessageTypeError(f"message type {msgtype} is not installed")
    return cls


def msgtype_of(message: Any) -> str:
    """ROS 2 type name (``pkg/msg/Name``) of a message instance or class."""
    cls = message if isinstance(message, type) else type(message)
    parts = cls.__module__.split(".")
    if len(parts) < 2 or not hasattr(cls, "_fields_and_field_types"):
        raise UnknownMessageTypeError(f"{cls.__module__}.{cls.__name__} is not a ROS message class")
    return f"{parts[0]}/{parts[1]}/{cls.__name__}"


def deserialize(message: BagMessage) -> Any:
    """Decode a recorded message into an instance of its installed ROS 2 class.

    Raises:
        UnknownMessageTypeError: its type is not installed (the bag still
            yields it raw; only decoding is impossible).
        MessageDeserializationError: the bytes do not decode as that type.
    """
    return decode_cdr(
        message.data, message.msgtype, where=f"{message.topic} @ {message.log_time_ns} ns"
    )


def decode_cdr(data: bytes, msgtype: str, *, where: str) -> Any:
    """Decode CDR bytes as an installed type, with rclpy's own deserialisation.

    Args:
        data: The serialised message.
        msgtype: ROS 2 type name, e.g. ``sensor_msgs/msg/Image``.
        where: What the bytes are (a topic, a time), for the error message.

    Raises:
        UnknownMessageTypeError: the type is not installed.
        MessageDeserializationError: the bytes do not decode as that type. A
            declared string or sequence length larger than the bytes is
            refused before anything is allocated (rmw's typesupport checks
            it; it also prints its own line to stderr).
    """
    cls = message_class(msgtype)
    try:
        return deserialize_message(data, cls)
    except Exception as exc:  # rclpy raises bare RuntimeError/TypeError subclasses
        detail = str(exc).strip().splitlines()
        raise MessageDeserializationError(
            f"{where}: {len(data)} bytes are not a valid {msgtype} "
            f"({type(exc).__name__}: {detail[0] if detail else ''})"
        ) from exc


def cdr_check(msgtype: str, where: str) -> Callable[[bytes], object]:
    """A function that decodes bytes as ``msgtype`` and raises if they do not decode.

    For checking messages that are passed on raw (endo-replay, endo-record):
    the decoded message is discarded. Images are checked by
    :func:`endo_io.image.image_from_cdr` (every field and declared length,
    the pixels not copied); other types decode with rclpy (a 640x480 rgb8
    image that way: about 0.06 ms, bench/bench_bag_checks.py).

    Raises:
        UnknownMessageTypeError: the type is not installed (raised at once).
    """
    message_class(msgtype)
    if msgtype == IMAGE_MSGTYPE:
        return functools.partial(_check_image, where=where)

    def check(data: bytes) -> object:
        return decode_cdr(data, msgtype, where=where)

    return check


#: Images are checked without copying their pixels (a recorder checks ~5 MB of
#: float images per frame of the live graph).
IMAGE_MSGTYPE = "sensor_msgs/msg/Image"


def _check_image(data: bytes, *, where: str) -> object:
    """:func:`endo_io.image.image_from_cdr` of ``data`` (every field and length, no pixel copy).

    Raises:
        MessageDeserializationError: as :func:`decode_cdr` for an undecodable Image.
    """
    try:
        return image_from_cdr(data)
    except Exception as exc:
        detail = str(exc).strip().splitlines()
        raise MessageDeserializationError(
            f"{where}: {len(data)} bytes are not a valid {IMAGE_MSGTYPE} "
            f"({type(exc).__name__}: {detail[0] if detail else ''})"
        ) from exc


@functools.lru_cache(maxsize=1)
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def dds_aligned(data: bytes) -> bytes:
    """``data`` padded with zero bytes to a multiple of 4 bytes.

    DDS (Fast DDS here) delivers a serialized message padded to 4-byte
    alignment, and that padded payload is what a recorder receives and
    stores, as ``ros2 bag record`` does.
    """
    return data + bytes(-len(data) % 4)


def serialize(message: Any) -> bytes:
    """Canonical CDR bytes of a ROS 2 message instance.

    rclpy's serialiser leaves CDR alignment padding (e.g. the bytes between
    ``Image.is_bigendian`` and ``Image.step``) uninitialised, so one message
    can serialise to different bytes from run to run. The bytes are therefore
    re-encoded with rosbags' CDR codec, which zeroes every padding byte, for
    every type of the standard Jazzy type store (other types keep rclpy's
    bytes), and padded to 4 bytes as DDS delivers them. Equal messages give
    equal bytes, and a bag written here equals its replay-and-record round
    trip byte for byte.
    """
    msgtype = msgtype_of(message)
    data = serialize_message(message)
    store = _typestore()
    if msgtype in store.fielddefs:
        data = bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype), msgtype))
    return dds_aligned(data)
