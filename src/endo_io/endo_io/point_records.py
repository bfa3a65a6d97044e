"""The point records of endo3d's PointCloud2 data, without ROS.

depth_image_proc's layout (``PointCloud2Modifier::setPointCloud2FieldsByString``)::

    without rgb: x FLOAT32 @0, y FLOAT32 @4, z FLOAT32 @8, 4 pad bytes -> point_step 16
    with rgb:    x @0, y @4, z @8, 4 pad, rgb FLOAT32 @16, 12 pad  -> point_step 32

``rgb`` holds the bytes of the uint32 ``0x00RRGGBB`` reinterpreted as float32.
:mod:`endo_io.pointcloud` wraps such records in ``sensor_msgs/PointCloud2``;
this module is apart so that an algorithm module (the flow node's voxel map)
can write records without importing ROS message packages.
"""

from __future__ import annotations

import numpy as np

XYZ_POINT_STEP = 16
XYZRGB_POINT_STEP = 32
RGB_OFFSET = 16

#: The point records of a cloud without and with colour (depth_image_proc's layout).
XYZ_RECORD = np.dtype(
    {"names": ["x", "y", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8],
     "itemsize": XYZ_POINT_STEP}
)
XYZRGB_RECORD = np.dtype(
    {"names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<u4"],
     "offsets": [0, 4, 8, RGB_OFFSET], "itemsize": XYZRGB_POINT_STEP}
)


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """Pack (..., 3) uint8 R, G, B into (...,) uint32 ``0x00RRGGBB``."""
    channels = rgb.astype(np.uint32)
    return (channels[..., 0] << 16) | (channels[..., 1] << 8) | channels[..., 2]


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """Unpack (...,) uint32 ``0x??RRGGBB`` into (..., 3) uint8 R, G, B."""
    shifts = np.array([16, 8, 0], dtype=np.uint32)
    return ((packed[..., None] >> shifts) & 0xFF).astype(np.uint8)
