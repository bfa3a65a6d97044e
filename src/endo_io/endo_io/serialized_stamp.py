"""The header stamp of a serialized (CDR) message, without deserializing it.

A node that skips stale frames (:meth:`endo_io.diagnostics.InputHealth.subscribe`
with ``newest=True``) still counts their stamps, for the gap count of lost
frames; decoding a 1.2 MB image only to read eight bytes would cost more than
the skip saves. Every message whose first field is a ``std_msgs/Header``
(Image, CameraInfo, PoseStamped, PointCloud2, ...) starts, after the 4-byte
CDR encapsulation header, with ``stamp.sec`` (int32) and ``stamp.nanosec``
(uint32), in the byte order the encapsulation names.
"""

from __future__ import annotations

import struct

from endo_io.stamp import NS_PER_S

#: Encapsulation identifiers (second byte) of plain CDR: 0 big endian, 1 little endian.
_CDR_BE, _CDR_LE = 0, 1


def serialized_header_stamp_ns(data: bytes) -> int | None:
    """Header stamp (integer ns) of a serialized message that starts with a Header.

    Args:
        data: the serialized message, CDR encapsulation header included.

    Returns:
        ``sec * 1e9 + nanosec``, or None when ``data`` is too short or not
        plain CDR (the caller then counts the message without a stamp).
    """
    if len(data) < 12 or data[0] != 0 or data[1] not in (_CDR_BE, _CDR_LE):
        return None
    sec, nanosec = struct.unpack_from("<iI" if data[1] == _CDR_LE else ">iI", data, 4)
    return sec * NS_PER_S + nanosec
