"""Optical tracker (ROS, OpenIGTLink, NDI, CSV) to camera pose.

Includes the hand-eye and clock calibration (``endo-handeye``). The names
below are imported on first use, so ``import endo_tracker_bridge`` is cheap.
"""

from typing import TYPE_CHECKING

from endo_io.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from endo_tracker_bridge.composition import compose_camera_pose, corrected_stamp_ns
    from endo_tracker_bridge.errors import HandEyeError, TrackerSampleError, TrackerSourceError
    from endo_tracker_bridge.handeye import (
        Checkerboard,
        HandEyeResult,
        calibrate_hand_eye,
        solve_hand_eye,
    )
    from endo_tracker_bridge.handeye_file import HandEyeCalibration
    from endo_tracker_bridge.node import TrackerBridgeNode
    from endo_tracker_bridge.sample import ToolStatus, TrackerSample
    from endo_tracker_bridge.validation import SampleGate, SpeedLimits

__all__ = [
    "Checkerboard",
    "HandEyeCalibration",
    "HandEyeError",
    "HandEyeResult",
    "SampleGate",
    "SpeedLimits",
    "ToolStatus",
    "TrackerBridgeNode",
    "TrackerSample",
    "TrackerSampleError",
    "TrackerSourceError",
    "calibrate_hand_eye",
    "compose_camera_pose",
    "corrected_stamp_ns",
    "solve_hand_eye",
]
__getattr__, __dir__ = lazy_exports(__name__)
