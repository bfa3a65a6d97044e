"""Reading and writing serialized (CDR) ROS 2 messages field by field, without rclpy's objects.

rclpy's ``deserialize_message`` builds a Python message object, every nested
message and array included: ~0.03–0.08 ms for a PoseStamped or a
CameraInfo, of which a node that takes them at 60–250 Hz needs only a few
numbers. The decoders built on :class:`CdrReader`
(:func:`endo_io.image.image_from_cdr`,
:func:`endo_io.pose.pose_stamped_from_cdr`,
:func:`endo_io.camera.camera_info_from_cdr`) read those fields in order,
with the values rclpy would give (each is tested against it), and hand any
other encapsulation than plain CDR to rclpy (:func:`decode_plain_cdr`).

Plain CDR (XCDR1), as Fast DDS serialises ROS 2 messages: a 4-byte
encapsulation header (``00 01``: little endian, ``00 00``: big endian, then
two option bytes), then the fields in declaration order, each aligned to its
own size counted from the end of that header; strings are a uint32 length
(the NUL included), the bytes and a NUL; sequences a uint32 count, then the
elements.

The writers that build a message's bytes directly (``array_to_image_cdr``,
``poses_to_cdr``, ``xyz_to_pointcloud2_cdr``, endo_flow's
``scale_message_cdr``) start from :func:`header_cdr` and write their strings
with :func:`cdr_string`, little endian.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any, TypeVar

from std_msgs.msg import Header

from endo_io.errors import UndecodableMessageError
from endo_io.stamp import NS_PER_S

#: Encapsulation identifiers (first two bytes) of plain CDR, big and little endian.
CDR_BIG_ENDIAN, CDR_LITTLE_ENDIAN = b"\x00\x00", b"\x00\x01"

#: The 4-byte encapsulation header the writers put first: plain CDR, little endian.
LITTLE_ENDIAN_ENCAPSULATION = CDR_LITTLE_ENDIAN + b"\x00\x00"


def cdr_string(text: str, offset: int = 0) -> bytes:
    """A little-endian CDR string at ``offset``: padding to 4, length with the NUL, bytes, NUL.

    Args:
        text: the string (UTF-8).
        offset: where it is written, counted from the end of the
            encapsulation header (the padding aligns its length to 4 from there).
    """
    data = text.encode()
    return bytes(-offset % 4) + struct.pack("<I", len(data) + 1) + data + b"\x00"


def header_cdr(stamp_ns: int, frame_id: str) -> bytearray:
    """The encapsulation header and a std_msgs/Header, the start of a message with a header.

    Args:
        stamp_ns: the header's stamp, nanoseconds since the epoch (>= 0).
        frame_id: the header's frame.

    Returns:
        :data:`LITTLE_ENDIAN_ENCAPSULATION`, int32 sec, uint32 nanosec and
        the frame_id string, unpadded: the next field aligns itself from
        ``len(result) - 4``.

    Raises:
        ValueError: a negative stamp.
    """
    if stamp_ns < 0:
        raise ValueError(f"stamp must be non-negative, got {stamp_ns} ns")
    head = bytearray(LITTLE_ENDIAN_ENCAPSULATION)
    head += struct.pack("<iI", *divmod(int(stamp_ns), NS_PER_S))
    head += cdr_string(frame_id)
    return head

_Decoded = TypeVar("_Decoded")


class CdrReader:
    """Reads plain CDR (XCDR1) fields in order, bounds-checked, as Fast CDR aligns them.

    Args:
        data: the serialized message, its 4-byte encapsulation header first.
        little_endian: the byte order the encapsulation header names.

    Every read raises :class:`endo_io.errors.UndecodableMessageError` naming
    the field (``what``) when the bytes end before it does; a declared string
    or sequence length longer than what is left is refused before anything
    is allocated.
    """

    def __init__(self, data: bytes, *, little_endian: bool) -> None:
        self._data = data
        self._offset = 4  # after the encapsulation header, where alignment starts
        self._order = "<" if little_endian else ">"
        self._uint32 = struct.Struct(self._order + "I")
        self._int32 = struct.Struct(self._order + "i")

    def _take(self, size: int, what: str, *, align: int = 1) -> int:
        start = self._offset + (-(self._offset - 4) % align)
        if size > len(self._data) - start:
            raise UndecodableMessageError(
                f"truncated at {what}: {size} byte(s) needed at byte {start}, "
                f"{max(len(self._data) - start, 0)} left"
            )
        self._offset = start + size
        return start

    def uint32(self, what: str) -> int:
        """A uint32."""
        return int(self._uint32.unpack_from(self._data, self._take(4, what, align=4))[0])

    def int32(self, what: str) -> int:
        """An int32."""
        return int(self._int32.unpack_from(self._data, self._take(4, what, align=4))[0])

    def uint8(self, what: str) -> int:
        """A uint8 (or a bool, a char)."""
        return self._data[self._take(1, what)]

    def float64s(self, count: int, what: str) -> tuple[float, ...]:
        """``count`` consecutive float64 (a fixed-size array, or fields one after another)."""
        start = self._take(8 * count, what, align=8)
        return struct.unpack_from(f"{self._order}{count}d", self._data, start)

    def string(self, what: str) -> str:
        """A CDR string as rclpy gives it: up to the first NUL, invalid UTF-8 replaced."""
        length = self.uint32(f"{what} length")
        start = self._take(length, what)
        text = self._data[start:start + length]
        return text.split(b"\x00", 1)[0].decode("utf-8", "replace")

    def octets(self, what: str) -> memoryview:
        """A ``uint8[]`` sequence: its length, then the bytes (a view, not a copy)."""
        length = self.uint32(f"{what} length")
        start = self._take(length, what)
        return memoryview(self._data)[start:start + length]

    def header(self, what: str = "header") -> Header:
        """A ``std_msgs/Header``: stamp (int32 sec, uint32 nanosec), then frame_id."""
        sec = self.int32(f"{what}.stamp.sec")
        nanosec = self.uint32(f"{what}.stamp.nanosec")
        header = Header(frame_id=self.string(f"{what}.frame_id"))
        header.stamp.sec, header.stamp.nanosec = sec, nanosec
        return header


def decode_plain_cdr(data: bytes, msg_type: Any,
                     read: Callable[[CdrReader], _Decoded]) -> _Decoded | Any:
    """``read(reader)`` on plain CDR ``data``; rclpy's deserialisation for other encapsulations.

    Args:
        data: the serialized message, its 4-byte encapsulation header first.
        msg_type: the message class, for rclpy (XCDR2, parameter lists: no
            endo3d or ROS 2 publisher sends them for these types, but DDS allows them).
        read: reads the fields from a :class:`CdrReader` placed after the header.

    Returns:
        What ``read`` returns, or an instance of ``msg_type`` in the rare case above.

    Raises:
        UndecodableMessageError: not CDR, truncated (from ``read``), or not
            decodable by rclpy.
    """
    head = bytes(data[:2])
    if len(data) >= 4 and head in (CDR_BIG_ENDIAN, CDR_LITTLE_ENDIAN):
        return read(CdrReader(data, little_endian=head == CDR_LITTLE_ENDIAN))
    if len(data) >= 4 and head[0] == 0:
        return deserialize_with_rclpy(data, msg_type)
    raise UndecodableMessageError(
        f"not CDR: encapsulation header {bytes(data[:4]).hex() or 'missing'}"
    )


def deserialize_with_rclpy(data: bytes, msg_type: Any) -> Any:
    """rclpy's ``deserialize_message(data, msg_type)``, its refusal as one named line.

    Raises:
        UndecodableMessageError: the first line of rclpy's error.
    """
    # imported here: endo_io.pose (and endo_io.tf through it) loads no rclpy
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(data, msg_type)
    except Exception as error:  # rclpy raises RMWError, or TypeError on junk
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise UndecodableMessageError(first) from None
