"""Scores of a graph run against the simulator's ground truth.

ROS-free: every function takes arrays and returns plain numbers (the
recording is read with :mod:`endo_io.bag.streams`). Depth is scored with
:func:`endo_sfs.evaluation.depth_error` (the SFS package's own measure),
poses with :func:`endo_io.pose.interpolate_transforms`; this module only
pairs the streams by stamp and reduces them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from endo_io.pose import interpolate_transforms, rotation_angle
from endo_sfs.evaluation import DepthError, depth_error

#: Longest gap in the estimated pose stream bridged when interpolating at a
#: ground-truth stamp, ns (the tracker runs at 60 Hz: up to two lost samples).
DEFAULT_POSE_MAX_GAP_NS = 60_000_000


def depth_errors_at_truth(
    estimates: dict[int, np.ndarray], truths: dict[int, np.ndarray]
) -> dict[int, DepthError]:
    """Median-scaled error of each estimated depth that has a truth with the same stamp.

    estimates, truths: stamp (ns) -> (H, W) float depth (NaN invalid); the
    estimate is relative (any scale), the truth metric. Each frame gets its
    own scale ``median(truth) / median(estimate)`` over the pixels where both
    are finite. Frames whose estimate has no finite pixel on the truth are left out.
    """
    errors: dict[int, DepthError] = {}
    for stamp in sorted(set(estimates) & set(truths)):
        try:
            errors[stamp] = depth_error(estimates[stamp], truths[stamp], scaling="median")
        except ValueError:
            continue
    return errors


def transform_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position and rotation difference of paired rigid transforms.

    estimated, truth: (N, 4, 4) float64, metres. Returns ((N,) position error
    in mm, (N,) rotation angle of ``truth⁻¹ · estimated`` in degrees).
    """
    position_mm = 1e3 * np.linalg.norm(estimated[:, :3, 3] - truth[:, :3, 3], axis=1)
    relative = np.einsum("nji,njk->nik", truth[:, :3, :3], estimated[:, :3, :3])
    return position_mm, np.degrees(rotation_angle(relative))


@dataclass(frozen=True)
class PoseComparison:
    """An estimated pose stream against the true poses at the true stamps.

    compared: true poses with an estimate (interpolated within the gap limit);
    missing: true poses without one (before/after the stream or in a dropout).
    position_mm, rotation_deg: (compared,) errors.
    """

    compared: int
    missing: int
    position_mm: np.ndarray
    rotation_deg: np.ndarray


def compare_poses(
    estimated_stamps_ns: np.ndarray,
    estimated: np.ndarray,
    truth_stamps_ns: np.ndarray,
    truth: np.ndarray,
    max_gap_ns: int = DEFAULT_POSE_MAX_GAP_NS,
) -> PoseComparison:
    """Interpolate the estimated stream at each true stamp and compare.

    estimated_stamps_ns: (M,) int64 sorted; estimated: (M, 4, 4) metres;
    truth_stamps_ns: (N,) int64; truth: (N, 4, 4) metres. The estimate at a
    true stamp is the linear/SLERP interpolation of the two estimated
    samples around it when they are at most ``max_gap_ns`` apart.
    """
    if len(estimated_stamps_ns) == 0:
        empty = np.empty(0)
        return PoseComparison(0, len(truth_stamps_ns), empty, empty)
    interpolated, valid = interpolate_transforms(
        estimated_stamps_ns, estimated, truth_stamps_ns, max_gap_ns
    )
    position_mm, rotation_deg = transform_errors(interpolated[valid], truth[valid])
    return PoseComparison(int(valid.sum()), int((~valid).sum()), position_mm, rotation_deg)


def inverse_response_error(
    fitted: np.ndarray, truth: np.ndarray, low: int = 5, high: int = 250
) -> float:
    """Largest |fitted − true| inverse response over raw values low..high, fraction of full scale.

    fitted, truth: (2^bits,) float64 g(v) with g(max) = 1.
    """
    return float(np.max(np.abs(fitted[low : high + 1] - truth[low : high + 1])))


def handeye_error(fitted: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation mm, rotation deg) of ``truth⁻¹ · fitted`` for (4, 4) T_marker_camera."""
    delta = np.linalg.inv(truth) @ fitted
    _, rotation_deg = transform_errors(delta[None], np.eye(4)[None])
    return 1e3 * float(np.linalg.norm(delta[:3, 3])), float(rotation_deg[0])
