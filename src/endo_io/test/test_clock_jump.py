"""endo_io.clock_jump.ClockJumpDetector: loops, restarts, one wild stamp, silences."""

from __future__ import annotations

import pytest

from endo_io.clock_jump import ClockJump, ClockJumpDetector
from endo_io.errors import FutureStampError, StampOrderError

MS = 1_000_000
S = 1_000 * MS


def _stream(detector, stamps, arrivals=None):
    """Feed stamps; return (accepted, jumps, dropped) lists of stamps."""
    accepted, jumps, dropped = [], [], []
    for i, stamp in enumerate(stamps):
        arrival = None if arrivals is None else arrivals[i]
        try:
            jump = detector.check(stamp, arrival)
        except StampOrderError:
            dropped.append(stamp)
            continue
        if jump is not None:
            jumps.append(jump)
        accepted.append(stamp)
    return accepted, jumps, dropped


def test_a_stream_in_order_passes_untouched():
    stamps = [10 * S + k * 16 * MS for k in range(100)]
    accepted, jumps, dropped = _stream(ClockJumpDetector(), stamps)
    assert accepted == stamps and not jumps and not dropped


def test_a_loop_is_one_jump_back_and_the_stream_resumes():
    one_pass = [10 * S + k * 33 * MS for k in range(90)]  # a 3 s bag
    accepted, jumps, dropped = _stream(ClockJumpDetector(), one_pass * 3)
    assert len(accepted) == 270 and not dropped
    assert jumps == [ClockJump(one_pass[-1], one_pass[0])] * 2
    assert jumps[0].delta_ns == -89 * 33 * MS
    assert jumps[0].describe("pose time").startswith("pose time jumped back 2.937 s")


def test_one_future_stamp_is_dropped_and_locks_nothing_out():
    good = [10 * S + k * 16 * MS for k in range(181)]
    stamps = [*good[:60], good[59] + 3600 * S, *good[60:]]
    detector = ClockJumpDetector()
    accepted, jumps, dropped = _stream(detector, stamps)
    assert dropped == [good[59] + 3600 * S]
    assert accepted == good and not jumps
    assert detector.reference_ns == good[-1]


def test_one_past_stamp_costs_at_most_two_samples():
    good = [100 * S + k * 16 * MS for k in range(181)]
    stamps = [*good[:60], good[59] - 3600 * S, *good[60:]]
    accepted, jumps, dropped = _stream(ClockJumpDetector(), stamps)
    # back to the wild stamp (a jump back), then forward again: suspect, confirmed
    assert [j.delta_ns < 0 for j in jumps] == [True, False]
    assert len(dropped) == 1 and set(good) - set(accepted) == {good[60]}


def test_a_restart_forward_is_confirmed_by_its_second_sample():
    old = [10 * S + k * 16 * MS for k in range(30)]
    new = [5000 * S + k * 16 * MS for k in range(30)]
    accepted, jumps, dropped = _stream(ClockJumpDetector(), old + new)
    assert dropped == [new[0]]
    assert jumps == [ClockJump(old[-1], new[1])]
    assert accepted == old + new[1:]


def test_out_of_order_within_the_tolerance_is_refused_then_a_short_loop_is_confirmed():
    detector = ClockJumpDetector(back_tolerance_ns=1 * S)
    detector.check(100 * MS)
    with pytest.raises(StampOrderError, match="16000000 ns before"):
        detector.check(84 * MS)
    with pytest.raises(StampOrderError):
        detector.check(100 * MS)  # a repeat of the newest continues nothing
    assert detector.check(117 * MS) is None
    # a 0.3 s loop (shorter than the tolerance): one sample lost, then a jump
    with pytest.raises(StampOrderError):
        detector.check(0)
    jump = detector.check(16 * MS)
    assert jump == ClockJump(117 * MS, 16 * MS)
    assert detector.jumps == 1


def test_a_long_silence_on_both_clocks_is_not_a_jump():
    detector = ClockJumpDetector(forward_tolerance_ns=2 * S)
    assert detector.check(10 * S, arrival_ns=1 * S) is None
    # 60 s of silence: stamps and arrivals agree -> in order
    assert detector.check(70 * S, arrival_ns=61 * S) is None
    # 60 s in stamps but 16 ms of arrival: a wild stamp
    with pytest.raises(FutureStampError):
        detector.check(130 * S, arrival_ns=61 * S + 16 * MS)
    assert detector.check(70 * S + 16 * MS, arrival_ns=61 * S + 16 * MS) is None


def test_reset_starts_a_new_timeline():
    detector = ClockJumpDetector()
    detector.check(100 * S)
    detector.reset()
    assert detector.check(1 * S) is None and detector.reference_ns == 1 * S
    with pytest.raises(ValueError):
        ClockJumpDetector(forward_tolerance_ns=0)


def test_late_frames_are_told_apart_from_a_jump_and_leave_the_stream_untouched():
    # A frame stream on a loaded machine: 66 and 33 ms are paired after 100 ms was
    # processed. A node skips what is_late says is late instead of checking it, so
    # two late frames in a row do not confirm a "jump" (which check would).
    detector = ClockJumpDetector(back_tolerance_ns=1 * S)
    assert not detector.is_late(0)  # no reference yet
    detector.check(100 * MS)
    late = [s for s in (66 * MS, 33 * MS) if detector.is_late(s)]
    assert late == [66 * MS, 33 * MS]
    assert detector.is_late(100 * MS)  # a repeat of the newest
    assert not detector.is_late(133 * MS) and detector.check(133 * MS) is None
    assert not detector.is_late(133 * MS - 2 * S)  # beyond the tolerance: a jump
    assert detector.check(133 * MS - 2 * S) == ClockJump(133 * MS, 133 * MS - 2 * S)
    assert detector.jumps == 1
    # without the check first, the two late frames would have made a jump
    naive = ClockJumpDetector(back_tolerance_ns=1 * S)
    naive.check(100 * MS)
    with pytest.raises(StampOrderError):
        naive.check(33 * MS)
    assert naive.check(66 * MS) == ClockJump(100 * MS, 66 * MS)
