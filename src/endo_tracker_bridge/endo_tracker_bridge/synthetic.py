"""Synthetic hand–eye recordings with known ground truth (no images).

The scene the solver's tests and ``bench/bench_handeye.py`` share: a 9×6
checkerboard with 5 mm squares fixed in the tracker frame
(:data:`T_TRACKER_TARGET`) is seen by a 640×480 camera rigidly fixed 25 cm
from the tracked marker (:data:`T_MARKER_CAMERA`, a rigid endoscope). The
camera swings and rolls in front of the board, 5–7 cm from it. The tracker
samples the marker at 60 Hz with noise, drops samples and stamps them late by
a fixed latency; the camera's corners are the exact projections plus pixel
noise, at 30 frames/s.

It lives in the package (not in a test's conftest) because tests under
``src/endo_tracker_bridge/test``, ``tests/`` and ``bench/`` all import it, and
an installed module is the one place all three can import without touching
``sys.path``.

Frames and units as in :mod:`endo_tracker_bridge.composition`: ``T_a_b`` maps
points from frame b to frame a, metres; stamps are integer nanoseconds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from endo_io.camera import CameraModel
from endo_io.pose import invert_transform, rigid_transform, rotation_angle, transform_points
from endo_tracker_bridge.handeye import BoardView, Checkerboard, board_view

#: The recording's first stamp: a realistic epoch (2023-11-14), so that stamp
#: arithmetic is exercised at the magnitudes real bags have.
EPOCH_NS = 1_700_000_000 * 1_000_000_000

#: 9×6 inner corners, 5 mm squares.
BOARD = Checkerboard(9, 6, 0.005)

#: A 640×480 endoscope camera with noticeable barrel distortion.
CAMERA = CameraModel.pinhole(
    640, 480, 520.0, 515.0, 322.0, 241.0, D=np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
)

#: The hand–eye transform the solver has to find: the camera 24 cm down the
#: scope from the marker, tilted arbitrarily.
T_MARKER_CAMERA = rigid_transform([0.3, -2.5, 0.4], [0.012, -0.008, -0.24])

#: Where the board is in the tracker frame, about 1.2 m from the tracker.
T_TRACKER_TARGET = rigid_transform([0.1, 0.2, -0.3], [0.1, -0.05, -1.2])


class SyntheticRecording(NamedTuple):
    """What a hand–eye recording gives the solver (unpacks as a 3-tuple).

    views: the camera's board views, one per image, camera-clock stamps.
    tracker_stamps_ns: (M,) int64 tracker stamps (late by the latency).
    tracker_poses: (M, 4, 4) noisy ``T_tracker_marker``, metres.
    """

    views: list[BoardView]
    tracker_stamps_ns: np.ndarray
    tracker_poses: np.ndarray


def camera_pose(t_s: float, motion_scale: float = 1.0) -> np.ndarray:
    """``T_tracker_camera`` (4, 4) at time ``t_s``: looking at the board from 5–7 cm.

    The camera swings about three axes with incommensurate periods (7, 5 and
    9 s) and moves towards and away from the board (3 s);
    ``motion_scale`` scales the swing angles (0.05 leaves too little rotation
    for a hand–eye solution).
    """
    centre = transform_points(T_TRACKER_TARGET, np.array([0.02, 0.0125, 0.0]))
    angles = motion_scale * np.array(
        [
            0.5 * np.sin(2 * np.pi * t_s / 7.0),
            0.4 * np.sin(2 * np.pi * t_s / 5.0 + 0.5),
            0.6 * np.sin(2 * np.pi * t_s / 9.0),
        ]
    )
    distance = 0.06 + 0.01 * np.sin(2 * np.pi * t_s / 3.0)
    R = T_TRACKER_TARGET[:3, :3] @ Rotation.from_euler("yxz", angles).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, centre - R[:, 2] * distance
    return T


def board_pose(t_s: float, motion_scale: float = 1.0) -> np.ndarray:
    """``T_camera_target`` (4, 4) at time ``t_s``: the board seen from :func:`camera_pose`."""
    return invert_transform(camera_pose(t_s, motion_scale)) @ T_TRACKER_TARGET


def synthetic_recording(
    *,
    seed: int = 0,
    duration_s: float = 10.0,
    latency_ms: float = 23.4,
    fps: float = 30.0,
    noise_mm: float = 0.25,
    noise_deg: float = 0.1,
    pixel_noise: float = 0.1,
    motion_scale: float = 1.0,
    dropout_fraction: float = 0.03,
    random_phase: bool = True,
    epoch_ns: int = EPOCH_NS,
) -> SyntheticRecording:
    """Simulate a hand–eye recording of ``duration_s`` seconds.

    Args:
        seed: seed of the one random generator every draw comes from.
        duration_s: recording length, seconds.
        latency_ms: tracker stamp minus true sample time (the time offset the
            calibration has to find), milliseconds.
        fps: camera frame rate; images start 0.1 s in and end 0.1 s early,
            so that every image lies inside the tracker's stream.
        noise_mm: 3-D RMS tracker position noise, millimetres.
        noise_deg: RMS tracker rotation noise, degrees (in the marker frame).
        pixel_noise: per-axis corner noise, pixels (Gaussian σ).
        motion_scale: scale of the camera's swing (see :func:`camera_pose`).
        dropout_fraction: fraction of tracker samples dropped at random.
        random_phase: start the 60 Hz tracker clock at a random phase within
            its first period (else exactly at 0).
        epoch_ns: added to every stamp, camera and tracker alike.

    Returns:
        The :class:`SyntheticRecording` (views, tracker stamps, tracker poses).
    """
    rng = np.random.default_rng(seed)
    t_tracker = np.arange(0.0, duration_s, 1 / 60)
    if random_phase:
        t_tracker = t_tracker + rng.uniform(0, 1 / 60)
    t_tracker = t_tracker[rng.random(len(t_tracker)) > dropout_fraction]
    X_inverse = invert_transform(T_MARKER_CAMERA)
    poses = []
    for t in t_tracker:
        A = camera_pose(t, motion_scale) @ X_inverse
        A[:3, 3] += rng.normal(0.0, noise_mm * 1e-3 / np.sqrt(3), 3)
        wobble = rng.normal(0.0, np.radians(noise_deg) / np.sqrt(3), 3)
        A[:3, :3] = A[:3, :3] @ Rotation.from_rotvec(wobble).as_matrix()
        poses.append(A)
    stamps = epoch_ns + np.round((t_tracker + latency_ms * 1e-3) * 1e9).astype(np.int64)
    P = BOARD.object_points()
    views = []
    for t in np.arange(0.1, duration_s - 0.1, 1 / fps):
        uv = CAMERA.project(transform_points(board_pose(t, motion_scale), P))
        uv += rng.normal(0.0, pixel_noise, uv.shape)
        views.append(board_view(epoch_ns + round(t * 1e9), uv, BOARD, CAMERA))
    return SyntheticRecording(views, stamps, np.stack(poses))


def transform_error(T_true: np.ndarray, T_estimated: np.ndarray) -> tuple[float, float]:
    """Return (translation error mm, rotation error degrees) of ``T_true⁻¹ · T_estimated``.

    Args:
        T_true: (4, 4) true rigid transform, metres.
        T_estimated: (4, 4) its estimate, metres.
    """
    delta = invert_transform(T_true) @ T_estimated
    return (
        1e3 * float(np.linalg.norm(delta[:3, 3])),
        float(np.degrees(rotation_angle(delta[:3, :3]))),
    )
