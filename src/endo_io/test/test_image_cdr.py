"""endo_io.image.array_to_image_cdr: serialize(array_to_image(...))'s bytes, built directly."""

from __future__ import annotations

import numpy as np
import pytest

from endo_io.bag.serde import decode_cdr, serialize
from endo_io.errors import ImageEncodingError, ImageLayoutError
from endo_io.image import array_to_image, array_to_image_cdr, image_to_array

CASES = [
    ("32FC1", np.float32, (48, 64)),
    ("32FC3", np.float32, (4, 3, 3)),
    ("mono8", np.uint8, (5, 7)),
    ("mono16", np.uint16, (3, 5)),
    ("rgb8", np.uint8, (3, 5, 3)),
    ("bgra8", np.uint8, (2, 3, 4)),
]


@pytest.mark.parametrize(("encoding", "dtype", "shape"), CASES)
@pytest.mark.parametrize("frame_id", ["", "a", "ab", "abc", "abcd", "endoscope_optical_frame"])
def test_equals_the_serialised_message(
    encoding: str, dtype: type, shape: tuple[int, ...], frame_id: str
) -> None:
    array = (np.random.default_rng(1).random(shape) * 200).astype(dtype)
    stamp_ns = 1_700_000_123_456_789_012
    direct = array_to_image_cdr(array, encoding, stamp_ns, frame_id)
    assert direct == serialize(array_to_image(array, encoding, stamp_ns, frame_id))
    decoded = decode_cdr(direct, "sensor_msgs/msg/Image", where="test")
    assert decoded.header.frame_id == frame_id and decoded.encoding == encoding
    assert decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec == stamp_ns
    np.testing.assert_array_equal(image_to_array(decoded), array)


def test_nan_and_a_non_contiguous_view_survive() -> None:
    depth = np.arange(60, dtype=np.float32).reshape(6, 10)
    depth[2, 3] = np.nan
    view = depth[:, ::2]  # not contiguous: packed on the way
    data = array_to_image_cdr(view, "32FC1", 5)
    decoded = image_to_array(decode_cdr(data, "sensor_msgs/msg/Image", where="test"))
    np.testing.assert_array_equal(decoded, view)


def test_refuses_what_array_to_image_refuses() -> None:
    with pytest.raises(ImageEncodingError):
        array_to_image_cdr(np.zeros((2, 2), np.float64), "32FC1")
    with pytest.raises(ImageLayoutError):
        array_to_image_cdr(np.zeros((0, 2), np.float32), "32FC1")
    with pytest.raises(ValueError, match="non-negative"):
        array_to_image_cdr(np.zeros((2, 2), np.float32), "32FC1", -1)
