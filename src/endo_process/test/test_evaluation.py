"""Scores of endo_process.evaluation on streams with known errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from endo_io.bag import BagWriter
from endo_io.bag.streams import count_messages, read_depth_frames, read_pose_stream
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose, rigid_transform
from endo_process.evaluation import (
    compare_poses,
    depth_errors_at_truth,
    handeye_error,
    inverse_response_error,
    transform_errors,
)

MS = 1_000_000


def rigid(rotvec_deg: tuple[float, float, float], translation_m: tuple[float, float, float]):
    return rigid_transform(np.radians(rotvec_deg), translation_m)


def test_transform_errors_of_a_known_offset():
    truth = np.stack([rigid((10, 20, 30), (0.1, 0.2, 0.3)), rigid((0, 0, 0), (0, 0, 0))])
    offset = rigid((0.0, 0.0, 0.5), (0.0, 0.003, 0.004))  # 0.5 deg about z, 5 mm
    estimated = truth @ offset
    position_mm, rotation_deg = transform_errors(estimated, truth)
    # position error is measured in the parent frame: |R_true · t_offset| = 5 mm
    np.testing.assert_allclose(position_mm, [5.0, 5.0], atol=1e-9)
    np.testing.assert_allclose(rotation_deg, [0.5, 0.5], atol=1e-6)


def test_handeye_error():
    truth = rigid((5, -40, 12), (0.012, -0.035, 0.3))
    fitted = truth @ rigid((0.0, 0.2, 0.0), (0.0001, 0.0, 0.0))
    translation_mm, rotation_deg = handeye_error(fitted, truth)
    assert translation_mm == pytest.approx(0.1, abs=1e-9)
    assert rotation_deg == pytest.approx(0.2, abs=1e-6)


def test_inverse_response_error_ignores_the_ends():
    truth = np.linspace(0.0, 1.0, 256) ** 2.2
    fitted = truth.copy()
    fitted[0] += 0.5  # outside 5..250: not counted
    fitted[100] += 0.01
    assert inverse_response_error(fitted, truth) == pytest.approx(0.01)


def test_compare_poses_interpolates_at_true_stamps_and_skips_gaps():
    # truth: a camera moving 10 mm/s along x and turning 10 deg/s about z, at 30 Hz
    truth_stamps = np.arange(0, 1000 * MS, 33 * MS, dtype=np.int64)
    truth = np.stack([rigid((0, 0, 10 * t / 1e9), (0.01 * t / 1e9, 0, 0)) for t in truth_stamps])
    # estimate: the same motion sampled at 60 Hz, 0.5 mm off in y, and a 200 ms dropout
    stamps = np.arange(0, 1000 * MS, 16 * MS, dtype=np.int64)
    stamps = stamps[(stamps < 400 * MS) | (stamps > 600 * MS)]
    estimated = np.stack([rigid((0, 0, 10 * t / 1e9), (0.01 * t / 1e9, 0.0005, 0)) for t in stamps])
    comparison = compare_poses(stamps, estimated, truth_stamps, truth, max_gap_ns=60 * MS)
    last_before, first_after = stamps[stamps < 400 * MS][-1], stamps[stamps > 600 * MS][0]
    inside_gap = (truth_stamps > last_before) & (truth_stamps < first_after)
    after_end = truth_stamps > stamps[-1]
    assert comparison.missing == int((inside_gap | after_end).sum())
    assert comparison.compared + comparison.missing == len(truth_stamps)
    # linear motion and constant-rate rotation interpolate exactly
    np.testing.assert_allclose(comparison.position_mm, 0.5, atol=1e-6)
    np.testing.assert_allclose(comparison.rotation_deg, 0.0, atol=1e-5)


def test_compare_poses_without_estimates():
    truth = np.stack([np.eye(4)] * 3)
    stamps = np.array([0, 1, 2], dtype=np.int64)
    comparison = compare_poses(np.empty(0, np.int64), np.empty((0, 4, 4)), stamps, truth)
    assert (comparison.compared, comparison.missing) == (0, 3)


def test_bag_readers_and_median_scaled_depth(tmp_path: Path):
    """Depth pairs by stamp; a relative depth that is the truth times 3 scores 0."""
    path = tmp_path / "run.mcap"
    y, x = np.mgrid[0:24, 0:32]
    truth = (0.03 + 0.001 * x + 0.0005 * y).astype(np.float32)
    estimate = 3.0 * truth
    estimate[0, 0] = np.nan
    with BagWriter(path) as writer:
        for k in range(3):
            stamp = 1_000 * MS + k * 33 * MS
            writer.write_message(
                "/endoscope/depth_relative", array_to_image(estimate, "32FC1", stamp, "cam"), stamp
            )
            pose = matrix_to_pose(rigid((0, 0, k), (k, 0, 0)), stamp, "world")
            writer.write_message("/endoscope/pose", pose, stamp)
        stamp = 1_000 * MS + 33 * MS  # truth for the middle frame only
        writer.write_message(
            "/ground_truth/depth", array_to_image(truth, "32FC1", stamp, "cam"), stamp + 5 * MS
        )
    counts = count_messages(path)
    assert counts == {
        "/endoscope/depth_relative": 3,
        "/endoscope/pose": 3,
        "/ground_truth/depth": 1,
    }
    errors = depth_errors_at_truth(
        read_depth_frames(path, "/endoscope/depth_relative"),
        read_depth_frames(path, "/ground_truth/depth"),
    )
    assert list(errors) == [1_000 * MS + 33 * MS]
    error = errors[1_000 * MS + 33 * MS]
    assert error.scale == pytest.approx(1 / 3, rel=1e-6)
    assert error.abs_rel == pytest.approx(0.0, abs=1e-6)
    assert error.coverage == pytest.approx(1 - 1 / truth.size)
    stamps, poses = read_pose_stream(path, "/endoscope/pose")
    assert stamps.tolist() == [1_000 * MS + k * 33 * MS for k in range(3)]
    assert math.isclose(poses[2, 0, 3], 2.0)
    assert read_depth_frames(path, "/missing") == {}
