"""Source ``ros``: a ``geometry_msgs/PoseStamped`` topic from a third-party driver.

The driver's message gives the marker in the tracker's frame
(``header.frame_id``). Some drivers publish millimetres in the metre fields;
the ``unit`` option scales them. When ``expected_frame_id`` is set, a pose in
any other frame is rejected rather than silently mixed in.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped

from endo_io.stamp import stamp_to_ns
from endo_tracker_bridge.conventions import LengthUnit, transform_from_quaternion
from endo_tracker_bridge.errors import UnexpectedFrameError
from endo_tracker_bridge.sample import TrackerSample
from endo_tracker_bridge.validation import DEFAULT_ROTATION_TOLERANCE


def sample_from_pose_stamped(
    msg: PoseStamped,
    unit: LengthUnit = LengthUnit.METRE,
    expected_frame_id: str = "",
    tool_id: str = "marker",
    tolerance: float = DEFAULT_ROTATION_TOLERANCE,
) -> TrackerSample:
    """Convert a driver's PoseStamped (translation in ``unit``) to a sample in metres.

    Raises NonFinitePoseError, NonUnitQuaternionError, or
    UnexpectedFrameError when ``expected_frame_id`` is non-empty and differs
    from ``msg.header.frame_id``.
    """
    if expected_frame_id and msg.header.frame_id != expected_frame_id:
        raise UnexpectedFrameError(
            f"pose in frame '{msg.header.frame_id}', expected '{expected_frame_id}'"
        )
    p, o = msg.pose.position, msg.pose.orientation
    T = transform_from_quaternion(
        np.array([o.x, o.y, o.z, o.w]), np.array([p.x, p.y, p.z]), unit, tolerance
    )
    return TrackerSample(
        stamp_ns=stamp_to_ns(msg.header.stamp), T_tracker_marker=T, tool_id=tool_id
    )
