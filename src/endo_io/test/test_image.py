"""Round trips and bad-input checks for endo_io.image."""

from __future__ import annotations

import sys
from array import array as byte_array

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image

from endo_io.errors import ImageEncodingError, ImageLayoutError, MessageConversionError
from endo_io.image import SUPPORTED_ENCODINGS, array_to_image, image_to_array, pixel_format
from endo_io.stamp import stamp_to_ns

SHAPES = {
    "mono8": (np.uint8, None),
    "mono16": (np.uint16, None),
    "16UC1": (np.uint16, None),
    "32FC1": (np.float32, None),
    "32FC3": (np.float32, 3),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
}


def random_pixels(encoding: str, height: int = 7, width: int = 5, seed: int = 0) -> np.ndarray:
    dtype, channels = SHAPES[encoding]
    shape = (height, width) if channels is None else (height, width, channels)
    rng = np.random.default_rng(seed)
    if dtype is np.float32:
        pixels = rng.uniform(0.01, 5.0, size=shape).astype(np.float32)
        pixels[0, 0] = np.nan  # REP 118 invalid depth must survive bit for bit
        pixels[1, 2] = np.inf
        return pixels
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)


def bit_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def raw_message(encoding: str, pixels: np.ndarray, *, padding: int, bigendian: bool) -> Image:
    """Build an Image by hand, independently of array_to_image."""
    order = ">" if bigendian else "<"
    stored = pixels.astype(pixels.dtype.newbyteorder(order))
    height, width = pixels.shape[:2]
    row_bytes = stored[0].nbytes
    rows = stored.reshape(height, -1).view(np.uint8).reshape(height, row_bytes)
    pad = np.full((height, padding), 0xAB, dtype=np.uint8)  # garbage, must be ignored
    msg = Image()
    msg.height, msg.width, msg.encoding = height, width, encoding
    msg.is_bigendian = int(bigendian)
    msg.step = row_bytes + padding
    msg.data = byte_array("B", np.hstack([rows, pad]).tobytes())
    return msg


def test_supported_encodings_are_the_contract_set():
    assert frozenset(SHAPES) == SUPPORTED_ENCODINGS


@pytest.mark.parametrize("encoding", sorted(SHAPES))
def test_round_trip_is_exact(encoding):
    pixels = random_pixels(encoding)
    msg = array_to_image(pixels, encoding, stamp_ns=1_700_000_000_123_456_789, frame_id="cam")
    fmt = pixel_format(encoding)
    assert (msg.height, msg.width) == (7, 5)
    assert msg.step == 5 * fmt.bytes_per_pixel
    assert len(msg.data) == msg.step * msg.height
    assert msg.is_bigendian == int(sys.byteorder == "big")
    assert msg.header.frame_id == "cam"
    assert stamp_to_ns(msg.header.stamp) == 1_700_000_000_123_456_789
    assert bit_equal(image_to_array(msg), pixels)


@pytest.mark.parametrize("encoding", sorted(SHAPES))
def test_round_trip_through_cdr(encoding):
    pixels = random_pixels(encoding, seed=1)
    wire = serialize_message(array_to_image(pixels, encoding))
    assert bit_equal(image_to_array(deserialize_message(wire, Image)), pixels)


@pytest.mark.parametrize("encoding", sorted(SHAPES))
@pytest.mark.parametrize("padding", [0, 1, 7, 64])
@pytest.mark.parametrize("bigendian", [False, True])
def test_padded_and_big_endian_messages(encoding, padding, bigendian):
    pixels = random_pixels(encoding, height=6, width=9, seed=padding)
    msg = raw_message(encoding, pixels, padding=padding, bigendian=bigendian)
    out = image_to_array(msg)
    assert out.dtype.isnative
    assert out.flags.c_contiguous
    assert bit_equal(out, pixels)
    # and back: the re-published message is packed and native, same pixels
    again = array_to_image(out, encoding)
    assert again.step == 9 * pixel_format(encoding).bytes_per_pixel
    assert bit_equal(image_to_array(again), pixels)


