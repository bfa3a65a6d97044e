"""One tracker measurement in the bridge's own conventions.

Whatever a tracker sends (millimetres or metres, w-first or w-last
quaternions, 4x4 matrices, frame numbers), each source turns it into a
:class:`TrackerSample`: integer nanoseconds on the tracker's clock, and a 4x4
homogeneous ``T_tracker_marker`` in metres that maps points from the marker
frame to the tracker frame.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


class ToolStatus(enum.Enum):
    """What the tracker says about the tool in this sample."""

    #: The tool was seen and its pose is valid.
    VISIBLE = "visible"
    #: The tool is out of the measurement volume or occluded (NDI "MISSING").
    MISSING = "missing"
    #: The tool's port is not enabled (NDI "DISABLED").
    DISABLED = "disabled"


@dataclass(frozen=True)
class TrackerSample:
    """One pose of one tool from a tracker.

    Attributes:
        stamp_ns: Time of the measurement on the tracker's clock, integer nanoseconds.
        T_tracker_marker: (4, 4) float64 homogeneous transform, metres, marker frame → tracker
            frame (x_tracker = T · x_marker).
        tool_id: Name of the tool (ROS frame id, OpenIGTLink device name, NDI port
            handle as text, or the log's tool column).
        status: Visibility reported by the tracker.
        frame_number: Tracker frame counter when the tracker has one (NDI: 60 Hz), else None.
        quality: Tracker's own fit error for the tool when it has one (NDI: RMS marker
            fit error in mm, lower is better), else None.
    """

    stamp_ns: int
    T_tracker_marker: np.ndarray = field(repr=False)
    tool_id: str = ""
    status: ToolStatus = ToolStatus.VISIBLE
    frame_number: int | None = None
    quality: float | None = None

    def __post_init__(self) -> None:
        matrix = np.asarray(self.T_tracker_marker, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"T_tracker_marker must be (4, 4), got {matrix.shape}")
        matrix = matrix.copy()
        matrix.setflags(write=False)
        object.__setattr__(self, "T_tracker_marker", matrix)
        object.__setattr__(self, "stamp_ns", int(self.stamp_ns))

    @property
    def translation_m(self) -> np.ndarray:
        """(3,) float64 marker origin in the tracker frame, metres."""
        return self.T_tracker_marker[:3, 3]

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) float64 rotation marker → tracker."""
        return self.T_tracker_marker[:3, :3]
