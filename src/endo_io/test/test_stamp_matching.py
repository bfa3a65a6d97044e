"""Stamp matching of image and camera_info streams."""

from __future__ import annotations

import pytest

from endo_io.stamp_matching import MISMATCH_ARRIVALS, StampMatcher


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


def test_a_loop_drops_the_old_timelines_leftovers_so_they_never_pair_with_the_new():
    ms = 1_000_000
    matcher: StampMatcher[str, str] = StampMatcher(queue_size=20)
    for k in range(90):  # a 3 s bag; the last image's camera_info was lost
        stamp = 10_000 * ms + k * 33 * ms
        matcher.add_first(stamp, f"pass1 image {k}")
        if k != 89:
            assert matcher.add_second(stamp, f"pass1 info {k}") is not None
    assert matcher.pending() == (1, 0)
    # second pass: same stamps again; its frame 89 must pair with pass 2's image
    pairs = []
    for k in range(90):
        stamp = 10_000 * ms + k * 33 * ms
        pairs.append(matcher.add_second(stamp, f"pass2 info {k}"))
        pairs.append(matcher.add_first(stamp, f"pass2 image {k}"))
    matched = [p for p in pairs if p is not None]
    assert len(matched) == 90 and matcher.clock_jumps == 2
    assert all(p.first.startswith("pass2") and p.second.startswith("pass2") for p in matched)
    assert matcher.pending() == (0, 0)


def test_two_streams_stamped_apart_are_named_once_each_brought_enough_unpaired():
    # a driver stamping camera_info 2 ms before its image: nothing ever pairs
    matcher: StampMatcher[int, int] = StampMatcher(queue_size=10)
    period = 33_333_333
    for k in range(MISMATCH_ARRIVALS):
        assert matcher.mismatch("/image", "/info") is None
        matcher.add_second(k * period - 2_000_000, k)
        matcher.add_first(k * period, k)
    line = matcher.mismatch("/image", "/info")
    assert line is not None
    assert line.startswith(f"{MISMATCH_ARRIVALS} /image and {MISMATCH_ARRIVALS} /info messages")
    assert "2.000 ms apart" in line and "stamp_tolerance" in line
    # the same streams with a tolerance above the offset pair, and the line goes
    matcher.tolerance_ns = 3_000_000
    k = MISMATCH_ARRIVALS
    matcher.add_second(k * period - 2_000_000, k)
    assert matcher.add_first(k * period, k) is not None
    assert matcher.mismatch("/image", "/info") is None


def test_one_stream_that_stops_is_not_a_mismatch():
    matcher: StampMatcher[int, int] = StampMatcher(queue_size=10)
    for k in range(3 * MISMATCH_ARRIVALS):  # camera_info goes on, the images stopped
        matcher.add_second(k * 1000, k)
    assert matcher.dropped > MISMATCH_ARRIVALS and matcher.mismatch("/image", "/info") is None
