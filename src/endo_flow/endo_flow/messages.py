"""The flow node's output messages built from the pipeline's arrays (one builder each).

The ``endo-flow`` node and the offline processor publish the same messages;
both build them here.

``/endoscope/scale`` is a ``geometry_msgs/Vector3Stamped``: the installed
message packages have no type for "a value, its uncertainty and a state";
this one is stamped (so the scale can be matched with its depth frame),
carries three float64 fields and is plotted by every ROS tool. Layout:
x = s, metres per unit of depth_relative (NaN before the first
observation); y = the standard deviation of ln s (≈ relative standard
deviation of s; inf before the first observation); z = the state,
:class:`endo_flow.scale.ScaleState` as a number (0 initializing, 1
tracking, 2 holding, 3 recovering). The header is the frame's (stamp,
optical frame id).
"""

from __future__ import annotations

import struct

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from sensor_msgs.msg import PointCloud2

from endo_flow.scale import ScaleEstimate
from endo_io.cdr import header_cdr
from endo_io.pointcloud import xyz_to_pointcloud2, xyz_to_pointcloud2_cdr
from endo_io.stamp import ns_to_stamp

#: The scale topic's message type (layout in the module docstring).
SCALE_TYPE = "geometry_msgs/msg/Vector3Stamped"


def scale_message(estimate: ScaleEstimate, stamp_ns: int, frame_id: str) -> Vector3Stamped:
    """The scale estimate as the scale topic's message (layout in the module docstring)."""
    msg = Vector3Stamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.vector.x = float(estimate.value) if np.isfinite(estimate.value) else float("nan")
    msg.vector.y = float(estimate.log_std) if np.isfinite(estimate.log_std) else float("inf")
    msg.vector.z = float(int(estimate.state))
    return msg


def scale_message_cdr(estimate: ScaleEstimate, stamp_ns: int, frame_id: str) -> bytes:
    """:func:`scale_message`'s CDR bytes, built directly (endo-process writes them).

    Little-endian CDR (the 4-byte encapsulation header, then, aligned from
    its end): int32 sec, uint32 nanosec, frame_id (uint32 length with the
    NUL, bytes, NUL), zero padding to 8, three float64 (x, y, z). The bytes
    rclpy's serialisation of the message gives (tested); ~0.01 against
    ~0.09 ms a message.
    """
    head = header_cdr(stamp_ns, frame_id)
    value, log_std = float(estimate.value), float(estimate.log_std)
    return b"".join((
        head, bytes(-(len(head) - 4) % 8),
        struct.pack("<3d", value if np.isfinite(value) else float("nan"),
                    log_std if np.isfinite(log_std) else float("inf"),
                    float(int(estimate.state))),
    ))  # fmt: skip


def grey_cloud(points: np.ndarray, grey: np.ndarray, stamp_ns: int, frame_id: str
               ) -> PointCloud2:
    """(N, 3) points, metres, with (N,) grey levels 0–255 as a PointCloud2 (xyz + rgb grey)."""
    return xyz_to_pointcloud2(np.asarray(points, np.float32), stamp_ns, frame_id,
                              _grey_rgb(grey))


def grey_cloud_cdr(points: np.ndarray, grey: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """:func:`grey_cloud`'s CDR bytes, built directly (what the live node publishes)."""
    return xyz_to_pointcloud2_cdr(np.asarray(points, np.float32), stamp_ns, frame_id,
                                  _grey_rgb(grey))


def _grey_rgb(grey: np.ndarray) -> np.ndarray:
    level = np.asarray(grey)
    if level.dtype != np.uint8:  # the pipeline's grey levels are uint8 already
        level = np.clip(np.rint(level.astype(np.float64)), 0, 255).astype(np.uint8)
    return np.repeat(level[:, None], 3, axis=1)
