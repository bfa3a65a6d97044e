"""endo_io.bag.serde.cdr_check: what endo-record and endo-replay check each message with.

Images go through endo_io.image.image_from_cdr (no copy of the pixels), other
types through rclpy; both refuse what does not decode with one named error.
"""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo

from endo_io.bag import MessageDeserializationError, UnknownMessageTypeError, serialize
from endo_io.bag.serde import cdr_check
from endo_io.image import array_to_image, image_to_array

MS = 1_000_000


def test_an_image_is_checked_field_by_field_without_copying_its_pixels():
    pixels = np.arange(12, dtype=np.float32).reshape(3, 4) / 8
    data = serialize(array_to_image(pixels, "32FC1", 5 * MS, "cam"))
    checked = cdr_check("sensor_msgs/msg/Image", "/img")(data)
    assert checked.encoding == "32FC1" and (checked.height, checked.width) == (3, 4)
    assert checked.header.frame_id == "cam"
    assert np.array_equal(image_to_array(checked), pixels)
    assert np.shares_memory(np.frombuffer(checked.data, np.uint8), np.frombuffer(data, np.uint8))


def test_a_truncated_image_is_refused_naming_the_topic_the_type_and_the_field():
    data = serialize(array_to_image(np.ones((3, 4), np.float32), "32FC1", 5 * MS, "cam"))
    with pytest.raises(MessageDeserializationError) as caught:
        cdr_check("sensor_msgs/msg/Image", "/img")(data[:40])
    text = str(caught.value)
    assert text.startswith("/img: 40 bytes are not a valid sensor_msgs/msg/Image")
    assert "UndecodableMessageError" in text and "step" in text
    assert "\n" not in text


def test_other_types_decode_through_rclpy_and_an_unknown_type_is_refused_at_once():
    info = CameraInfo(width=640, height=480, distortion_model="plumb_bob")
    info.d = [0.1, -0.05, 0.0, 0.0, 0.0]
    checked = cdr_check("sensor_msgs/msg/CameraInfo", "/info")(serialize(info))
    assert checked.width == 640 and list(checked.d) == [0.1, -0.05, 0.0, 0.0, 0.0]
    with pytest.raises(MessageDeserializationError):
        cdr_check("sensor_msgs/msg/CameraInfo", "/info")(b"\x00\x01\x00\x00" + b"\xff" * 8)
    with pytest.raises(UnknownMessageTypeError):
        cdr_check("no_such_pkg/msg/Nothing", "/x")
