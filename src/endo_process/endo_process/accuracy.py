"""Accuracy of a recording of the graph's outputs against endo_sim's ground truth.

Works on any MCAP that holds the graph's topics beside ``/ground_truth/*``:
``endo-process``'s output (which copies the truth through) and a live
recording alike, so the two are scored by the same code. Depth is scored
with :func:`endo_sfs.evaluation.depth_error`, streams are read and paired by
:mod:`endo_process.evaluation` (the demo's scoring); nothing here measures
an error a second way.

* **relative depth**: AbsRel of ``/endoscope/depth_relative`` after one
  median scale per frame;
* **oracle scale**: the one scale that best fits the relative depth to the
  truth over the whole sequence (:func:`endo_sfs.evaluation.sequence_scale`:
  the median of ln(d*/d) over every pixel of every frame with truth), the
  reference for the estimated scale, and the oracle-scaled AbsRel it gives;
* **metric depth**: MAE and AbsRel of ``/endoscope/depth`` with no scaling;
* **scale over time**: the estimated scale against the oracle;
* **cloud**: RMS distance of each world point of ``/endoscope/points`` to the
  true surface of the same frame (true depth through the true pose);
* **pose**: ``/endoscope/pose`` against ``/ground_truth/camera_pose``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from endo_io import topics
from endo_io.bag import BagReader, deserialize
from endo_io.bag.streams import read_depth_frames, read_pose_stream
from endo_io.camera import CameraModel
from endo_io.pointcloud import pointcloud2_to_xyz
from endo_io.pose import transform_points
from endo_io.stamp import stamp_to_ns
from endo_process.evaluation import PoseComparison, compare_poses, depth_errors_at_truth
from endo_sfs.errors import NoCommonPixelsError
from endo_sfs.evaluation import DepthError, depth_error, sequence_scale


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
    oracle_scale: the best single scale of relative depth to truth over the
    sequence (NaN without truth); oracle: stamp -> error of the relative
    depth times that scale; metric: stamp -> unscaled error of the
    metric depth; cloud_rms_m: stamp -> RMS distance of the world points
    to the true surface; poses: the camera poses against the truth; scale:
    the estimated scale over time.
    """

    truth_frames: int = 0
    relative: dict[int, DepthError] = field(default_factory=dict)
    oracle_scale: float = float("nan")
    oracle: dict[int, DepthError] = field(default_factory=dict)
    metric: dict[int, DepthError] = field(default_factory=dict)
    cloud_rms_m: dict[int, float] = field(default_factory=dict)
    poses: PoseComparison | None = None
    scale: ScaleTrack | None = None
    #: The true camera trajectory: ((K,) int64 stamps, (K, 3) positions in
    #: metres), None without ``/ground_truth/camera_pose``; the scale's
    #: convergence is judged from the true motion (endo_bringup.acceptance).
    true_positions: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def has_truth(self) -> bool:
        """The recording carried ground-truth depth or poses."""
        return self.truth_frames > 0 or (self.poses is not None and self.poses.compared > 0)


def oracle_scale(estimates: dict[int, np.ndarray], truths: dict[int, np.ndarray]) -> float:
    """The single scale that best fits relative depth to truth over all paired frames.

    :func:`endo_sfs.evaluation.sequence_scale` (the median of ln(d*/d) over
    every pixel of every frame with both values: the project's one oracle,
    as endo_flow's evaluation uses it) over the frames whose stamps both
    hold. estimates, truths: stamp -> (H, W) depth (NaN invalid). NaN when
    no pixel pairs; a frame whose shapes differ raises SfsInputError.
    """
    stamps = sorted(set(estimates) & set(truths))
    try:
        return sequence_scale((estimates[s] for s in stamps), (truths[s] for s in stamps))
    except NoCommonPixelsError:
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


def read_scale_stream(path: Path, *, with_std: bool = False) -> tuple[np.ndarray, ...]:
    """((K,) int64 stamps, (K,) float64 scale[, (K,) std of ln s]) of the scale topic.

    The scale is NaN before the first observation.
    """
    rows: list[tuple[int, float, float]] = []
    with BagReader(path) as reader:
        if topics.SCALE in reader.topics:
            for message in reader.messages([topics.SCALE]):
                msg = deserialize(message)
                rows.append((stamp_to_ns(msg.header.stamp), msg.vector.x, msg.vector.y))
    stamps = np.asarray([r[0] for r in rows], np.int64)
    scale = np.asarray([r[1] for r in rows], np.float64)
    if with_std:
        return stamps, scale, np.asarray([r[2] for r in rows], np.float64)
    return stamps, scale


