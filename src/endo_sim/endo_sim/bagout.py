"""Write a simulated recording as a rosbag2 MCAP bag plus its ground-truth files.

Topics (every message stamped on the simulated clock, never the wall clock,
so the same seed gives byte-identical files):

=============================  ===========================  ==========================
topic                          type                         frame / content
=============================  ===========================  ==========================
/endoscope/image_raw           sensor_msgs/msg/Image        endoscope_optical_frame;
                                                            mono8, mono16 (12 bit), rgb8
/endoscope/camera_info         sensor_msgs/msg/CameraInfo   endoscope_optical_frame
/ground_truth/depth            sensor_msgs/msg/Image        32FC1 metres along z, NaN
                                                            outside the FOV (REP 118)
/ground_truth/camera_pose      geometry_msgs/msg/PoseStamped  endoscope_optical_frame
                                                            in ``world``
/tracker/pose                  geometry_msgs/msg/PoseStamped  marker in ``tracker``, m or
                                                            mm; stamp = sample + latency
/calibration/gray_level        std_msgs/msg/Float32         card reflectance (gray card
                                                            sequence only)
=============================  ===========================  ==========================

Messages are written in log-time order; a message's log time is its stamp
(the tracker's is its latency-shifted stamp, i.e. when it would arrive).

Ground-truth files beside ``<stem>.mcap``: ``<stem>.ground_truth.yaml``,
``<stem>.camera.yaml`` (ROS camera_calibration format),
``<stem>.inverse_response.npy`` ((2^bits,) float64 g(v), g(max) = 1) and
``<stem>.light_map.npy`` ((H, W) float64 L(x)).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from std_msgs.msg import Float32

from endo_io.bag import BagError, BagWriter, qos_profiles_to_yaml, serialize
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose
from endo_io.qos import reliable_qos
from endo_io.topics import (
    CAMERA_INFO,
    GRAY_LEVEL,
    IMAGE_RAW,
    TRACKER_FRAME,
    TRACKER_POSE,
    TRUE_CAMERA_POSE,
    TRUE_DEPTH,
    WORLD_FRAME,
)
from endo_sim.sequences import Sequence, SimulationConfig
from endo_sim.tracker import simulate_tracker
from endo_sim.trajectory import NS_PER_S

_TOPIC_TYPES = {
    IMAGE_RAW: "sensor_msgs/msg/Image",
    CAMERA_INFO: "sensor_msgs/msg/CameraInfo",
    TRUE_DEPTH: "sensor_msgs/msg/Image",
    TRUE_CAMERA_POSE: "geometry_msgs/msg/PoseStamped",
    TRACKER_POSE: "geometry_msgs/msg/PoseStamped",
    GRAY_LEVEL: "std_msgs/msg/Float32",
}


@dataclass(frozen=True)
class TimedMessage:
    """One message of the recording: log time (ns), topic, ROS message."""

    log_time_ns: int
    topic: str
    message: Any


def image_noise_rng(seed: int) -> np.random.Generator:
    """The generator of the sensor noise of a recording with ``seed``."""
    return np.random.default_rng([int(seed), 1])


def tracker_rng(seed: int) -> np.random.Generator:
    """The generator of the tracker's noise and dropouts of a recording with ``seed``."""
    return np.random.default_rng([int(seed), 2])


def frame_messages(sequence: Sequence, k: int, frame: Any, stamp_ns: int) -> list[TimedMessage]:
    """The messages published with frame ``k`` (already rendered) at ``stamp_ns``."""
    camera = sequence.camera
    frame_id = camera.frame_id
    pose = sequence.trajectory.pose_at(int(sequence.frame_times_ns[k]))
    out = [
        TimedMessage(
            stamp_ns, IMAGE_RAW, array_to_image(frame.image, frame.encoding, stamp_ns, frame_id)
        ),
        TimedMessage(stamp_ns, CAMERA_INFO, camera.to_camera_info(stamp_ns)),
    ]
    if k % sequence.config.depth_every == 0:
        out.append(
            TimedMessage(
                stamp_ns, TRUE_DEPTH, array_to_image(frame.depth, "32FC1", stamp_ns, frame_id)
            )
        )
    out.append(
        TimedMessage(stamp_ns, TRUE_CAMERA_POSE, matrix_to_pose(pose, stamp_ns, WORLD_FRAME))
    )
    if sequence.gray_levels is not None:
        out.append(
            TimedMessage(stamp_ns, GRAY_LEVEL, Float32(data=float(sequence.gray_levels[k])))
        )
    return out


