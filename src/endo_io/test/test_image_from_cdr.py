"""``image_from_cdr`` decodes an Image as rclpy does, without copying the pixels.

Compared field by field, and through ``image_to_array``, with rclpy's own
``deserialize_message`` on real frames (the phantom bag's mono8 frames, the
32FC1 a node publishes, bgr8, an odd padded step, big-endian pixels, both CDR
byte orders) and on every truncation of a message; the hostile and flipped
bytes of the CDR fuzz tests are compared there (``test_cdr_fuzz.py``).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from endo_io.bag import BagReader
from endo_io.errors import MessageConversionError, UndecodableMessageError
from endo_io.image import ImageView, array_to_image, image_from_cdr, image_to_array

PHANTOM = Path(__file__).resolve().parents[3] / "bags" / "phantom_colon.mcap"


def assert_decodes_as_rclpy(data: bytes) -> str:
    """``image_from_cdr(data)`` against ``deserialize_message(data, Image)``; the outcome.

    Either both refuse the bytes (``image_from_cdr`` with
    :class:`UndecodableMessageError`, one line), or both decode them to the
    same fields and ``image_to_array`` gives the same array or refuses both
    with the same named error.
    """
    try:
        expected = deserialize_message(data, Image)
    except Exception:
        with pytest.raises(UndecodableMessageError) as refused:
            image_from_cdr(data)
        assert "\n" not in str(refused.value)
        return "undecodable"
    got = image_from_cdr(data)
    for name in ("height", "width", "encoding", "is_bigendian", "step"):
        assert getattr(got, name) == getattr(expected, name), name
    assert got.header == expected.header
    assert bytes(got.data) == expected.data.tobytes()
    try:
        want = image_to_array(expected)
    except MessageConversionError as error:
        with pytest.raises(type(error)):
            image_to_array(got)
        return "rejected"
    pixels = image_to_array(got)
    assert pixels.dtype == want.dtype and pixels.shape == want.shape
    np.testing.assert_array_equal(pixels, want)
    return "ok"


def _with_cdr_byte_order_big(msg: Image) -> bytes:
    """``msg`` serialized in big-endian CDR (encapsulation 0x0000), as another DDS may send it."""
    def string(text: str) -> bytes:
        raw = text.encode() + b"\x00"
        return struct.pack(">I", len(raw)) + raw

    body = struct.pack(">iI", msg.header.stamp.sec, msg.header.stamp.nanosec)
    body += string(msg.header.frame_id)
    body += bytes(-len(body) % 4) + struct.pack(">II", msg.height, msg.width)
    body += string(msg.encoding) + bytes([msg.is_bigendian])
    body += bytes(-len(body) % 4) + struct.pack(">II", msg.step, len(msg.data))
    return b"\x00\x00\x00\x00" + body + msg.data.tobytes()


def _frames() -> list[Image]:
    frames = []
    with BagReader(PHANTOM) as bag:
        for message in bag.messages(topics=["/endoscope/image_raw"]):
            frames.append(deserialize_message(message.data, Image))
            if len(frames) == 2:
                break
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.01, 0.1, (48, 64)).astype(np.float32)
    depth[5, 7] = np.nan
    stamp_ns = 1_700_000_000_123_456_789
    frames.append(array_to_image(depth, "32FC1", stamp_ns, "endoscope_optical_frame"))
    frames.append(array_to_image(rng.integers(0, 256, (5, 7, 3), dtype=np.uint8), "bgr8", 3, "é"))
    odd = Image(height=3, width=5, encoding="mono8", step=7, is_bigendian=0)  # 2 padding bytes
    odd.header.frame_id = "cam"
    odd.data = rng.integers(0, 256, 21, dtype=np.uint8).tobytes()
    frames.append(odd)
    big = array_to_image(depth[:4, :6].astype(">f4").astype(np.float32), "32FC1", 9, "cam")
    big.is_bigendian = 1
    big.data = depth[:4, :6].astype(">f4").tobytes()
    frames.append(big)
    return frames


def test_real_frames_decode_as_rclpy_into_writeable_pixels():
    frames = _frames()
    assert frames[0].width == 640 and frames[0].encoding == "mono8"
    for msg in frames:
        for data in (serialize_message(msg), _with_cdr_byte_order_big(msg)):
            assert assert_decodes_as_rclpy(data) == "ok"
            view = image_from_cdr(data)
            assert isinstance(view, ImageView)
            pixels = image_to_array(view)
            # always a writeable array of its own: a read-only view of the received bytes
            # would make numba compile every warmed-up kernel again for that type
            assert not np.shares_memory(pixels, np.frombuffer(data, np.uint8))
            assert pixels.flags.writeable and pixels.flags.c_contiguous


def test_every_truncation_is_refused_as_rclpy_refuses_it():
    msg = _frames()[4]  # the odd step: strings, padding and data all short
    data = serialize_message(msg)
    outcomes = [assert_decodes_as_rclpy(data[:cut]) for cut in range(len(data) + 1)]
    assert outcomes[-1] == "ok" and outcomes[0] == "undecodable"
    assert "undecodable" in outcomes[len(data) - 4:]  # cut inside the pixel data


def test_hostile_lengths_are_refused_before_allocating():
    data = bytearray(serialize_message(_frames()[3]))
    for offset in range(4, len(data) - 3, 4):
        for value in (0xFFFFFFFF, 0x80000000):
            hostile = bytearray(data)
            hostile[offset:offset + 4] = value.to_bytes(4, "little")
            assert_decodes_as_rclpy(bytes(hostile))
    with pytest.raises(UndecodableMessageError, match="truncated at data: 4294967295 byte"):
        image_from_cdr(bytes(data[:-len(_frames()[3].data) - 4]) + b"\xff\xff\xff\xff")
    with pytest.raises(UndecodableMessageError, match="not CDR"):
        image_from_cdr(b"\x42\x01\x00\x00" + bytes(data[4:]))
    with pytest.raises(UndecodableMessageError, match="not CDR"):
        image_from_cdr(b"")
