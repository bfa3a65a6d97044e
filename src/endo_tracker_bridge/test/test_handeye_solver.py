"""The hand–eye solver on synthetic correspondences with known ground truth.

A checkerboard fixed in the tracker frame is seen by a camera rigidly fixed
25 cm from the tracked marker (a rigid endoscope). The camera moves around
the board; the tracker samples the marker at 60 Hz with noise, drops samples
and stamps them late by a fixed latency; images come at 30 fps and their
corners are the exact projections plus pixel noise.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_io.pose import invert_transform, rigid_transform
from endo_tracker_bridge.errors import HandEyeError
from endo_tracker_bridge.handeye import (
    CLOSED_FORM_MAX_VIEWS,
    METHODS,
    MS,
    OffsetSearch,
    board_view,
    calibrate_hand_eye,
    detect_checkerboard,
    marker_poses_at,
    solve_hand_eye,
)
from endo_tracker_bridge.synthetic import (
    BOARD,
    CAMERA,
    EPOCH_NS,
    T_MARKER_CAMERA,
    T_TRACKER_TARGET,
    board_pose,
    camera_pose,
    synthetic_recording,
    transform_error,
)

# AX = XB notation: X the hand–eye transform, W the board in the tracker frame
X_TRUE = T_MARKER_CAMERA
W_TRUE = T_TRACKER_TARGET


def _errors(T_estimated):
    return transform_error(X_TRUE, T_estimated)


def _noise_free_views(count, seed=3, spread_rad=0.5):
    """Marker poses with the board fixed (A_i X B_i = W exactly), 1 m from the tracker."""
    rng = np.random.default_rng(seed)
    A = np.stack(
        [
            rigid_transform(
                rng.normal(0, spread_rad, 3), rng.normal(0, 0.1, 3) + np.array([0.0, 0.0, -1.0])
            )
            for _ in range(count)
        ]
    )
    return A, invert_transform(A @ X_TRUE) @ W_TRUE


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    ("count", "spread_rad"),
    [(12, 0.5), (12, 1.5), (CLOSED_FORM_MAX_VIEWS + 30, 0.5)],
    ids=["12-views", "12-views-large-rotations", "subsampled"],
)
def test_each_opencv_method_recovers_the_truerigid_transform(method, count, spread_rad):
    A, B = _noise_free_views(count, spread_rad=spread_rad)
    X = solve_hand_eye(A, B, method)
    translation_mm, rotation_deg = _errors(X)
    assert translation_mm < 1e-6
    assert rotation_deg < 1e-6
    np.testing.assert_allclose(X[:3, :3].T @ X[:3, :3], np.eye(3), atol=1e-14)
    np.testing.assert_array_equal(X[3], [0, 0, 0, 1])


def test_closed_form_refusals():
    A, B = _noise_free_views(12)
    with pytest.raises(HandEyeError, match="at least 3 views"):
        solve_hand_eye(A[:2], B[:2], "park")
    with pytest.raises(HandEyeError, match="unknown hand-eye method 'horaud'"):
        solve_hand_eye(A, B, "horaud")
    with pytest.raises(HandEyeError, match=r"\(N, 4, 4\)"):
        solve_hand_eye(A, B[:-1], "park")
    # rotations about one axis only leave X free to turn about it
    turns = np.stack(
        [
            rigid_transform([0.0, 0.0, angle], A[k, :3, 3])
            for k, angle in enumerate(np.linspace(-0.6, 0.6, 12))
        ]
    )
    for method in METHODS:
        with pytest.raises(HandEyeError, match="one axis"):
            solve_hand_eye(turns, invert_transform(turns @ X_TRUE) @ W_TRUE, method)
    # views a few degrees apart: OpenCV's Tsai finds no pair rotating by 17°
    # or more and refuses; Park and Daniilidis still solve exact data
    small, small_B = _noise_free_views(12, seed=4, spread_rad=0.03)
    with pytest.raises(HandEyeError, match="too few view pairs"):
        solve_hand_eye(small, small_B, "tsai")
    for method in ("park", "daniilidis"):
        assert _errors(solve_hand_eye(small, small_B, method))[0] < 1e-6


def test_board_pose_from_projected_corners_is_exact():
    B = board_pose(1.3)
    P = BOARD.object_points()
    view = board_view(0, CAMERA.project(P @ B[:3, :3].T + B[:3, 3]), BOARD, CAMERA)
    np.testing.assert_allclose(view.T_camera_target, B, atol=1e-9)
    assert view.reprojection_rms_px < 1e-6


def test_interpolated_marker_poses_and_gaps():
    T0, T1 = rigid_transform([0, 0, 0], [0, 0, 0]), rigid_transform([0, 0, np.pi / 2], [0.01, 0, 0])
    stamps = np.array([0, 16 * MS, 200 * MS, 216 * MS], dtype=np.int64)
    poses = np.stack([T0, T1, T0, T1])
    query = np.array([8 * MS, 16 * MS, 100 * MS, 300 * MS], dtype=np.int64)
    result, valid = marker_poses_at(stamps, poses, query, max_gap_ns=60 * MS)
    assert valid.tolist() == [True, True, False, False]
    np.testing.assert_allclose(result[0][:3, 3], [0.005, 0, 0])
    np.testing.assert_allclose(
        Rotation.from_matrix(result[0][:3, :3]).as_rotvec(), [0, 0, np.pi / 4], atol=1e-12
    )
    np.testing.assert_allclose(result[1], T1, atol=1e-12)


def test_calibration_with_tracker_noise_latency_and_dropouts():
    views, stamps, poses = synthetic_recording(seed=1)
    result = calibrate_hand_eye(views[::2], stamps, poses, BOARD, CAMERA)
    translation_mm, rotation_deg = _errors(result.T_marker_camera)
    offset_error_ms = result.time_offset_ns / MS - 23.4
    # measured on this scenario: ~0.03 mm, ~0.01°, ~0.1 ms
    assert translation_mm < 0.3
    assert rotation_deg < 0.1
    assert abs(offset_error_ms) < 0.5
    # the residuals are the tracker's noise (0.25 mm / 0.1° per sample, less
    # after interpolation averages two samples)
    assert 0.1 < result.translation_rms_mm < 0.35
    assert 0.04 < result.rotation_rms_deg < 0.12
    assert set(result.closed_form) == set(METHODS)
    for values in result.closed_form.values():
        assert values["translation_rms_mm"] < 1.0
    np.testing.assert_allclose(result.T_tracker_target[:3, 3], W_TRUE[:3, 3], atol=1e-3)


def test_outlier_views_are_rejected():
    views, stamps, poses = synthetic_recording(seed=2, duration_s=6.0)
    views = views[::2]
    rng = np.random.default_rng(5)
    bad = rng.choice(len(views), size=len(views) // 10, replace=False)
    for k in bad:
        # a wrong board pose, e.g. a mis-ordered detection
        wrong = views[k].T_camera_target @ rigid_transform([0.0, 0.0, 0.2], [0.004, -0.003, 0.0])
        views[k] = type(views[k])(views[k].stamp_ns, views[k].corners, wrong, 0.1)
    result = calibrate_hand_eye(views, stamps, poses, BOARD, CAMERA)
    translation_mm, rotation_deg = _errors(result.T_marker_camera)
    assert result.views_used <= len(views) - len(bad)
    assert translation_mm < 0.5
    assert rotation_deg < 0.15
    assert abs(result.time_offset_ns / MS - 23.4) < 1.0


def test_fixed_offset_and_refusals():
    views, stamps, poses = synthetic_recording(seed=4, duration_s=4.0, latency_ms=0.0)
    result = calibrate_hand_eye(views[::3], stamps, poses, BOARD, CAMERA, OffsetSearch(0, 0))
    assert result.time_offset_ns == 0
    assert _errors(result.T_marker_camera)[0] < 0.5
    with pytest.raises(HandEyeError, match="at least 5"):
        calibrate_hand_eye(views[:4], stamps, poses, BOARD, CAMERA)
    still, stamps, poses = synthetic_recording(seed=4, duration_s=4.0, motion_scale=0.05)
    with pytest.raises(HandEyeError, match="marker rotation"):
        calibrate_hand_eye(still[::3], stamps, poses, BOARD, CAMERA, OffsetSearch(0, 0))


_RAYS: dict[int, list[np.ndarray]] = {}


def _rays(supersample):
    """Unit rays through supersample x supersample points of every pixel (cached)."""
    if supersample not in _RAYS:
        v, u = np.mgrid[0 : CAMERA.height, 0 : CAMERA.width].astype(np.float64)
        offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
        _RAYS[supersample] = [
            CAMERA.pixels_to_rays(np.stack([u + du, v + dv], axis=-1))
            for du in offsets
            for dv in offsets
        ]
    return _RAYS[supersample]


def _render_board(B, supersample=3):
    """Grey image of the board seen with pose B: white margin, black/white squares."""
    image = np.zeros((CAMERA.height, CAMERA.width))
    R, t = B[:3, :3], B[:3, 3]
    normal = R[:, 2]
    for rays in _rays(supersample):
        depth = (normal @ t) / (rays @ normal)
        hit = (rays * depth[..., None] - t) @ R  # board coordinates
        col = np.floor(hit[..., 0] / BOARD.square_m + 1)
        row = np.floor(hit[..., 1] / BOARD.square_m + 1)
        inside = (col >= 0) & (col <= BOARD.columns) & (row >= 0) & (row <= BOARD.rows)
        image += np.where(inside & ((col + row) % 2 == 1), 0.1, 0.9)
    return np.clip(image / supersample**2 * 255, 0, 255).astype(np.uint8)


def test_corners_detected_in_a_rendered_image_give_the_true_pose():
    B = board_pose(2.0)
    corners = detect_checkerboard(_render_board(B), BOARD)
    assert corners is not None
    truth = CAMERA.project(BOARD.object_points() @ B[:3, :3].T + B[:3, 3])
    # OpenCV may start at either end of a board; compare in the matching order
    if np.linalg.norm(corners[0] - truth[0]) > np.linalg.norm(corners[0] - truth[-1]):
        corners = corners[::-1]
    # a steeply tilted board: measured 0.16 px RMS
    assert np.sqrt(np.mean(np.sum((corners - truth) ** 2, axis=-1))) < 0.3
    view = board_view(0, corners, BOARD, CAMERA)
    assert np.linalg.norm(view.T_camera_target[:3, 3] - B[:3, 3]) * 1e3 < 0.1
    assert detect_checkerboard(np.full((480, 640), 128, np.uint8), BOARD) is None


def test_endo_handeye_cli_on_a_rendered_bag(tmp_path):
    """Render a short hand-eye recording into a bag and run the CLI on it."""
    from endo_io.bag import BagWriter
    from endo_io.image import array_to_image
    from endo_io.pose import matrix_to_pose
    from endo_tracker_bridge.handeye_cli import main
    from endo_tracker_bridge.handeye_file import HandEyeCalibration

    latency_ms, duration_s = 31.0, 3.0
    rng = np.random.default_rng(8)
    bag_path = tmp_path / "handeye.mcap"
    with BagWriter(bag_path) as bag:
        bag.write_message("/endoscope/camera_info", CAMERA.to_camera_info(EPOCH_NS), EPOCH_NS)
        for t in np.arange(0.0, duration_s, 1 / 60):
            A = camera_pose(t) @ invert_transform(X_TRUE)
            A[:3, 3] += rng.normal(0.0, 0.25e-3 / np.sqrt(3), 3)
            stamp = EPOCH_NS + round((t + latency_ms * 1e-3) * 1e9)
            bag.write_message("/tracker/pose", matrix_to_pose(A, stamp, "tracker"), stamp)
        for t in np.arange(0.1, duration_s - 0.1, 1 / 12):
            B = board_pose(t)
            stamp = EPOCH_NS + round(t * 1e9)
            image = array_to_image(_render_board(B, supersample=2), "mono8", stamp, "camera")
            bag.write_message("/endoscope/image_raw", image, stamp)
    output = tmp_path / "handeye.yaml"
    assert main([str(bag_path), "-o", str(output), "--board", "9x6", "--square-mm", "5"]) == 0
    calibration = HandEyeCalibration.load(output)
    translation_mm, rotation_deg = _errors(calibration.T_marker_camera)
    assert translation_mm < 0.5
    assert rotation_deg < 0.2
    assert abs(calibration.time_offset_ns / MS - latency_ms) < 2.0
    assert calibration.views_used >= 30
    assert set(calibration.residuals) == {
        "reprojection_rms_px",
        "translation_rms_mm",
        "rotation_rms_deg",
    }
    assert calibration.residuals["translation_rms_mm"] < 0.5


def test_corner_numbering_does_not_depend_on_the_image_orientation():
    B = board_pose(0.7)
    image = _render_board(B, supersample=2)
    corners = detect_checkerboard(image, BOARD)
    turned = detect_checkerboard(np.ascontiguousarray(image[::-1, ::-1]), BOARD)
    assert corners is not None and turned is not None
    back = np.array([CAMERA.width - 1, CAMERA.height - 1]) - turned
    np.testing.assert_allclose(back, corners, atol=0.3)
    # 12-bit data in mono16 is stretched to 8 bits and gives the same corners
    twelve_bit = detect_checkerboard(image.astype(np.uint16) * 16 + 7, BOARD)
    np.testing.assert_allclose(twelve_bit, corners, atol=0.05)
    # the first corner is the one next to the dark outer square (board's far end here)
    truth = CAMERA.project(BOARD.object_points() @ B[:3, :3].T + B[:3, 3])
    assert np.linalg.norm(corners[0] - truth[-1]) < 0.5
