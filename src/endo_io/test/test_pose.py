"""endo_io.pose against closed forms and scipy.spatial.transform."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from scipy.spatial.transform import Rotation, Slerp

from endo_io.errors import PoseError
from endo_io.pose import (
    canonical_quaternion,
    interpolate_transform,
    interpolate_transforms,
    matrix_to_pose,
    matrix_to_quaternion,
    motion_onset,
    pose_to_matrix,
    quaternion_to_matrix,
    slerp,
)
from endo_io.stamp import ns_to_stamp


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_z(angle: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])


def transform(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def random_rotations(n: int, seed: int = 0) -> Rotation:
    return Rotation.random(n, rng=np.random.default_rng(seed))


@pytest.mark.parametrize("degrees", [0.0, 30.0, 90.0, 179.0, 180.0, -135.0])
def test_rotation_about_z_closed_form(degrees):
    angle = math.radians(degrees)
    np.testing.assert_allclose(quaternion_to_matrix(quat_z(angle)), rot_z(angle), atol=1e-15)
    q = matrix_to_quaternion(rot_z(angle))
    expected = canonical_quaternion(quat_z(angle))
    np.testing.assert_allclose(q, expected, atol=1e-15)
    assert q[3] >= 0.0


def test_matches_scipy_for_random_rotations():
    rotations = random_rotations(500)
    quats = rotations.as_quat()  # x, y, z, w
    np.testing.assert_allclose(quaternion_to_matrix(quats), rotations.as_matrix(), atol=1e-14)
    ours = matrix_to_quaternion(rotations.as_matrix())
    assert np.all(ours[:, 3] >= 0.0)
    np.testing.assert_allclose(ours, canonical_quaternion(quats), atol=1e-14)
    # single-matrix call agrees with the batched one
    np.testing.assert_array_equal(matrix_to_quaternion(rotations.as_matrix()[7]), ours[7])


def test_half_turns_are_canonical():
    for axis in np.eye(3):
        R = Rotation.from_rotvec(math.pi * axis).as_matrix()
        q = matrix_to_quaternion(R)
        np.testing.assert_allclose(q, np.append(axis, 0.0), atol=1e-15)
    # 2 n n^T - I for n = (0, 0.6, 0.8): a half turn written exactly, w == 0,
    # so the sign rule falls to the first non-zero of x, y, z
    R = np.array([[-1.0, 0.0, 0.0], [0.0, -0.28, 0.96], [0.0, 0.96, 0.28]])
    np.testing.assert_allclose(matrix_to_quaternion(R), [0.0, 0.6, 0.8, 0.0], atol=1e-15)
    np.testing.assert_allclose(quaternion_to_matrix([0.0, -0.6, -0.8, 0.0]), R, atol=1e-15)


def test_pose_round_trip():
    R = random_rotations(1, seed=3).as_matrix()[0]
    T = transform(R, [0.01, -0.25, 1.5])
    msg = matrix_to_pose(T, 1_700_000_000_000_000_001, "tracker")
    assert msg.header.frame_id == "tracker"
    assert msg.pose.orientation.w >= 0.0
    back, stamp_ns = pose_to_matrix(msg)
    assert stamp_ns == 1_700_000_000_000_000_001
    np.testing.assert_allclose(back, T, atol=1e-15)
    assert back[:3, 3].tolist() == [0.01, -0.25, 1.5]  # translation is exact


def test_pose_to_matrix_closed_form():
    msg = PoseStamped()
    msg.header.stamp = ns_to_stamp(42)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = 1.0, 2.0, 3.0
    q = quat_z(math.radians(90.0))
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = (-q).tolist()  # the other sign of the same rotation
    T, stamp_ns = pose_to_matrix(msg)
    assert stamp_ns == 42
    np.testing.assert_allclose(T, transform(rot_z(math.pi / 2), [1, 2, 3]), atol=1e-15)
    np.testing.assert_allclose(T @ [1.0, 0.0, 0.0, 1.0], [1.0, 3.0, 3.0, 1.0], atol=1e-15)


def test_pose_rejects_nan_and_non_unit_quaternions():
    msg = PoseStamped()
    msg.pose.orientation.w = 1.0005  # within the default 1e-3
    T, _ = pose_to_matrix(msg)
    np.testing.assert_allclose(T, np.eye(4), atol=1e-15)
    with pytest.raises(PoseError, match=r"tolerance 0\.0001"):
        pose_to_matrix(msg, tolerance=1e-4)
    msg.pose.orientation.w = 1.01
    with pytest.raises(PoseError, match="norm deviates from 1"):
        pose_to_matrix(msg)
    msg.pose.orientation.w = 0.0  # the all-zero default quaternion
    with pytest.raises(PoseError, match="norm deviates from 1 by 1"):
        pose_to_matrix(msg)
    msg.pose.orientation.w = math.nan
    with pytest.raises(PoseError, match="NaN"):
        pose_to_matrix(msg)
    msg.pose.orientation.w = 1.0
    msg.pose.position.y = math.nan
    with pytest.raises(PoseError, match="position is not finite"):
        pose_to_matrix(msg)


@pytest.mark.parametrize(
    ("T", "match"),
    [
        (np.eye(3), "shape"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
        (np.diag([1.1, 1.0, 1.0, 1.0]), "not orthonormal"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "bottom row"),
        (np.full((4, 4), np.nan), "NaN"),
    ],
)
def test_matrix_to_pose_rejects_bad_transforms(T, match):
    with pytest.raises(PoseError, match=match):
        matrix_to_pose(T, 0, "world")


def test_slerp_midpoint_of_0_and_90_degrees_is_45():
    q = slerp(quat_z(0.0), quat_z(math.pi / 2), 0.5)
    np.testing.assert_allclose(q, quat_z(math.pi / 4), atol=1e-15)
    np.testing.assert_allclose(quaternion_to_matrix(q), rot_z(math.pi / 4), atol=1e-15)


def test_slerp_takes_the_short_way_for_either_sign():
    q0, q1 = quat_z(math.radians(10.0)), quat_z(math.radians(50.0))
    expected = quat_z(math.radians(20.0))
    np.testing.assert_allclose(slerp(q0, q1, 0.25), expected, atol=1e-15)
    np.testing.assert_allclose(slerp(q0, -q1, 0.25), expected, atol=1e-15)
    np.testing.assert_allclose(slerp(-q0, q1, 0.25), expected, atol=1e-15)
    # 170 deg to -170 deg is a 20 deg step through 180 deg, not 340 deg back
    half = slerp(quat_z(math.radians(170.0)), quat_z(math.radians(-170.0)), 0.5)
    np.testing.assert_allclose(quaternion_to_matrix(half), rot_z(math.pi), atol=1e-15)


def test_slerp_matches_scipy_and_is_uniform_in_angle():
    rotations = random_rotations(2, seed=11)
    alphas = np.linspace(0.0, 1.0, 33)
    ours = slerp(rotations[0].as_quat(), rotations[1].as_quat(), alphas)
    reference = Slerp([0.0, 1.0], rotations)(alphas)
    np.testing.assert_allclose(ours, canonical_quaternion(reference.as_quat()), atol=1e-14)
    # the rotation angle from the start grows linearly with alpha
    total = (rotations[0].inv() * rotations[1]).magnitude()
    steps = (rotations[0].inv() * Rotation.from_quat(ours)).magnitude()
    np.testing.assert_allclose(steps, alphas * total, atol=1e-13)


def test_slerp_of_nearly_identical_quaternions():
    q0 = quat_z(0.3)
    for delta in (1e-6, 1e-9, 1e-12, 0.0):
        q1 = quat_z(0.3 + delta)
        q = slerp(q0, q1, 0.5)
        assert np.all(np.isfinite(q))
        assert abs(np.linalg.norm(q) - 1.0) < 1e-15
        np.testing.assert_allclose(q, quat_z(0.3 + delta / 2), atol=1e-15)


def test_slerp_rejects_bad_quaternions():
    with pytest.raises(PoseError, match="NaN"):
        slerp([0, 0, 0, math.nan], quat_z(0.0), 0.5)
    with pytest.raises(PoseError, match="norm deviates"):
        slerp([0, 0, 0, 2.0], quat_z(0.0), 0.5)


def test_interpolate_transform_against_scipy():
    rotations = random_rotations(2, seed=5)
    t_a, t_b = np.array([0.1, 0.2, 0.3]), np.array([-0.4, 0.9, 1.3])
    T0 = transform(rotations[0].as_matrix(), t_a)
    T1 = transform(rotations[1].as_matrix(), t_b)
    t0_ns, t1_ns = 1_700_000_000_000_000_000, 1_700_000_000_040_000_000  # 40 ms apart
    t_ns = t0_ns + 10_000_000  # a quarter of the way
    T = interpolate_transform(T0, t0_ns, T1, t1_ns, t_ns)
    expected_R = Slerp([0.0, 1.0], rotations)([0.25]).as_matrix()[0]
    np.testing.assert_allclose(T[:3, :3], expected_R, atol=1e-14)
    np.testing.assert_allclose(T[:3, 3], 0.75 * t_a + 0.25 * t_b, atol=1e-15)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(interpolate_transform(T0, t0_ns, T1, t1_ns, t0_ns), T0)
    np.testing.assert_array_equal(interpolate_transform(T0, t0_ns, T1, t1_ns, t1_ns), T1)


def test_interpolate_transform_time_checks():
    T0, T1 = np.eye(4), transform(rot_z(0.2), [1.0, 0.0, 0.0])
    with pytest.raises(PoseError, match="same time"):
        interpolate_transform(T0, 5, T1, 5, 5)
    with pytest.raises(PoseError, match="outside"):
        interpolate_transform(T0, 0, T1, 10, 11)
    T = interpolate_transform(T0, 0, T1, 10, 20, extrapolate=True)
    np.testing.assert_allclose(T, transform(rot_z(0.4), [2.0, 0.0, 0.0]), atol=1e-15)


def _stream(seed: int = 0, count: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A tracker-like stream with the awkward cases.

    60 Hz with jitter, two long dropouts, rotations that jump (both
    quaternion signs, large angles) and one repeated pose.
    """
    rng = np.random.default_rng(seed)
    steps = rng.integers(14_000_000, 19_000_000, count - 1)
    dropouts = [count // 4, 2 * count // 3]
    steps[dropouts] = [80_000_000, 250_000_000]
    stamps = 1_700_000_000_000_000_000 + np.concatenate([[0], np.cumsum(steps)])
    rotations = Rotation.from_rotvec(rng.normal(0.0, 1.2, (count, 3))).as_matrix()
    rotations[count // 2] = rotations[count // 2 - 1]  # identical: SLERP's linear branch
    poses = np.stack([transform(R, rng.normal(0.0, 0.2, 3)) for R in rotations])
    return stamps.astype(np.int64), poses


def test_interpolate_transforms_agrees_with_the_scalar_interpolation():
    stamps, poses = _stream()
    rng = np.random.default_rng(1)
    query = np.concatenate(
        [
            rng.integers(stamps[0] - 30_000_000, stamps[-1] + 30_000_000, 400),
            stamps[::3],  # exactly on samples
            stamps[[10, 26]] - 1,  # inside the dropouts
            [stamps[0] - 1, stamps[-1] + 1],  # just outside the stream
        ]
    )
    max_gap_ns = 60_000_000
    result, valid = interpolate_transforms(stamps, poses, query, max_gap_ns)
    assert result.shape == (len(query), 4, 4) and result.dtype == np.float64
    checked = 0
    for k, t in enumerate(query.tolist()):
        after = int(np.searchsorted(stamps, t, side="right"))
        if after > 0 and stamps[after - 1] == t:
            assert valid[k]
            np.testing.assert_array_equal(result[k], poses[after - 1])
        elif 0 < after < len(stamps) and stamps[after] - stamps[after - 1] <= max_gap_ns:
            assert valid[k]
            expected = interpolate_transform(
                poses[after - 1], int(stamps[after - 1]), poses[after], int(stamps[after]), t
            )
            np.testing.assert_allclose(result[k], expected, rtol=0.0, atol=1e-12)
            checked += 1
        else:
            assert not valid[k]
            assert np.all(np.isnan(result[k]))
    assert checked > 200
    assert valid.sum() < len(query) - 4  # dropouts and the ends are invalid


def test_interpolate_transforms_against_scipy_slerp():
    stamps, poses = _stream(seed=2, count=12)
    bracket = np.arange(len(stamps) - 1)
    bracket = bracket[np.diff(stamps) <= 60_000_000]
    alpha = np.linspace(0.05, 0.95, len(bracket))
    offsets = np.round(alpha * (stamps[bracket + 1] - stamps[bracket])).astype(np.int64)
    result, valid = interpolate_transforms(stamps, poses, stamps[bracket] + offsets, 60_000_000)
    assert valid.all()
    fraction = offsets / (stamps[bracket + 1] - stamps[bracket])
    for k, i in enumerate(bracket):
        pair = Rotation.from_matrix(poses[i : i + 2, :3, :3])
        expected_R = Slerp([0.0, 1.0], pair)([fraction[k]]).as_matrix()[0]
        np.testing.assert_allclose(result[k, :3, :3], expected_R, atol=1e-13)
        expected_t = (1 - fraction[k]) * poses[i, :3, 3] + fraction[k] * poses[i + 1, :3, 3]
        np.testing.assert_allclose(result[k, :3, 3], expected_t, atol=1e-15)
        np.testing.assert_array_equal(result[k, 3], [0, 0, 0, 1])


def test_interpolate_transforms_gap_rule_and_edge_cases():
    T0, T1 = np.eye(4), transform(rot_z(math.pi / 2), [0.01, 0.0, 0.0])
    stamps = np.array([0, 16, 200, 216, 216], dtype=np.int64)
    poses = np.stack([T0, T1, T0, T0, T1])
    query = np.array([8, 16, 100, 216, -1, 300, 208], dtype=np.int64)
    result, valid = interpolate_transforms(stamps, poses, query, max_gap_ns=16)
    assert valid.tolist() == [True, True, False, True, False, False, True]
    np.testing.assert_allclose(result[0], transform(rot_z(math.pi / 4), [0.005, 0, 0]), atol=1e-15)
    np.testing.assert_array_equal(result[1], T1)
    np.testing.assert_array_equal(result[3], T1)  # of equal stamps the last sample counts
    # a gap of exactly max_gap_ns is bridged, one longer is not
    assert not interpolate_transforms(stamps, poses, query, max_gap_ns=15)[1][0]
    # empty stream or no queries
    empty, none = interpolate_transforms(np.zeros(0, np.int64), np.zeros((0, 4, 4)), query, 10)
    assert empty.shape == (7, 4, 4) and not none.any()
    assert interpolate_transforms(stamps, poses, np.zeros(0, np.int64), 10)[0].shape == (0, 4, 4)


@pytest.mark.parametrize(
    ("stamps", "poses", "query", "gap", "match"),
    [
        ([10, 0], np.stack([np.eye(4)] * 2), [5], 10, "sorted"),
        ([0, 10], np.stack([np.eye(4)] * 3), [5], 10, "3 poses"),
        ([0.0, 10.0], np.stack([np.eye(4)] * 2), [5], 10, "integer"),
        ([0, 10], np.stack([np.eye(4)] * 2), [5.0], 10, "integer"),
        ([0, 10], np.eye(4), [5], 10, "shape"),
        ([0, 10], np.stack([np.eye(4), np.diag([1.0, 1.0, -1.0, 1.0])]), [5], 10, "reflection"),
        ([0, 10], np.stack([np.eye(4), np.full((4, 4), np.nan)]), [5], 10, "NaN"),
        ([0, 10], np.stack([np.eye(4)] * 2), [5], -1, "max_gap_ns"),
    ],
)
def test_interpolate_transforms_rejects_bad_input(stamps, poses, query, gap, match):
    with pytest.raises(PoseError, match=match):
        interpolate_transforms(np.array(stamps), poses, np.array(query), gap)


def test_invert_transform_is_the_rigid_inverse():
    from scipy.spatial.transform import Rotation

    from endo_io.pose import invert_transform

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, 0.2, -0.1]).as_matrix()
    T[:3, 3] = [0.4, -1.0, 2.0]
    np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-14)
    stack = np.stack([T, np.eye(4)])
    np.testing.assert_allclose(invert_transform(stack)[0], np.linalg.inv(T), atol=1e-14)
    np.testing.assert_array_equal(invert_transform(stack)[1], np.eye(4))


def test_motion_onset_is_the_first_position_that_far_from_the_start() -> None:
    # a wobble back and forth under 2 mm, then a straight move along a diagonal
    wobble = np.array([0.0, 1.5e-3, -1.5e-3, 1.0e-3])
    steps = np.concatenate([wobble, np.linspace(1.3e-3, 4.1e-3, 8)])
    start = np.array([0.01, 0.02, 0.03])
    positions = start + np.outer(steps, np.ones(3) / math.sqrt(3.0))
    onset = motion_onset(positions, 2e-3)
    assert onset is not None
    assert np.linalg.norm(positions[onset] - positions[0]) >= 2e-3
    assert np.all(np.linalg.norm(positions[:onset] - positions[0], axis=1) < 2e-3)
    assert onset == 6  # 1.3, 1.7, then 2.1 mm along the diagonal
    assert motion_onset(positions, 1.0) is None
    assert motion_onset(np.empty((0, 3)), 2e-3) is None
    with pytest.raises(PoseError, match="shape"):
        motion_onset(np.zeros((4, 2)), 2e-3)
    with pytest.raises(PoseError, match="finite"):
        motion_onset(positions, float("nan"))
