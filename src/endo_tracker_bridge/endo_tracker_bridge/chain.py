"""The bridge's whole per-sample chain as one ROS-free object: gate, compose, restamp.

For every tracker sample the bridge node (and the offline processor,
``endo-process``) does the same three things, in this order:

1. :class:`endo_tracker_bridge.validation.SampleGate` accepts or rejects the
   sample against the tool's history (visible, time forwards, speed limits);
2. :func:`endo_tracker_bridge.composition.compose_camera_pose` turns the
   marker pose into ``T_world_camera`` through ``T_world_tracker`` and the
   hand–eye ``T_marker_camera``;
3. :func:`endo_tracker_bridge.composition.corrected_stamp_ns` puts the
   tracker stamp on the camera's clock (minus the calibrated time offset).

:class:`CameraPoseChain` holds the settings and the gate's state so that a
live node and an offline run over a recording give the same poses for the
same samples. Units are already metres in a :class:`TrackerSample` (the
sources convert them);
:func:`endo_tracker_bridge.sources.ros.sample_from_pose_stamped` does that for
a recorded PoseStamped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from endo_io.clock_jump import ClockJump
from endo_tracker_bridge.composition import compose_camera_pose, corrected_stamp_ns
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.sample import TrackerSample
from endo_tracker_bridge.validation import SampleGate, SpeedLimits


@dataclass(frozen=True)
class CameraPose:
    """One accepted sample and the camera pose it gives.

    Attributes:
        sample: the accepted tracker sample (T_tracker_marker, tracker clock).
        stamp_ns: integer ns on the camera's clock (tracker stamp − time offset).
        T_world_camera: (4, 4) float64, metres, optical frame → world.
        clock_jump: the jump of the tool's time this sample revealed (its
            history was reset before it was accepted), or None.
    """

    sample: TrackerSample
    stamp_ns: int
    T_world_camera: np.ndarray = field(repr=False)
    clock_jump: ClockJump | None = None


class CameraPoseChain:
    """Marker samples in, camera poses out, with the bridge's rejection rules.

    Args:
        calibration: the hand–eye and clock calibration (``handeye.yaml``);
            :meth:`HandEyeCalibration.identity` when there is none.
        T_world_tracker: (4, 4) float64, metres, tracker frame → world.
        limits: the gate's speed limits.
    """

    def __init__(
        self,
        calibration: HandEyeCalibration,
        T_world_tracker: np.ndarray | None = None,
        limits: SpeedLimits | None = None,
    ) -> None:
        self.calibration = calibration
        self.T_world_tracker = (
            np.eye(4) if T_world_tracker is None else np.asarray(T_world_tracker, np.float64)
        )
        self.gate = SampleGate(limits)

    def accept(self, sample: TrackerSample, arrival_ns: int | None = None) -> CameraPose:
        """Gate ``sample`` and return its camera pose.

        Args:
            sample: the tracker sample.
            arrival_ns: ``time.monotonic_ns()`` when it arrived (a live source),
                so that a pose after a long silence is not taken for a jump;
                None offline.

        Raises:
            ToolNotVisibleError, NonFinitePoseError, TimeWentBackwardsError,
            FutureStampError, SpeedLimitError: the gate rejected the sample (it
            is not remembered).
            StampCorrectionError: the corrected stamp would be negative.
        """
        admitted = self.gate.admit(sample, arrival_ns)
        accepted = admitted.sample
        T_world_camera = compose_camera_pose(
            self.T_world_tracker, accepted.T_tracker_marker, self.calibration.T_marker_camera
        )
        stamp_ns = corrected_stamp_ns(accepted.stamp_ns, self.calibration.time_offset_ns)
        return CameraPose(accepted, stamp_ns, T_world_camera, admitted.clock_jump)

    def reset(self) -> None:
        """Forget the gate's history (a restarted tracker, a looped recording)."""
        self.gate.reset()
