"""The scale topic's CDR bytes built directly are rclpy's serialisation of the message."""

import pytest

from endo_flow.messages import scale_message, scale_message_cdr
from endo_flow.scale import ScaleEstimate, ScaleState
from endo_io.bag.serde import serialize


@pytest.mark.parametrize("frame_id", ["", "c", "abc", "abcd", "abcdefg", "endoscope_optical_frame"])
@pytest.mark.parametrize("stamp_ns", [0, 999_999_999, 1_800_000_000_123_456_789])
def test_bytes_equal_the_serialised_message(frame_id, stamp_ns):
    for value, log_std in [(0.04, 0.01), (float("nan"), float("inf")), (float("inf"), 0.0),
                           (-1.5e-7, float("nan"))]:
        for state in ScaleState:
            estimate = ScaleEstimate(value, log_std, state, True)
            expected = serialize(scale_message(estimate, stamp_ns, frame_id))
            assert scale_message_cdr(estimate, stamp_ns, frame_id) == expected


def test_a_negative_stamp_is_refused():
    with pytest.raises(ValueError, match="non-negative"):
        scale_message_cdr(ScaleEstimate(0.04, 0.01, ScaleState.TRACKING, True), -1, "c")
