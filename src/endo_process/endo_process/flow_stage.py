"""The flow step of an offline run: :class:`endo_flow.pipeline.FlowPipeline` and its messages.

Each shaded frame, with the camera pose at its stamp (None in a tracker
dropout: the pipeline keeps tracking and holds the scale, and makes no
world points), goes through ``FlowPipeline.process``. Its output becomes
the live graph's topics: ``/endoscope/depth`` (32FC1 metres, REP 118, once
the scale is usable), ``/endoscope/points`` (the frame's world points,
PointCloud2 in ``world``, grey as rgb), ``/endoscope/scale`` and, at the end,
``/endoscope/map`` (the fused voxel map's last state).

The messages are the ``flow`` node's (``endo_flow.node``): the scale is
``geometry_msgs/Vector3Stamped`` with x = s (metres per unit of
depth_relative, NaN before the first observation), y = the standard
deviation of ln s (inf while unknown), z = the filter state
(``endo_flow.scale.ScaleState`` value), the image's header; the clouds carry
the grey level as rgb; the map holds the voxels fused from at least
``map_min_count`` points.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from sensor_msgs.msg import PointCloud2

from endo_flow.node import pipeline_options
from endo_flow.pipeline import FlowFrame, FlowOptions, FlowOutput, FlowPipeline
from endo_flow.scale import ScaleEstimate
from endo_io.pointcloud import xyz_to_pointcloud2
from endo_io.stamp import ns_to_stamp
from endo_process.errors import ParameterFileError
from endo_process.shading import ShadedFrame


def flow_options(values: dict[str, Any]) -> FlowOptions:
    """The FlowOptions the flow node builds from its parameters (``pipeline_options``).

    Raises:
        ParameterFileError: a value the options refuse.
    """
    try:
        return pipeline_options(values)
    except (TypeError, ValueError) as error:
        raise ParameterFileError(f"flow: {error}") from None


def scale_message(estimate: ScaleEstimate, stamp_ns: int, frame_id: str) -> Vector3Stamped:
    """The scale estimate as the scale topic's message (see the module docstring)."""
    msg = Vector3Stamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.vector.x = float(estimate.value) if np.isfinite(estimate.value) else float("nan")
    msg.vector.y = float(estimate.log_std) if np.isfinite(estimate.log_std) else float("inf")
    msg.vector.z = float(int(estimate.state))
    return msg


def grey_cloud(points: np.ndarray, grey: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud2:
    """(N, 3) world points with (N,) grey levels 0–255 as a PointCloud2 (xyz + rgb)."""
    level = np.clip(np.rint(np.asarray(grey, np.float64)), 0, 255).astype(np.uint8)
    return xyz_to_pointcloud2(
        np.asarray(points, np.float32), stamp_ns, frame_id, np.repeat(level[:, None], 3, axis=1)
    )


class FlowStage:
    """One FlowPipeline over the shaded frames, in stamp order."""

    def __init__(self, options: FlowOptions, map_min_count: int = 1) -> None:
        self.pipeline = FlowPipeline(options)
        self.map_min_count = map_min_count

    def process(self, shaded: ShadedFrame, T_world_camera: np.ndarray | None) -> FlowOutput:
        """Run the pipeline on one frame (raises the pipeline's errors: see FlowPipeline)."""
        assert shaded.irradiance is not None and shaded.depth_relative is not None
        frame = FlowFrame(
            shaded.stamp_ns, shaded.irradiance, shaded.depth_relative, shaded.camera,
            T_world_camera,
        )  # fmt: skip
        return self.pipeline.process(frame)

    def map_cloud(self, stamp_ns: int, frame_id: str) -> PointCloud2 | None:
        """The voxel map's current state as a PointCloud2, None when empty or disabled."""
        voxel_map = self.pipeline.voxel_map
        if voxel_map is None or len(voxel_map) == 0:
            return None
        cloud = voxel_map.points(self.map_min_count)
        return grey_cloud(cloud.points, cloud.grey, stamp_ns, frame_id)
