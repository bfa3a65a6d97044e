"""Stamp matching of image and camera_info streams."""

from __future__ import annotations

import pytest

from endo_io.stamp_matching import StampMatcher


def test_pairs_come_out_in_either_arrival_order():
    matcher: StampMatcher[str, str] = StampMatcher()
    assert matcher.add_first(100, "image@100") is None
    pair = matcher.add_second(100, "info@100")
    assert pair is not None and (pair.stamp_ns, pair.first, pair.second) == (
        100, "image@100", "info@100"
    )
    assert matcher.add_second(200, "info@200") is None
    pair = matcher.add_first(200, "image@200")
    assert pair is not None and pair.second == "info@200"
    assert matcher.pending() == (0, 0)


def test_different_stamps_do_not_pair_and_older_ones_are_dropped_after_a_match():
    matcher: StampMatcher[str, str] = StampMatcher()
    matcher.add_first(100, "image@100")  # its camera_info was lost
    matcher.add_second(150, "info@150")  # its image was lost
    assert matcher.add_first(200, "image@200") is None
    pair = matcher.add_second(200, "info@200")
    assert pair is not None and pair.first == "image@200"
    assert matcher.pending() == (0, 0)
    assert matcher.dropped == 2


def test_queue_is_bounded_when_one_stream_stops():
    matcher: StampMatcher[int, int] = StampMatcher(queue_size=3)
    for stamp in range(10):
        assert matcher.add_first(stamp, stamp) is None
    assert matcher.pending() == (3, 0)
    assert matcher.dropped == 7
    assert matcher.add_second(9, -9) is not None
    assert matcher.add_second(5, -5) is None  # dropped long ago


def test_tolerance_pairs_the_nearest_stamp_within_it():
    matcher: StampMatcher[str, str] = StampMatcher(tolerance_ns=1_000)
    matcher.add_second(10_000, "info@10000")
    matcher.add_second(10_900, "info@10900")
    pair = matcher.add_first(10_800, "image@10800")
    assert pair is not None and pair.second == "info@10900" and pair.stamp_ns == 10_800
    assert matcher.add_first(20_000, "image@20000") is None


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="queue_size"):
        StampMatcher(queue_size=0)
    with pytest.raises(ValueError, match="tolerance_ns"):
        StampMatcher(tolerance_ns=-1)
