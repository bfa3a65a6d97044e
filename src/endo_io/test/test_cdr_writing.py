"""The CDR writers' shared start: header_cdr and cdr_string against rclpy's serialisation."""

from __future__ import annotations

import pytest
from rclpy.serialization import serialize_message
from std_msgs.msg import Header, String

from endo_io.cdr import cdr_string, header_cdr
from endo_io.stamp import ns_to_stamp


@pytest.mark.parametrize("frame_id", ["", "a", "ab", "abc", "endoscope_optical_frame", "wörld"])
@pytest.mark.parametrize("stamp_ns", [0, 1, 1_700_000_000_123_456_789])
def test_header_cdr_is_rclpys_header(frame_id: str, stamp_ns: int) -> None:
    expected = serialize_message(Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id))
    head = header_cdr(stamp_ns, frame_id)
    # unpadded at the end, as rclpy serialises it: the next field aligns itself
    assert bytes(head) == expected


@pytest.mark.parametrize("text", ["", "x", "rgb", "32FC1", "é"])
@pytest.mark.parametrize("offset", [0, 1, 2, 3, 5])
def test_cdr_string_aligns_from_its_offset(text: str, offset: int) -> None:
    written = cdr_string(text, offset)
    padding = -offset % 4
    assert written[:padding] == bytes(padding)
    body = written[padding:]
    expected = serialize_message(String(data=text))[4:]  # a String message is just the string
    assert body == expected


def test_a_negative_stamp_is_refused() -> None:
    with pytest.raises(ValueError, match="non-negative"):
        header_cdr(-1, "world")
