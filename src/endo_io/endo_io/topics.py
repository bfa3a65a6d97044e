"""Every default topic and frame name of the endo3d graph, in one place.

Nodes subscribe and publish these names (absolute, so that a node started
without a namespace still lands on the graph's topics; remap or push a
namespace to change them), and the simulator's bag writer, the offline
processor, the viewers and the bringup use the same constants.

=================================  =================================================
topic                              what
=================================  =================================================
``/endoscope/image_raw``           the camera driver's image (any encoding)
``/endoscope/camera_info``         its calibration, same stamp and frame
``/endoscope/image_corrected``     linear irradiance, 16UC1 fixed point or 32FC1 (``endo_calib``)
``/endoscope/depth_relative``      relative depth along z, 32FC1 (``endo_sfs``)
``/endoscope/normals``             unit normals, 32FC3, optical frame (``endo_sfs``)
``/endoscope/depth``               metric depth, 32FC1 metres, REP 118 (``endo_flow``)
``/endoscope/points``              world-frame PointCloud2 of each frame (``endo_flow``)
``/endoscope/map``                 fused voxel map in ``world`` (``endo_flow``)
``/endoscope/scale``               the depth scale and its confidence (``endo_flow``)
``/endoscope/pose``                ``T_world_camera`` at camera time (tracker bridge)
``/tracker/pose``                  the tracker driver's marker pose (input)
``/tracker/marker_pose``           the validated marker pose (tracker bridge)
``/ground_truth/depth``            the simulator's true depth, metres
``/ground_truth/camera_pose``      the simulator's true ``T_world_camera``
``/calibration/gray_level``        the gray card's reflectance level (calibration bags)
=================================  =================================================
"""

from __future__ import annotations

from typing import Final

IMAGE_RAW: Final = "/endoscope/image_raw"
CAMERA_INFO: Final = "/endoscope/camera_info"
IMAGE_CORRECTED: Final = "/endoscope/image_corrected"
DEPTH_RELATIVE: Final = "/endoscope/depth_relative"
NORMALS: Final = "/endoscope/normals"
DEPTH: Final = "/endoscope/depth"
POINTS: Final = "/endoscope/points"
MAP: Final = "/endoscope/map"
SCALE: Final = "/endoscope/scale"
CAMERA_POSE: Final = "/endoscope/pose"

TRACKER_POSE: Final = "/tracker/pose"
MARKER_POSE: Final = "/tracker/marker_pose"

TRUE_DEPTH: Final = "/ground_truth/depth"
TRUE_CAMERA_POSE: Final = "/ground_truth/camera_pose"

GRAY_LEVEL: Final = "/calibration/gray_level"

DIAGNOSTICS: Final = "/diagnostics"
CLOCK: Final = "/clock"
TF: Final = "/tf"
TF_STATIC: Final = "/tf_static"

#: REP 103 frames.
WORLD_FRAME: Final = "world"
TRACKER_FRAME: Final = "tracker"
MARKER_FRAME: Final = "endoscope_marker"
OPTICAL_FRAME: Final = "endoscope_optical_frame"
