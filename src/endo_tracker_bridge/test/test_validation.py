"""Rejection of bad samples: NaN, non-unit quaternions, hidden tools, time, speed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_tracker_bridge.conventions import LengthUnit, transform_from_quaternion
from endo_tracker_bridge.errors import (
    NonFinitePoseError,
    NonOrthonormalRotationError,
    NonUnitQuaternionError,
    SpeedLimitError,
    TimeWentBackwardsError,
    ToolNotVisibleError,
)
from endo_tracker_bridge.sample import ToolStatus, TrackerSample
from endo_tracker_bridge.validation import (
    SampleGate,
    SpeedLimits,
    check_rotation_matrix,
    check_unit_quaternion,
)

MS = 1_000_000


def _sample(stamp_ms, x_m=0.0, angle_deg=0.0, tool="scope", status=ToolStatus.VISIBLE):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", angle_deg, degrees=True).as_matrix()
    T[0, 3] = x_m
    return TrackerSample(stamp_ns=stamp_ms * MS, T_tracker_marker=T, tool_id=tool, status=status)


def test_nan_is_rejected():
    with pytest.raises(NonFinitePoseError, match="translation is not finite"):
        transform_from_quaternion(
            np.array([0, 0, 0, 1.0]), np.array([1.0, np.nan, 0.0]), LengthUnit.MILLIMETRE
        )
    with pytest.raises(NonFinitePoseError, match="quaternion"):
        check_unit_quaternion(np.array([np.nan, 0, 0, 1.0]))
    T = np.eye(4)
    T[2, 3] = np.inf
    with pytest.raises(NonFinitePoseError):
        SampleGate().check(TrackerSample(stamp_ns=1, T_tracker_marker=T, tool_id="a"))


def test_non_unit_quaternion_is_rejected_and_near_unit_is_normalised():
    with pytest.raises(NonUnitQuaternionError, match=r"norm 1\.0100"):
        check_unit_quaternion(np.array([0.0, 0.0, 0.0, 1.01]))
    with pytest.raises(NonUnitQuaternionError):
        check_unit_quaternion(np.array([0.0, 0.0, 0.0, 0.5]), tolerance=0.1)
    q = check_unit_quaternion(np.array([0.0, 0.0, 0.0, 1.0004]))
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    # a looser tolerance accepts what the default rejects
    q = check_unit_quaternion(np.array([0.0, 0.0, 0.0, 1.01]), tolerance=0.02)
    np.testing.assert_allclose(q, [0, 0, 0, 1.0])


def test_non_rotation_matrix_is_rejected():
    with pytest.raises(NonOrthonormalRotationError):
        check_rotation_matrix(np.diag([1.0, 1.0, 1.1]))
    with pytest.raises(NonOrthonormalRotationError, match="det"):
        check_rotation_matrix(np.diag([1.0, 1.0, -1.0]))


def test_missing_or_disabled_tool_is_rejected():
    gate = SampleGate()
    with pytest.raises(ToolNotVisibleError, match="missing"):
        gate.check(_sample(0, status=ToolStatus.MISSING))
    with pytest.raises(ToolNotVisibleError, match="disabled"):
        gate.check(_sample(0, status=ToolStatus.DISABLED))
    assert gate.check(_sample(1)).stamp_ns == 1 * MS


def test_a_repeated_stamp_is_rejected_and_a_step_back_restarts_the_tool():
    gate = SampleGate()
    gate.check(_sample(100))
    with pytest.raises(TimeWentBackwardsError, match="0 ns before or at"):
        gate.check(_sample(100))
    # the reference stays the last accepted sample; a later one passes
    assert gate.check(_sample(117)).stamp_ns == 117 * MS
    # 16 ms back: a restart of the tool's stream, accepted with its history reset
    result = gate.admit(_sample(101))
    assert result.clock_jump is not None and result.clock_jump.delta_ns == -16 * MS
    assert gate.check(_sample(118)).stamp_ns == 118 * MS
    # tools are independent
    assert gate.check(_sample(50, tool="pointer")).tool_id == "pointer"
    # a gate given a back tolerance still drops a step back within it
    tolerant = SampleGate(back_tolerance_ns=1_000 * MS)
    tolerant.check(_sample(100))
    with pytest.raises(TimeWentBackwardsError, match="16000000 ns before"):
        tolerant.check(_sample(84))


def test_a_loop_seen_as_a_short_step_back_is_a_restart_not_a_drop():
    # issue 16: after a respawn under load the bridge saw a looped bag as a 0.7 s step
    # back; under the old 1 s tolerance that sample was dropped (TimeWentBackwardsError,
    # an [ERROR] line) until the next one confirmed the restart
    before = [_sample(1_000 + 16 * k, x_m=0.0005 * k) for k in range(60)]  # up to 1.944 s
    after = [_sample(1_244 + 16 * k, x_m=0.0005 * k) for k in range(60)]  # 0.700 s back
    accepted, jumps, causes = _run(SampleGate(), [*before, *after])
    assert not causes and len(accepted) == 120
    assert [j.delta_ns for j in jumps] == [-700 * MS]


def test_speed_jumps_are_rejected():
    gate = SampleGate(SpeedLimits(linear_m_s=1.0, angular_deg_s=360.0))
    gate.check(_sample(0))
    # 10 mm in 16 ms = 0.625 m/s: fine
    gate.check(_sample(16, x_m=0.010))
    # 50 mm more in the next 16 ms = 3.1 m/s: a glitch
    with pytest.raises(SpeedLimitError, match=r"moved 50.0 mm in 16.0 ms"):
        gate.check(_sample(32, x_m=0.060))
    # 10° in 16 ms = 625°/s > 360°/s
    with pytest.raises(SpeedLimitError, match="turned"):
        gate.check(_sample(32, x_m=0.010, angle_deg=10.0))
    # after the glitch the stream resumes against the last good sample
    assert gate.check(_sample(48, x_m=0.012, angle_deg=2.0)).stamp_ns == 48 * MS


def test_millimetres_read_as_metres_are_named_in_the_rejection():
    # an NDI driver publishing mm with the bridge left at ros_unit m: a scope 1.3 m from
    # the camera moving 0.5 mm per 8.3 ms (60 mm/s) is read as 1300 m moving 60 m/s
    gate = SampleGate()
    gate.check(_sample(0, x_m=1300.0))
    with pytest.raises(SpeedLimitError) as caught:
        gate.check(_sample(8, x_m=1300.5))
    assert str(caught.value) == (
        "tool 'scope' moved 500.0 mm in 8.0 ms (62.50 m/s > limit 2 m/s); the tool is 1300 m "
        "from the tracker: millimetres read as metres? (the bridge's ros_unit / igtl_unit / "
        "csv_unit: mm)")
    # the same stream in metres passes, and a glitch 1.3 m away gets no hint
    gate = SampleGate()
    assert [gate.check(_sample(8 * k, x_m=1.3 + 0.0005 * k)).stamp_ns for k in range(3)] == [
        0, 8 * MS, 16 * MS]
    with pytest.raises(SpeedLimitError, match=r"m/s\)$"):
        gate.check(_sample(24, x_m=1.4))


def _run(gate, samples):
    """Feed samples; return (accepted stamps, clock jumps, causes of drops)."""
    accepted, jumps, causes = [], [], []
    for sample in samples:
        try:
            result = gate.admit(sample)
        except Exception as error:  # the test counts every cause
            causes.append(type(error).__name__)
            continue
        accepted.append(result.sample.stamp_ns)
        if result.clock_jump is not None:
            jumps.append(result.clock_jump)
    return accepted, jumps, causes


def test_one_future_stamped_pose_does_not_lock_the_tool_out():
    # issue 16: 60 good poses, one at +3600 s, 120 good ones -> the 120 pass
    good = [_sample(1_000 + 16 * k, x_m=0.0001 * k) for k in range(180)]
    future = _sample(1_000 + 16 * 59 + 3_600_000, x_m=0.0059)
    accepted, jumps, causes = _run(SampleGate(), [*good[:60], future, *good[60:]])
    assert causes == ["FutureStampError"]
    assert accepted == [s.stamp_ns for s in good] and not jumps


def test_a_looped_recording_resets_the_gate_and_every_pass_is_accepted():
    one_pass = [_sample(1_000 + 16 * k, x_m=0.0005 * k) for k in range(180)]  # 3 s, 3 cm
    accepted, jumps, causes = _run(SampleGate(), one_pass * 3)
    # the loop jumps back 3 cm in no time: without the reset, a speed or time glitch
    assert len(accepted) == 540 and not causes
    assert [j.delta_ns for j in jumps] == [-179 * 16 * MS] * 2


def test_a_restarted_driver_is_accepted_from_its_second_sample():
    before = [_sample(5_000_000 + 16 * k) for k in range(30)]
    after = [_sample(1_000 + 16 * k, x_m=0.05) for k in range(30)]  # earlier clock, moved
    accepted, jumps, causes = _run(SampleGate(), [*before, *after])
    assert not causes and len(jumps) == 1 and len(accepted) == 60
    later = [_sample(9_000_000 + 16 * k, x_m=0.05) for k in range(30)]  # later clock
    accepted, jumps, causes = _run(SampleGate(), [*before, *later])
    assert causes == ["FutureStampError"] and len(jumps) == 1 and len(accepted) == 59
