"""Accuracy of a recording of the graph's outputs against endo_sim's ground truth.

Works on any MCAP that holds the graph's topics beside ``/ground_truth/*``:
``endo-process``'s output (which copies the truth through) and a live
recording alike, so the two are scored by the same code. Depth is scored
with :func:`endo_sfs.evaluation.depth_error`, streams are read and paired by
:mod:`endo_bringup.evaluation` (the demo's scoring); nothing here measures
an error a second way.

* **relative depth**: AbsRel of ``/endoscope/depth_relative`` after one
  median scale per frame;
* **oracle scale**: the one scale that best fits the relative depth to the
  truth over the whole sequence (least squares over every pixel of every
  frame with truth), the reference for the estimated scale;
* **metric depth**: MAE and AbsRel of ``/endoscope/depth`` with no scaling;
* **scale over time**: the estimated scale against the oracle;
* **cloud**: RMS distance of each world point of ``/endoscope/points`` to the
  true surface of the same frame (true depth through the true pose);
* **pose**: ``/endoscope/pose`` against ``/ground_truth/camera_pose``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from endo_bringup.evaluation import (
    PoseComparison,
    compare_poses,
    depth_errors_at_truth,
    read_depth_frames,
    read_pose_stream,
)
from endo_io import topics
from endo_sfs.evaluation import DepthError, depth_error


@dataclass(frozen=True)
class ScaleTrack:
    """The estimated scale over time against the oracle.

    stamps_ns: (K,) int64; scale: (K,) the estimate (NaN while unusable);
    oracle: the sequence's best single scale. relative_error: (K,)
    ``scale / oracle − 1``.
    """

    stamps_ns: np.ndarray
    scale: np.ndarray
    oracle: float

    @property
    def relative_error(self) -> np.ndarray:
        """(K,) signed relative error of the estimate."""
        return self.scale / self.oracle - 1.0


@dataclass
class Accuracy:
    """Every figure of a scored recording (empty fields: the recording lacks that topic).

    relative: stamp -> median-scaled error of the relative depth;
    oracle_scale: least-squares scale of relative depth to truth over the
    sequence (NaN without truth); metric: stamp -> unscaled error of the
    metric depth; cloud_rms_m: stamp -> RMS distance of the world points
    to the true surface; poses: the camera poses against the truth; scale:
    the estimated scale over time.
    """

    truth_frames: int = 0
    relative: dict[int, DepthError] = field(default_factory=dict)
    oracle_scale: float = float("nan")
    metric: dict[int, DepthError] = field(default_factory=dict)
    cloud_rms_m: dict[int, float] = field(default_factory=dict)
    poses: PoseComparison | None = None
    scale: ScaleTrack | None = None

    @property
    def has_truth(self) -> bool:
        """The recording carried ground-truth depth or poses."""
        return self.truth_frames > 0 or (self.poses is not None and self.poses.compared > 0)


def oracle_scale(estimates: dict[int, np.ndarray], truths: dict[int, np.ndarray]) -> float:
    """The single least-squares scale of relative depth to truth over all paired frames.

    estimates, truths: stamp -> (H, W) depth (NaN invalid). NaN when no
    frame pairs.
    """
    stamps = sorted(set(estimates) & set(truths))
    if not stamps:
        return float("nan")
    estimate = np.concatenate([estimates[s].ravel() for s in stamps])
    truth = np.concatenate([truths[s].ravel() for s in stamps])
    try:
        return depth_error(estimate, truth, scaling="least_squares").scale
    except ValueError:
        return float("nan")


def metric_errors(
    estimates: dict[int, np.ndarray], truths: dict[int, np.ndarray]
) -> dict[int, DepthError]:
    """Unscaled (metric) error of each estimate that has a truth with its stamp."""
    errors: dict[int, DepthError] = {}
    for stamp in sorted(set(estimates) & set(truths)):
        try:
            errors[stamp] = depth_error(estimates[stamp], truths[stamp], scaling="none")
        except ValueError:
            continue
    return errors


def score_recording(
    path: Path,
    *,
    cloud_rms: Callable[[Path, dict[int, np.ndarray]], dict[int, float]] | None = None,
    scale_stream: Callable[[Path], tuple[np.ndarray, np.ndarray]] | None = None,
) -> Accuracy:
    """Score a recording that holds the graph's outputs and the ground truth.

    Args:
        path: the MCAP.
        cloud_rms: (path, true depth by stamp) -> stamp -> RMS, for the
            world points (the flow stage's layout); None skips it.
        scale_stream: path -> ((K,) stamps, (K,) scale), the scale topic
            decoded; None skips it.
    """
    accuracy = Accuracy()
    truths = read_depth_frames(path, topics.TRUE_DEPTH)
    accuracy.truth_frames = len(truths)
    stamps = set(truths)
    if truths:
        relative = read_depth_frames(path, topics.DEPTH_RELATIVE, stamps)
        accuracy.relative = depth_errors_at_truth(relative, truths)
        accuracy.oracle_scale = oracle_scale(relative, truths)
        accuracy.metric = metric_errors(read_depth_frames(path, topics.DEPTH, stamps), truths)
        if cloud_rms is not None:
            accuracy.cloud_rms_m = cloud_rms(path, truths)
    true_stamps, true_poses = read_pose_stream(path, topics.TRUE_CAMERA_POSE)
    if len(true_stamps):
        estimated_stamps, estimated = read_pose_stream(path, topics.CAMERA_POSE)
        accuracy.poses = compare_poses(estimated_stamps, estimated, true_stamps, true_poses)
    if scale_stream is not None and np.isfinite(accuracy.oracle_scale):
        scale_stamps, scale = scale_stream(path)
        if len(scale_stamps):
            accuracy.scale = ScaleTrack(scale_stamps, scale, accuracy.oracle_scale)
    return accuracy