def _frame_stream(sequence: Sequence) -> Iterator[tuple[int, int, TimedMessage]]:
    rng = image_noise_rng(sequence.config.seed)
    start = sequence.config.start_ns
    for k, t_ns in enumerate(sequence.frame_times_ns):
        pose = sequence.trajectory.pose_at(int(t_ns))
        frame = sequence.renderer.render(sequence.scene_of_frame(k), pose, rng)
        for order, message in enumerate(frame_messages(sequence, k, frame, start + int(t_ns))):
            yield message.log_time_ns, order, message


def _tracker_stream(sequence: Sequence) -> Iterator[tuple[int, int, TimedMessage]]:
    model = sequence.config.tracker
    samples = simulate_tracker(model, sequence.trajectory, tracker_rng(sequence.config.seed))
    start = sequence.config.start_ns
    scale = model.unit_scale
    for stamp, pose, visible in zip(samples.stamp_ns, samples.poses, samples.visible, strict=True):
        if not visible:
            continue
        published = pose.copy()
        published[:3, 3] *= scale
        stamp_ns = start + int(stamp)
        # After the frame messages of the same instant (order 10).
        yield (
            stamp_ns,
            10,
            TimedMessage(
                stamp_ns, TRACKER_POSE, matrix_to_pose(published, stamp_ns, TRACKER_FRAME)
            ),
        )


def recording_messages(sequence: Sequence) -> Iterator[TimedMessage]:
    """Every message of the recording in log-time order (frames rendered lazily)."""
    merged = heapq.merge(_frame_stream(sequence), _tracker_stream(sequence), key=lambda m: m[:2])
    for _log_time, _order, message in merged:
        yield message


@dataclass(frozen=True)
class BagSummary:
    """What was written: paths, message counts per topic, and the bag's size.

    ``failure``: the writer's one-line error when a write failed (a full
    disk, a file size limit): the bag then reads to its last complete chunk
    and ``message_counts`` are what it holds; "" otherwise.
    """

    bag_path: Path
    ground_truth_paths: tuple[Path, ...]
    message_counts: dict[str, int]
    bag_bytes: int
    failure: str = ""


#: Compressed bytes per raw byte with zstd chunks, measured on the sample and
#: evaluation bags (640×480, default photometry): images about 0.54, 32FC1
#: ground-truth depth about 0.34 (NaN outside the field of view compresses).
_IMAGE_RATIO, _DEPTH_RATIO = 0.55, 0.35


@dataclass(frozen=True)
class SizeEstimate:
    """Expected size of a recording, bytes: all of it and the ground-truth depth's share."""

    total_bytes: int
    depth_bytes: int
    depth_frames: int


def estimated_size(config: SimulationConfig, frames: int) -> SizeEstimate:
    """The approximate size of a bag of ``frames`` images before rendering it.

    For zstd chunks (lz4 and none write more); small images compress less well.
    """
    depth_frames = -(-frames // config.depth_every)
    pixels = config.width * config.height
    sample_bytes = 2 if config.photometry.bit_depth > 8 else 1
    images = frames * pixels * config.channels * sample_bytes * _IMAGE_RATIO
    depth = depth_frames * pixels * 4 * _DEPTH_RATIO
    return SizeEstimate(int(images + depth), int(depth), depth_frames)


def write_bag(
    sequence: Sequence,
    path: str | Path,
    compression: str = "zstd",
    progress: Callable[[int], None] | None = None,
) -> BagSummary:
    """Render and write the recording to ``path`` and its ground truth beside it.

    ``path``: a new ``NAME.mcap`` file, or any other NAME for a rosbag2 bag
    directory (:class:`endo_io.bag.BagWriter`); the ground truth is
    ``NAME.ground_truth.yaml`` (...) beside it either way. ``progress`` is
    called with the number of frames written so far after each image.
    """
    path = Path(path)
    topics = [IMAGE_RAW, CAMERA_INFO, TRUE_DEPTH, TRUE_CAMERA_POSE, TRACKER_POSE]
    if sequence.gray_levels is not None:
        topics.append(GRAY_LEVEL)
    qos = qos_profiles_to_yaml([reliable_qos(10)])
    counts = dict.fromkeys(topics, 0)
    failure = ""
    with BagWriter(path, compression=compression) as bag:
        for topic in topics:
            bag.add_topic(topic, _TOPIC_TYPES[topic], qos)
        try:
            for message in recording_messages(sequence):
                data = serialize(message.message)
                bag.write(message.topic, data, message.log_time_ns)
                counts[message.topic] += 1
                if progress is not None and message.topic == IMAGE_RAW:
                    progress(counts[IMAGE_RAW])
        except BagError:
            if not bag.failure:
                raise
            failure = bag.failure  # a full disk: the file reads to its last complete chunk
    if failure:
        counts = {topic: bag.written[topic][0] for topic in topics}
    truth: tuple[Path, ...] = ()
    try:
        truth = write_ground_truth(sequence, path, counts)
    except OSError as error:
        if not failure:
            raise
        failure += f"; ground truth not written ({error.strerror})"
    size = sum(file.stat().st_size for file in bag.file_paths)
    return BagSummary(path, truth, counts, size, failure)


def _matrix(value: np.ndarray) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(value)]


