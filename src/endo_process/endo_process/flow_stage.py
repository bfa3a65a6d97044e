"""The flow step of an offline run: :class:`endo_flow.pipeline.FlowPipeline` and its messages.

Each shaded frame, with the camera pose at its stamp (None in a tracker
dropout: the pipeline keeps tracking and holds the scale, and makes no
world points), goes through ``FlowPipeline.process``. Its output becomes
the live graph's topics: ``/endoscope/depth`` (32FC1 metres, REP 118, once
the scale is usable), ``/endoscope/points`` (the frame's world points,
PointCloud2 in ``world``, grey as rgb; full resolution by default, unlike the
live topic: :func:`offline_flow_options`), ``/endoscope/scale`` and, at the
end, ``/endoscope/map`` (the fused voxel map's last state, fused from every
frame).

The messages are the ``flow`` node's, built by the same functions
(:mod:`endo_flow.messages`: ``scale_message``, ``grey_cloud`` and its CDR
bytes built directly, ``grey_cloud_cdr``); the map holds the voxels fused
from at least ``map_min_count`` points.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2

from endo_flow.messages import grey_cloud
from endo_flow.node import pipeline_options
from endo_flow.pipeline import FlowFrame, FlowOptions, FlowOutput, FlowPipeline
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


def offline_flow_options(values: dict[str, Any], cloud_decimation: int | None = None
                         ) -> FlowOptions:
    """The flow node's options (:func:`flow_options`) as an offline run uses them.

    The live node's, so that the offline output compares with a live
    recording frame by frame: the map at the parameters' ``map_decimation``
    (1, every pixel) of every ``map_every``-th frame (8), and
    ``/endoscope/points`` at their ``cloud_decimation`` (4) unless
    ``cloud_decimation`` (the command line's) says otherwise. Fusing every
    pixel of every frame would cost ~17 CPU-ms per frame for a map no closer
    to the truth (1.10 against 1.04 mm RMS on the held-out matte abdomen,
    docs/flow.md); full-resolution points double the output (6.8 against 3.2
    MB per phantom frame) and cost ~9 CPU-ms per frame to write.

    Raises:
        ParameterFileError: a value the options refuse.
    """
    options = flow_options(values)
    if cloud_decimation is None:
        return options
    try:
        return replace(options, cloud_decimation=int(cloud_decimation))
    except ValueError as error:
        raise ParameterFileError(f"flow: {error}") from None


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
