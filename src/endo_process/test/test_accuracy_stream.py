"""RecordingScorer: the figures of known depth errors, and a truth that comes late."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from endo_io import topics
from endo_io.bag import BagWriter
from endo_io.image import array_to_image, array_to_image_cdr
from endo_process.accuracy import RecordingScorer, score_recording

STAMP = 1_000_000_000


def truth_and_estimate() -> tuple[np.ndarray, np.ndarray]:
    """A 40x50 true depth (m) and a relative estimate 10x too small, 5 % too deep on one half."""
    truth = np.linspace(0.02, 0.06, 40 * 50, dtype=np.float32).reshape(40, 50)
    estimate = truth / np.float32(10.0)
    estimate[:, 25:] *= np.float32(1.05)
    return truth, estimate


def image(depth: np.ndarray, stamp_ns: int = STAMP) -> bytes:
    return array_to_image_cdr(depth, "32FC1", stamp_ns, "endoscope_optical_frame")


def test_truth_first_scores_the_frame_as_the_file_scorer_does(tmp_path: Path) -> None:
    truth, estimate = truth_and_estimate()
    metric = estimate * np.float32(10.0)
    scorer = RecordingScorer()
    scorer.add(topics.TRUE_DEPTH, image(truth))
    scorer.add(topics.DEPTH_RELATIVE, image(estimate))
    scorer.add(topics.DEPTH, image(metric))
    assert scorer.complete
    streamed = scorer.result()
    assert streamed.truth_frames == 1
    # half the pixels 5 % too deep: the unscaled metric error is their mean, 2.5 %
    assert streamed.metric[STAMP].abs_rel == pytest.approx(0.025, rel=1e-5)
    # one scale for the sequence: between the two halves' (ln-median over the pixels)
    assert 10.0 / 1.05 <= streamed.oracle_scale <= 10.0
    assert streamed.oracle[STAMP].abs_rel == pytest.approx(0.0244, abs=2e-4)
    # the same messages in a file, read back: the same figures
    path = tmp_path / "run.mcap"
    with BagWriter(path) as writer:
        for topic, depth in ((topics.DEPTH_RELATIVE, estimate), (topics.DEPTH, metric),
                             (topics.TRUE_DEPTH, truth)):  # fmt: skip
            writer.write_message(topic, array_to_image(depth, "32FC1", STAMP, "f"), STAMP)
    read_back = score_recording(path)
    assert read_back.relative == streamed.relative and read_back.metric == streamed.metric
    assert read_back.oracle_scale == streamed.oracle_scale


def test_a_truth_after_the_estimates_of_its_stamp_is_flagged() -> None:
    truth, estimate = truth_and_estimate()
    scorer = RecordingScorer()
    scorer.add(topics.DEPTH_RELATIVE, image(estimate))
    scorer.add(topics.TRUE_DEPTH, image(truth))
    assert not scorer.complete  # the file is to be scored by score_recording instead
    # another stamp's truth after this estimate is no such case
    later = RecordingScorer()
    later.add(topics.DEPTH_RELATIVE, image(estimate))
    later.add(topics.TRUE_DEPTH, image(truth, STAMP + 1))
    assert later.complete and later.result().truth_frames == 1
    assert later.result().relative == {}


def test_the_pruned_cloud_search_finds_the_exact_nearest_true_points() -> None:
    """cloud_distances' per-point bounds change the work, not one distance (to the bit)."""
    from scipy.spatial import cKDTree

    from endo_io.camera import CameraModel
    from endo_io.pose import rigid_transform, transform_points
    from endo_process.accuracy import cloud_distances

    camera = CameraModel.pinhole(64, 48, 50.0, 50.0, 31.5, 23.5,
                                 D=np.array([-0.1, 0.02, 0.0, 0.0, 0.0]))  # fmt: skip
    v, u = np.mgrid[0:48, 0:64]
    depth = (0.04 + 0.01 * np.sin(u / 9.0) * np.cos(v / 7.0)).astype(np.float32)
    depth[:5, :7] = np.nan  # no truth there
    T = rigid_transform(np.radians([10.0, -5.0, 30.0]), [0.01, -0.02, 0.03])
    local = camera.depth_to_points(depth).reshape(-1, 3)
    truth = transform_points(T, local[np.isfinite(local).all(axis=1)])
    rng = np.random.default_rng(3)
    # points near the surface, far from it, behind the camera and outside the view
    points = np.concatenate([
        truth[::3] + rng.normal(0.0, 0.002, (len(truth[::3]), 3)),
        truth[:50] + rng.normal(0.0, 0.05, (50, 3)),
        transform_points(T, np.array([[0.0, 0.0, -0.05], [1.0, 1.0, 0.04]])),
    ])  # fmt: skip
    expected, _ = cKDTree(truth).query(points)
    np.testing.assert_array_equal(cloud_distances(points, depth, camera, T), expected)


def test_a_camera_info_logged_before_its_truth_still_scores_the_cloud(tmp_path: Path) -> None:
    """A live recording may log the camera_info before the true depth of the same stamp."""
    from endo_io.camera import CameraModel
    from endo_io.pointcloud import xyz_to_pointcloud2_cdr
    from endo_io.pose import matrix_to_pose, rigid_transform, transform_points

    truth, _ = truth_and_estimate()
    camera = CameraModel.pinhole(50, 40, 45.0, 45.0, 24.5, 19.5)
    T = rigid_transform(np.radians([5.0, 0.0, -10.0]), [0.01, 0.0, 0.02])
    surface = transform_points(T, camera.depth_to_points(truth).reshape(-1, 3))
    cloud = xyz_to_pointcloud2_cdr(surface + np.float32(0.001), STAMP, topics.WORLD_FRAME)
    path = tmp_path / "live.mcap"
    with BagWriter(path) as writer:
        writer.write_message(topics.CAMERA_INFO, camera.to_camera_info(STAMP), STAMP)
        writer.write_message(topics.TRUE_DEPTH, array_to_image(truth, "32FC1", STAMP, "f"),
                             STAMP + 1)
        writer.write_message(topics.TRUE_CAMERA_POSE,
                             matrix_to_pose(T, STAMP, topics.WORLD_FRAME), STAMP + 2)
        writer.write_message(topics.DEPTH, array_to_image(truth, "32FC1", STAMP, "f"),
                             STAMP + 3)
        writer.add_topic(topics.POINTS, "sensor_msgs/msg/PointCloud2")
        writer.write(topics.POINTS, cloud, STAMP + 4)
    accuracy = score_recording(path)
    assert list(accuracy.metric) == [STAMP] and list(accuracy.cloud_rms_m) == [STAMP]
    # every point 1 mm off along each axis: within sqrt(3) mm of the surface, never farther
    assert 0.0 < accuracy.cloud_rms_m[STAMP] <= np.sqrt(3) * 1e-3 + 1e-6