def messages_at(path: Path, topic: str, stamps: set[int]) -> dict[int, object]:
    """Header stamp -> the decoded message of ``topic`` with one of ``stamps`` (others skipped)."""
    found: dict[int, object] = {}
    with BagReader(path) as reader:
        if topic in reader.topics:
            for message in reader.messages([topic]):
                msg = deserialize(message)
                stamp = stamp_to_ns(msg.header.stamp)
                if stamp in stamps:
                    found[stamp] = msg
    return found


def cloud_distances(
    points: np.ndarray, true_depth: np.ndarray, camera: CameraModel, T_world_camera: np.ndarray
) -> np.ndarray:
    """Distance (m) of each world point to the true surface of one frame.

    points: (N, 3) world points (non-finite rows are dropped); true_depth:
    (H, W) metres; camera: its model; T_world_camera: (4, 4) the true pose.
    Returns (N',) distances to the nearest true point (the truth is dense, one
    point per pixel, so this is the distance to the surface to within a pixel
    footprint), for the finite points; empty when either side is.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    local = camera.depth_to_points(true_depth).reshape(-1, 3)
    truth = transform_points(T_world_camera, local[np.isfinite(local).all(axis=1)])
    if len(points) == 0 or len(truth) == 0:
        return np.empty(0)
    distance, _ = cKDTree(truth).query(points)
    return np.asarray(distance, np.float64)


CLOUD_SCORE_POINTS = 50_000
"""At most this many points of one cloud are scored (an even stride over them).

A full-resolution cloud holds ~300 000 points; the RMS of 50 000 of them taken
evenly over the image is the same figure to well under 1 % and costs a sixth
of the nearest-neighbour queries.
"""


def cloud_rms_at_truth(path: Path, truths: dict[int, np.ndarray]) -> dict[int, float]:
    """RMS distance (m) of each frame's world points to that frame's true surface.

    The true surface is the true depth through the frame's camera model and
    its true pose (:func:`cloud_distances`), at most :data:`CLOUD_SCORE_POINTS`
    points per cloud. One pass over the points topic, each cloud scored and
    dropped as it is read: full-resolution clouds are ~5 MB each. Frames
    without points, camera_info or true pose are left out.
    """
    stamps = set(truths)
    infos = messages_at(path, topics.CAMERA_INFO, stamps)
    true_stamps, true_poses = read_pose_stream(path, topics.TRUE_CAMERA_POSE)
    poses = dict(zip(true_stamps.tolist(), true_poses, strict=True))
    wanted = stamps & set(infos) & set(poses)
    rms: dict[int, float] = {}
    with BagReader(path) as reader:
        if topics.POINTS not in reader.topics:
            return rms
        for message in reader.messages([topics.POINTS]):
            cloud = deserialize(message)
            stamp = stamp_to_ns(cloud.header.stamp)
            if stamp not in wanted:
                continue
            points, _ = pointcloud2_to_xyz(cloud)
            stride = max(1, -(-len(points) // CLOUD_SCORE_POINTS))
            camera = CameraModel.from_camera_info(infos[stamp])
            distance = cloud_distances(points[::stride], truths[stamp], camera, poses[stamp])
            if len(distance):
                rms[stamp] = float(np.sqrt(np.mean(distance**2)))
    return dict(sorted(rms.items()))


def score_recording(path: Path) -> Accuracy:
    """Score a recording that holds the graph's outputs and the ground truth (any may be absent)."""
    accuracy = Accuracy()
    truths = read_depth_frames(path, topics.TRUE_DEPTH)
    accuracy.truth_frames = len(truths)
    stamps = set(truths)
    if truths:
        relative = read_depth_frames(path, topics.DEPTH_RELATIVE, stamps)
        accuracy.relative = depth_errors_at_truth(relative, truths)
        accuracy.oracle_scale = oracle_scale(relative, truths)
        if np.isfinite(accuracy.oracle_scale):
            scaled = {k: v * np.float32(accuracy.oracle_scale) for k, v in relative.items()}
            accuracy.oracle = metric_errors(scaled, truths)
        accuracy.metric = metric_errors(read_depth_frames(path, topics.DEPTH, stamps), truths)
        accuracy.cloud_rms_m = cloud_rms_at_truth(path, truths)
    true_stamps, true_poses = read_pose_stream(path, topics.TRUE_CAMERA_POSE)
    if len(true_stamps):
        accuracy.true_positions = (true_stamps, np.asarray(true_poses)[:, :3, 3])
        estimated_stamps, estimated = read_pose_stream(path, topics.CAMERA_POSE)
        accuracy.poses = compare_poses(estimated_stamps, estimated, true_stamps, true_poses)
    if np.isfinite(accuracy.oracle_scale):
        scale_stamps, scale = read_scale_stream(path)
        if len(scale_stamps):
            accuracy.scale = ScaleTrack(scale_stamps, scale, accuracy.oracle_scale)
    return accuracy