def test_known_pixel_values_and_channel_order():
    msg = Image()
    msg.height, msg.width, msg.encoding, msg.step = 2, 2, "bgr8", 8  # 2 bytes of padding
    msg.data = byte_array("B", [1, 2, 3, 4, 5, 6, 0, 0, 7, 8, 9, 10, 11, 12, 0, 0])
    out = image_to_array(msg)
    np.testing.assert_array_equal(out[0, 1], [4, 5, 6])  # B, G, R kept as stored
    np.testing.assert_array_equal(out[1, 0], [7, 8, 9])

    depth = Image()
    depth.height, depth.width, depth.encoding, depth.step = 1, 2, "32FC1", 8
    depth.is_bigendian = 1
    depth.data = byte_array("B", np.array([1.5, -2.25], dtype=">f4").tobytes())
    np.testing.assert_array_equal(image_to_array(depth), [[1.5, -2.25]])

    mono16 = Image()
    mono16.height, mono16.width, mono16.encoding, mono16.step = 1, 1, "mono16", 2
    mono16.is_bigendian = 1
    mono16.data = byte_array("B", [0x12, 0x34])
    assert image_to_array(mono16)[0, 0] == 0x1234
    mono16.is_bigendian = 0
    assert image_to_array(mono16)[0, 0] == 0x3412


def test_packed_native_message_is_a_view():
    msg = array_to_image(random_pixels("rgb8"), "rgb8")
    assert np.shares_memory(image_to_array(msg), np.frombuffer(msg.data, np.uint8))


def test_single_channel_accepts_trailing_axis_and_any_byte_order():
    pixels = random_pixels("mono16")
    msg = array_to_image(pixels[:, :, None], "mono16")
    assert bit_equal(image_to_array(msg), pixels)
    msg = array_to_image(pixels.astype(">u2"), "16UC1")
    assert bit_equal(image_to_array(msg), pixels)


def test_unknown_encoding_names_it():
    msg = array_to_image(random_pixels("mono8"), "mono8")
    msg.encoding = "bayer_rggb8"
    with pytest.raises(ImageEncodingError, match="bayer_rggb8"):
        image_to_array(msg)
    with pytest.raises(ImageEncodingError, match="yuv422"):
        array_to_image(random_pixels("rgb8"), "yuv422")


def test_wrong_step_names_the_numbers():
    msg = array_to_image(random_pixels("rgb8"), "rgb8")  # 5 px wide -> 15 bytes per row
    msg.step = 14
    with pytest.raises(ImageLayoutError, match=r"step 14 < width 5 x 3 .* = 15"):
        image_to_array(msg)


def test_truncated_and_oversized_buffers():
    msg = array_to_image(random_pixels("32FC1"), "32FC1")  # 7 x 5 x 4 bytes
    full = msg.data
    msg.data = full[:-1]
    with pytest.raises(ImageLayoutError, match=r"truncated: 139 bytes, expected .* = 140"):
        image_to_array(msg)
    msg.data = full + byte_array("B", [0])
    with pytest.raises(ImageLayoutError, match="oversized: 141 bytes"):
        image_to_array(msg)


def test_zero_size_is_rejected():
    msg = Image()
    msg.encoding = "mono8"
    with pytest.raises(ImageLayoutError, match="zero size 0x0"):
        image_to_array(msg)
    with pytest.raises(ImageLayoutError, match="zero-size"):
        array_to_image(np.zeros((0, 4), np.uint8), "mono8")


@pytest.mark.parametrize(
    ("pixels", "encoding", "error"),
    [
        (np.zeros((4, 4), np.float64), "32FC1", ImageEncodingError),
        (np.zeros((4, 4), np.uint16), "mono8", ImageEncodingError),
        (np.zeros((4, 4, 3), np.uint8), "mono8", ImageLayoutError),
        (np.zeros((4, 4), np.uint8), "rgb8", ImageLayoutError),
        (np.zeros((4, 4, 3), np.uint8), "rgba8", ImageLayoutError),
        (np.zeros(16, np.uint8), "mono8", ImageLayoutError),
    ],
)
def test_array_must_match_encoding(pixels, encoding, error):
    with pytest.raises(error) as info:
        array_to_image(pixels, encoding)
    assert isinstance(info.value, MessageConversionError)
    assert encoding in str(info.value)
