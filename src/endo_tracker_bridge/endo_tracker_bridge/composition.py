"""The transform chain from the tracker's marker to the camera, and the clock fix.

Frames (each T_a_b maps points from frame b to frame a, x_a = T_a_b · x_b)::

    world ──T_world_tracker──▶ tracker ──T_tracker_marker──▶ marker ──T_marker_camera──▶ camera
    (parameter, identity        (measured, 60 Hz)             (hand–eye calibration,
     by default)                                                handeye.yaml)

    T_world_camera = T_world_tracker · T_tracker_marker · T_marker_camera

``camera`` is the endoscope's optical frame (REP 103: x right, y down,
z forward).

Clock. The hand–eye calibration measures ``time_offset_ns``, defined by

    tracker_stamp = camera_time + time_offset

for the same physical instant: a tracker that stamps its poses 20 ms late
(the usual sign: transmission and processing latency) has a positive offset
of +20 ms. A tracker stamp is put on the camera's clock by subtracting it.
"""

from __future__ import annotations

import numpy as np

from endo_tracker_bridge.errors import StampCorrectionError


def compose_camera_pose(
    T_world_tracker: np.ndarray, T_tracker_marker: np.ndarray, T_marker_camera: np.ndarray
) -> np.ndarray:
    """Return T_world_camera (4,4) float64 = T_world_tracker · T_tracker_marker · T_marker_camera.

    All inputs are (4,4) homogeneous transforms in metres, or stacks (...,4,4)
    that broadcast.
    """
    return (
        np.asarray(T_world_tracker, np.float64)
        @ np.asarray(T_tracker_marker, np.float64)
        @ (np.asarray(T_marker_camera, np.float64))
    )


def corrected_stamp_ns(tracker_stamp_ns: int, time_offset_ns: int) -> int:
    """Put a tracker stamp on the camera's clock: ``tracker_stamp_ns − time_offset_ns``.

    Integer nanoseconds in and out. Raises :class:`StampCorrectionError` when
    the result would be negative (a ROS stamp cannot be).
    """
    stamp = int(tracker_stamp_ns) - int(time_offset_ns)
    if stamp < 0:
        raise StampCorrectionError(
            f"tracker stamp {tracker_stamp_ns} ns minus time offset {time_offset_ns} ns is negative"
        )
    return stamp