def ground_truth_document(sequence: Sequence, stem: str, counts: dict[str, int]) -> dict[str, Any]:
    """The content of ``<stem>.ground_truth.yaml`` as plain data."""
    config = sequence.config
    p = config.photometry
    tracker = config.tracker
    camera = sequence.camera
    return {
        "format": "endo_sim ground truth 1",
        "bag": f"{stem}.mcap",
        "scene": sequence.ground_truth,
        "recording": {
            "start_ns": int(config.start_ns),
            "duration_s": sequence.duration_ns / NS_PER_S,
            "fps": float(config.fps),
            "frames": len(sequence.frame_times_ns),
            "depth_every": int(config.depth_every),
            "message_counts": dict(counts),
        },
        "camera": {
            "model_yaml": f"{stem}.camera.yaml",
            "width": camera.width,
            "height": camera.height,
            "K": _matrix(camera.K),
            "D": [float(x) for x in camera.D],
            "distortion_model": camera.distortion_model,
            "fov_radius_px": float(config.fov_radius),
            "frame_id": camera.frame_id,
        },
        "photometry": {
            "roughness_rad": float(p.roughness),
            "full_scale_distance_m": float(p.full_scale_distance_m),
            "exposure_m2": float(p.exposure),
            "light_offset_m": [float(x) for x in p.light_offset_m],
            "spot_exponent": float(p.spot_exponent),
            "vignetting_exponent": float(p.vignetting_exponent),
            "noise": bool(p.noise),
            "full_well_electrons": float(p.full_well_electrons),
            "read_noise_electrons": float(p.read_noise_electrons),
            "bit_depth": int(p.bit_depth),
            "specular_strength": float(p.specular_strength),
            "specular_shininess": float(p.specular_shininess),
            "channels": int(config.channels),
            "light_map_npy": f"{stem}.light_map.npy",
            "light_map_formula": "cos(theta)^(spot_exponent + vignetting_exponent)",
        },
        "texture": {
            "drift": float(config.texture.drift),
            "mottle": float(config.texture.mottle),
            "vessel_density_per_cm2": float(config.texture.vessel_density_per_cm2),
        },
        "response": {
            **p.response.parameters(),
            "inverse_response_npy": f"{stem}.inverse_response.npy",
        },
        "tracker": {
            "topic": TRACKER_POSE,
            "frame_id": TRACKER_FRAME,
            "units": tracker.units,
            "rate_hz": float(tracker.rate_hz),
            "latency_s": float(tracker.latency_s),
            "position_noise_rms_m": float(tracker.position_noise_rms_m),
            "rotation_noise_rms_deg": math.degrees(tracker.rotation_noise_rms_rad),
            "dropout_rate_hz": float(tracker.dropout_rate_hz),
            "dropout_mean_s": float(tracker.dropout_mean_s),
            "first_sample_s": float(tracker.phase_s),
            "T_marker_camera": _matrix(tracker.T_marker_camera),
            "T_tracker_world": _matrix(tracker.T_tracker_world),
            "model": "T_tracker_marker(t) = T_tracker_world @ T_world_camera(t) "
            "@ inv(T_marker_camera); stamp = t + latency; metres unless units == mm",
        },
    }


def write_ground_truth(
    sequence: Sequence, bag_path: Path, counts: dict[str, int]
) -> tuple[Path, ...]:
    """Write the ground-truth files beside ``bag_path``; returns their paths."""
    stem = bag_path.stem  # what endo_sim.ground_truth.ground_truth_of looks for
    folder = bag_path.parent
    camera_yaml = folder / f"{stem}.camera.yaml"
    sequence.camera.save_yaml(camera_yaml)
    inverse = folder / f"{stem}.inverse_response.npy"
    np.save(
        inverse,
        sequence.config.photometry.response.inverse_lut(sequence.config.photometry.bit_depth),
    )
    light = folder / f"{stem}.light_map.npy"
    np.save(light, sequence.renderer.light_map)
    document = folder / f"{stem}.ground_truth.yaml"
    content = ground_truth_document(sequence, stem, counts)
    content["bag"] = bag_path.name  # NAME.mcap, or a bag directory's NAME
    text = yaml.safe_dump(content, sort_keys=False, width=100)
    document.write_text(text)
    return (document, camera_yaml, inverse, light)
