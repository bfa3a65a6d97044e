"""endo3d message I/O: conversions, camera model, QoS, MCAP bags, replay and record.

Message/numpy conversions, the camera model, QoS presets, rosbag2-compatible
MCAP reading and writing, replay and record.

The main entry points are exported here and imported on first use (so
``import endo_io`` loads neither rclpy nor OpenCV):

>>> from endo_io import BagReader, CameraModel, PoseBuffer
"""

from typing import TYPE_CHECKING

from endo_io.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from endo_io import topics
    from endo_io.bag import BagReader, BagWriter, deserialize, serialize
    from endo_io.camera import CameraModel
    from endo_io.diagnostics import InputHealth
    from endo_io.errors import Endo3dError
    from endo_io.image import array_to_image, image_to_array, irradiance_to_mono8
    from endo_io.pointcloud import pointcloud2_to_xyz, xyz_to_pointcloud2
    from endo_io.pose import (
        check_rotation,
        interpolate_transform,
        interpolate_transforms,
        invert_transform,
        matrix_to_pose,
        pose_to_matrix,
        rigid_transform,
        rotation_angle,
        transform_points,
        unit_quaternion,
    )
    from endo_io.pose_buffer import PoseBuffer
    from endo_io.process import run_node
    from endo_io.qos import SENSOR_DATA_QOS, create_reliable_publisher
    from endo_io.stamp import NS_PER_S, ns_to_stamp, stamp_to_ns
    from endo_io.stamp_matching import MatchedPair, StampMatcher

__all__ = [
    "NS_PER_S",
    "SENSOR_DATA_QOS",
    "BagReader",
    "BagWriter",
    "CameraModel",
    "Endo3dError",
    "InputHealth",
    "MatchedPair",
    "PoseBuffer",
    "StampMatcher",
    "array_to_image",
    "check_rotation",
    "create_reliable_publisher",
    "deserialize",
    "image_to_array",
    "interpolate_transform",
    "interpolate_transforms",
    "invert_transform",
    "irradiance_to_mono8",
    "matrix_to_pose",
    "ns_to_stamp",
    "pointcloud2_to_xyz",
    "pose_to_matrix",
    "rigid_transform",
    "rotation_angle",
    "run_node",
    "serialize",
    "stamp_to_ns",
    "topics",
    "transform_points",
    "unit_quaternion",
    "xyz_to_pointcloud2",
]
__getattr__, __dir__ = lazy_exports(__name__)
