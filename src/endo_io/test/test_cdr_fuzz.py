"""Fuzzing CDR messages from other people's rigs: Image, CameraInfo, PoseStamped.

A recorded message is decoded with rclpy's own deserialisation
(:func:`endo_io.bag.deserialize`), then converted by the helpers every node
uses. Whatever the bytes (cut short, flipped, a sequence or string length of
``0xFFFFFFFF``), the only errors are the project's named ones:
:class:`MessageDeserializationError` for bytes that do not decode and
:class:`MessageConversionError` subclasses for decoded messages that make no
sense, and a declared length larger than the message is refused before
anything is allocated (the process's peak RSS does not grow).
"""

from __future__ import annotations

import os
import resource

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image

from endo_io.bag import BagMessage, MessageDeserializationError, deserialize
from endo_io.camera import CameraModel
from endo_io.errors import MessageConversionError, UndecodableMessageError
from endo_io.image import image_from_cdr, image_to_array
from endo_io.pose import pose_to_matrix

pytestmark = pytest.mark.fuzz

EXAMPLES = int(os.environ.get("ENDO3D_FUZZ_EXAMPLES", "30"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
HOSTILE_U32 = [0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF, 1 << 20]
# Peak RSS may grow by this much over every decode of a test (it would grow
# by gigabytes if a declared length were allocated).
RSS_GROWTH_LIMIT_KB = 64 * 1024


def _image() -> Image:
    msg = Image(height=3, width=4, encoding="rgb8", step=12, is_bigendian=0)
    msg.header.frame_id = "endoscope_optical_frame"
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.data = np.arange(36, dtype=np.uint8).tobytes()
    return msg


def _camera_info() -> CameraInfo:
    msg = CameraInfo(height=48, width=64, distortion_model="plumb_bob")
    msg.header.frame_id = "endoscope_optical_frame"
    msg.d = [0.1, -0.05, 0.001, 0.002, 0.0]
    msg.k = [50.0, 0.0, 32.0, 0.0, 50.0, 24.0, 0.0, 0.0, 1.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [50.0, 0.0, 32.0, 0.0, 0.0, 50.0, 24.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def _pose() -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = "tracker"
    msg.pose.position.x, msg.pose.position.z = 0.01, -0.02
    msg.pose.orientation.w = 1.0
    return msg


def _convert_image(msg: Image) -> None:
    image_to_array(msg)


def _convert_camera_info(msg: CameraInfo) -> None:
    CameraModel.from_camera_info(msg)


def _convert_pose(msg: PoseStamped) -> None:
    pose_to_matrix(msg)


CASES = {
    "sensor_msgs/msg/Image": (serialize_message(_image()), Image, _convert_image),
    "sensor_msgs/msg/CameraInfo": (
        serialize_message(_camera_info()),
        CameraInfo,
        _convert_camera_info,
    ),
    "geometry_msgs/msg/PoseStamped": (serialize_message(_pose()), PoseStamped, _convert_pose),
}
TYPES = st.sampled_from(sorted(CASES))


def _decode_and_convert(msgtype: str, data: bytes) -> str:
    """Decode and convert; returns which named outcome it had (anything else fails the test).

    An Image is also decoded by :func:`endo_io.image.image_from_cdr` (the
    nodes' decoding), which must agree: refused as undecodable, rejected by
    the same error, or the same pixels.
    """
    _, cls, convert = CASES[msgtype]
    try:
        msg = deserialize(BagMessage("/fuzz", msgtype, 0, data, 0))
    except MessageDeserializationError as error:
        assert "\n" not in str(error) and msgtype in str(error)
        if cls is Image:
            with pytest.raises(UndecodableMessageError):
                image_from_cdr(data)
        return "undecodable"
    assert isinstance(msg, cls)
    view = image_from_cdr(data) if cls is Image else None
    try:
        convert(msg)
    except MessageConversionError as error:
        assert "\n" not in str(error)
        if view is not None:
            with pytest.raises(type(error)):
                image_to_array(view)
        return "rejected"
    if view is not None:
        assert view.header == msg.header and view.encoding == msg.encoding
        np.testing.assert_array_equal(image_to_array(view), image_to_array(msg))
    return "ok"


def _peak_rss_kb() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def test_intact_messages_decode_and_convert():
    for msgtype, (data, _, _) in CASES.items():
        assert _decode_and_convert(msgtype, data) == "ok", msgtype


@FUZZ
@given(msgtype=TYPES, fraction=st.floats(0.0, 1.0))
def test_truncated_cdr_is_a_named_error(msgtype, fraction):
    data = CASES[msgtype][0]
    cut = int(fraction * len(data))
    outcome = _decode_and_convert(msgtype, data[:cut])
    assert outcome == ("ok" if cut == len(data) else "undecodable")


@FUZZ
@given(
    msgtype=TYPES,
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), min_size=1, max_size=6),
)
def test_flipped_cdr_bytes_are_a_named_error_or_a_message(msgtype, flips):
    data = bytearray(CASES[msgtype][0])
    for fraction, xor in flips:
        data[min(int(fraction * len(data)), len(data) - 1)] ^= xor
    _decode_and_convert(msgtype, bytes(data))


@FUZZ
@given(
    msgtype=TYPES,
    word=st.integers(0, 200),
    value=st.sampled_from(HOSTILE_U32) | st.integers(0, 2**32 - 1),
)
def test_hostile_u32_fields_are_a_named_error_or_a_message(msgtype, word, value):
    data = bytearray(CASES[msgtype][0])
    offset = 4 + 4 * (word % ((len(data) - 4) // 4))  # after the 4-byte encapsulation header
    data[offset : offset + 4] = value.to_bytes(4, "little")
    _decode_and_convert(msgtype, bytes(data))


@pytest.mark.parametrize("msgtype", sorted(CASES))
def test_every_length_set_to_4_gib_is_refused_without_allocating(msgtype):
    data = CASES[msgtype][0]
    before = _peak_rss_kb()
    outcomes = set()
    for offset in range(4, len(data) - 3, 4):
        for value in (0xFFFFFFFF, 0x80000000):
            hostile = bytearray(data)
            hostile[offset : offset + 4] = value.to_bytes(4, "little")
            outcomes.add(_decode_and_convert(msgtype, bytes(hostile)))
    # Header.frame_id and the string/sequence lengths are among the words: some
    # of the hostile copies must have been refused as undecodable.
    assert "undecodable" in outcomes
    assert _peak_rss_kb() - before < RSS_GROWTH_LIMIT_KB
