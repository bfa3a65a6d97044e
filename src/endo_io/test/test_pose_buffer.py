"""endo_io.pose_buffer.PoseBuffer: interpolation, bounded memory, typed refusals, clock jumps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from endo_io.errors import (
    ClockJumpError,
    FutureStampError,
    PoseBeforeStreamError,
    PoseError,
    PoseGapError,
    PoseNotYetError,
    PoseOrderError,
    PoseTooOldError,
)
from endo_io.pose import rigid_transform
from endo_io.pose_buffer import PoseBuffer

MS = 1_000_000


def _stream(n: int, period_ns: int = 10 * MS):
    stamps = [1_000 * MS + i * period_ns for i in range(n)]
    poses = [rigid_transform((0.0, 0.02 * i, 0.01 * i), (0.001 * i, 0.0, 0.05)) for i in range(n)]
    return stamps, poses


def test_query_interpolates_like_scipy_slerp():
    buffer = PoseBuffer(max_gap_ns=20 * MS)
    stamps, poses = _stream(5)
    for s, T in zip(stamps, poses, strict=True):
        buffer.insert(s, T)
    np.testing.assert_array_equal(buffer.query(stamps[2]), poses[2])
    t = stamps[1] + 3 * MS
    T = buffer.query(t)
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix([poses[1][:3, :3], poses[2][:3, :3]]))
    np.testing.assert_allclose(T[:3, :3], slerp([0.3]).as_matrix()[0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], 0.7 * poses[1][:3, 3] + 0.3 * poses[2][:3, 3], atol=1e-15)


def test_refusals_are_typed():
    buffer = PoseBuffer(capacity=3, max_gap_ns=15 * MS)
    with pytest.raises(PoseNotYetError):
        buffer.query(0)
    stamps, poses = _stream(5)
    for s, T in zip(stamps, poses, strict=True):
        buffer.insert(s, T)
    assert len(buffer) == 3 and buffer.oldest_ns == stamps[2]  # bounded
    with pytest.raises(PoseTooOldError, match="evicted") as refused:
        buffer.query(stamps[1])
    assert not isinstance(refused.value, PoseBeforeStreamError)  # it was held once
    with pytest.raises(PoseNotYetError):
        buffer.query(stamps[4] + 1)
    np.testing.assert_array_equal(buffer.query(stamps[4] + 2 * MS, tolerance_ns=2 * MS), poses[4])
    buffer.insert(stamps[4] + 100 * MS, poses[0])
    with pytest.raises(PoseGapError):
        buffer.query(stamps[4] + 50 * MS)


def test_bad_poses_and_order():
    buffer = PoseBuffer()
    stamps, poses = _stream(3)
    buffer.insert(stamps[1], poses[1])
    bad = poses[0].copy()
    bad[0, 0] = np.nan
    with pytest.raises(PoseError):
        buffer.insert(stamps[2], bad)
    with pytest.raises(PoseOrderError):  # a duplicate
        buffer.insert(stamps[1], poses[1])
    assert len(buffer) == 1
    # 10 ms back: the stream restarted; the buffer holds the new timeline only
    with pytest.raises(ClockJumpError, match=r"jumped back 0\.010 s"):
        buffer.insert(stamps[0], poses[0])
    assert len(buffer) == 1 and buffer.newest_ns == stamps[0]


def test_a_stamp_before_the_streams_first_pose_is_told_apart_from_an_evicted_one():
    # issue 16: the first image of a recording (and of every loop) is 4 ms before the
    # first pose; that is the stream's start (PoseBeforeStreamError), not a pose lost
    buffer = PoseBuffer(capacity=4, max_gap_ns=20 * MS)
    stamps, poses = _stream(3)
    for s, T in zip(stamps, poses, strict=True):
        buffer.insert(s, T)
    with pytest.raises(PoseBeforeStreamError, match=r"4\.0 ms before the pose stream's first"):
        buffer.query(stamps[0] - 4 * MS)
    # a loop: the same stamps again, the buffer restarts on them
    with pytest.raises(ClockJumpError):
        buffer.insert(stamps[0], poses[0])
    with pytest.raises(PoseBeforeStreamError):
        buffer.query(stamps[0] - 4 * MS)
    for s, T in zip(stamps[1:], poses[1:], strict=True):
        buffer.insert(s, T)
    np.testing.assert_allclose(buffer.query(stamps[1] + 5 * MS)[:3, 3],
                               0.5 * (poses[1][:3, 3] + poses[2][:3, 3]), atol=1e-15)
    # once poses are evicted, a stamp before the oldest held is too old
    buffer.insert(stamps[2] + 10 * MS, poses[2])
    buffer.insert(stamps[2] + 20 * MS, poses[2])
    with pytest.raises(PoseTooOldError) as refused:
        buffer.query(stamps[0] - 4 * MS)
    assert not isinstance(refused.value, PoseBeforeStreamError)


def test_backward_jump_resets_and_future_sample_does_not_lock_out():
    buffer = PoseBuffer(jump_tolerance_ns=500 * MS)
    stamps, poses = _stream(4)
    for s, T in zip(stamps, poses, strict=True):
        buffer.insert(s, T)
    # a bag loop: back to the start
    with pytest.raises(ClockJumpError):
        buffer.insert(stamps[0] - 3_000 * MS, poses[0])
    assert len(buffer) == 1 and buffer.newest_ns == stamps[0] - 3_000 * MS
    # one future-stamped sample, then the good stream again: refused, nothing is reset
    buffer.clear()
    buffer.insert(stamps[0], poses[0])
    with pytest.raises(FutureStampError):
        buffer.insert(stamps[0] + 3_600_000 * MS, poses[1])
    buffer.insert(stamps[1], poses[1])
    buffer.insert(stamps[2], poses[2])
    assert len(buffer) == 3
    np.testing.assert_allclose(buffer.query(stamps[2]), poses[2])


def test_short_loop_within_the_tolerance_resets_after_one_pose():
    # a loop shorter than the jump tolerance: the first pose of the new pass is
    # out of order, the second confirms the restart, and the buffer resumes
    buffer = PoseBuffer(jump_tolerance_ns=1_000 * MS)
    stamps, poses = _stream(4)
    for s, T in zip(stamps, poses, strict=True):
        buffer.insert(s, T)
    with pytest.raises(PoseOrderError):
        buffer.insert(stamps[0], poses[0])
    with pytest.raises(ClockJumpError, match="pose time jumped back"):
        buffer.insert(stamps[1], poses[1])
    buffer.insert(stamps[2], poses[2])
    assert len(buffer) == 2 and buffer.oldest_ns == stamps[1]


def test_pose_after_a_long_silence_is_taken_when_arrival_times_agree():
    buffer = PoseBuffer(forward_tolerance_ns=2_000 * MS)
    stamps, poses = _stream(2)
    buffer.insert(stamps[0], poses[0], arrival_ns=0)
    # 60 s later on both clocks: a tracker occlusion, not a jump
    buffer.insert(stamps[0] + 60_000 * MS, poses[1], arrival_ns=60_000 * MS)
    assert len(buffer) == 2
