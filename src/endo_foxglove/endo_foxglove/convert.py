"""ROS messages of the graph → Foxglove's own schemas (``foxglove.messages``).

Every function takes a ROS message, validates it with :mod:`endo_io` (bad
input raises an :class:`~endo_io.errors.Endo3dError` subclass naming the
cause) and returns the Foxglove message the bridge logs:

=============================  ==========================  =================================
ROS                            Foxglove                    what changes
=============================  ==========================  =================================
``sensor_msgs/Image``          ``foxglove.RawImage``       packed, native byte order;
                                                           32FC3 becomes rgb8 (Foxglove has
                                                           no 3-channel float encoding); the
                                                           corrected image's 16UC1 fixed
                                                           point becomes 32FC1 irradiance
``sensor_msgs/CameraInfo``     ``foxglove.CameraCalibration``  K/P of the image as published
                                                           (binning and ROI applied)
``sensor_msgs/PointCloud2``    ``foxglove.PointCloud``     finite points only, decimated
                                                           to ``max_points``, packed x, y, z
                                                           float32 (+ red, green, blue,
                                                           alpha uint8): stride 12 or 16
``geometry_msgs/PoseStamped``  ``foxglove.PoseInFrame``    the same pose
:class:`endo_io.tf.StampedTransform`  ``foxglove.FrameTransforms``  one entry per edge
=============================  ==========================  =================================

Clouds are repacked with numpy in one pass over structured arrays, never
per point in Python.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from foxglove.messages import (
    CameraCalibration,
    FrameTransform,
    FrameTransforms,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    Pose,
    PoseInFrame,
    Quaternion,
    RawImage,
    Timestamp,
    Vector3,
)
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from endo_io.camera import CameraModel
from endo_io.image import image_to_array, image_to_irradiance
from endo_io.pointcloud import pointcloud2_to_xyz
from endo_io.pose import matrix_to_quaternion, pose_to_matrix
from endo_io.stamp import NS_PER_S, stamp_to_ns
from endo_io.tf import StampedTransform

_F32 = PackedElementFieldNumericType.Float32
_U8 = PackedElementFieldNumericType.Uint8


def timestamp(stamp_ns: int) -> Timestamp:
    """Foxglove timestamp of integer nanoseconds (>= 0)."""
    sec, nsec = divmod(int(stamp_ns), NS_PER_S)
    return Timestamp(sec, nsec)


def raw_image(msg: Image, *, irradiance: bool = False) -> RawImage:
    """A ``sensor_msgs/Image`` as a Foxglove ``RawImage`` (pixels of :func:`display_pixels`).

    Raises:
        ImageEncodingError: an encoding endo_io does not read (or, with
            ``irradiance``, not 16UC1, 32FC1 or 32FC3).
        ImageLayoutError: step, size and data length disagree.
    """
    pixels, encoding = display_pixels(msg, irradiance=irradiance)
    height, width = pixels.shape[:2]
    return RawImage(
        timestamp=timestamp(stamp_to_ns(msg.header.stamp)),
        frame_id=msg.header.frame_id,
        width=width,
        height=height,
        encoding=encoding,
        step=pixels.strides[0],
        data=pixels.tobytes(),
    )


def display_pixels(msg: Image, *, irradiance: bool = False) -> tuple[np.ndarray, str]:
    """The pixels and encoding a viewer is sent for ``msg``.

    The pixels are validated and repacked by :func:`endo_io.image.image_to_array`
    (padded rows and big-endian data become packed, native little-endian).
    ``32FC3`` (colour irradiance, normals) is scaled to ``rgb8`` by its
    largest finite value, NaN black. With ``irradiance`` (the message is a
    corrected image) a single-channel image, 16UC1 fixed point or 32FC1, is
    sent as 32FC1 irradiance (:func:`endo_io.image.image_to_irradiance`),
    so the layout's 0-1 range shows it whatever the correction node's
    ``output_encoding``.

    Returns:
        (H, W) or (H, W, C) C-contiguous pixels, and their encoding.

    Raises:
        ImageEncodingError: as :func:`raw_image`.
        ImageLayoutError: as :func:`raw_image`.
    """
    if irradiance and msg.encoding != "32FC3":
        pixels, encoding = image_to_irradiance(msg), "32FC1"
    else:
        pixels, encoding = image_to_array(msg), msg.encoding
    if encoding == "32FC3":
        finite = np.isfinite(pixels)
        top = float(np.max(pixels, where=finite, initial=0.0))
        scale = 255.0 / top if top > 0.0 else 0.0
        with np.errstate(invalid="ignore"):
            scaled = np.clip(np.where(finite, pixels, 0.0) * scale, 0.0, 255.0)
        pixels, encoding = (scaled + 0.5).astype(np.uint8), "rgb8"
    return pixels, encoding


def camera_calibration(msg: CameraInfo) -> CameraCalibration:
    """A ``sensor_msgs/CameraInfo`` as a Foxglove ``CameraCalibration``.

    Foxglove projects with K/P as given, so binning and ROI are applied first
    (:meth:`endo_io.camera.CameraModel.from_camera_info`): the calibration
    describes the image as published.

    Raises:
        CameraModelError: an uncalibrated or inconsistent CameraInfo.
    """
    model = CameraModel.from_camera_info(msg)
    return CameraCalibration(
        timestamp=timestamp(stamp_to_ns(msg.header.stamp)),
        frame_id=msg.header.frame_id,
        width=model.width,
        height=model.height,
        distortion_model=model.distortion_model,
        D=[float(v) for v in model.D],
        K=[float(v) for v in model.K.ravel()],
        R=[float(v) for v in model.R.ravel()],
        P=[float(v) for v in model.P.ravel()],
    )


@dataclass(frozen=True)
class ViewerCloud:
    """A cloud packed for the viewer, and what was left out.

    Attributes:
        message: the Foxglove ``PointCloud``.
        published: points in it.
        finite: finite points of the input.
        total: points of the input (``width * height``).
    """

    message: PointCloud
    published: int
    finite: int
    total: int


def pack_points(
    xyz: np.ndarray, rgb: np.ndarray | None, *, max_points: int
) -> tuple[bytes, int, int]:
    """Finite points, decimated to at most ``max_points``, as a packed buffer.

    Args:
        xyz: (..., 3) float32 metres; rows with any NaN/inf are dropped.
        rgb: None, or (..., 3) uint8 colours of the same points.
        max_points: > 0; a larger cloud keeps every k-th finite point,
            ``k = ceil(finite / max_points)``, so the viewer gets an even
            spread of the surface.

    Returns:
        ``(buffer, point_count, finite_count)``: little-endian x, y, z
        float32 (stride 12), or x, y, z then red, green, blue, alpha uint8
        (alpha 255, stride 16) when ``rgb`` is given.
    """
    if max_points <= 0:
        raise ValueError(f"max_points must be positive, got {max_points}")
    points = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    # A NaN or an inf in any coordinate makes x + y + z non-finite. Two
    # column adds take ~0.2 ms for 300 000 points; numpy's row reductions
    # (sum or all over axis 1 of an (N, 3) array) take ~20 ms.
    with np.errstate(invalid="ignore", over="ignore"):
        total = points[:, 0] + points[:, 1]
        total += points[:, 2]
    keep = np.flatnonzero(np.isfinite(total))
    finite = int(keep.size)
    step = -(-finite // max_points) if finite else 1
    keep = keep[::step]
    chosen = np.take(points, keep, axis=0).astype("<f4", copy=False)  # faster than [keep]
    if rgb is None:
        return chosen.tobytes(), int(keep.size), finite
    # Column by column (long 1-D loops); writing (N, 3) blocks into a strided
    # view is an order of magnitude slower in numpy.
    packed = np.empty((keep.size, 4), dtype="<u4")
    bits = chosen.view("<u4")
    for axis in range(3):
        packed[:, axis] = bits[:, axis]
    colours = np.take(np.asarray(rgb, dtype=np.uint8).reshape(-1, 3), keep, axis=0)
    packed[:, 3] = 0xFF000000  # bytes 12..15 little-endian: red, green, blue, alpha 255
    for axis, shift in ((0, 0), (1, 8), (2, 16)):
        packed[:, 3] |= colours[:, axis].astype("<u4") << np.uint32(shift)
    return packed.tobytes(), int(keep.size), finite


def point_cloud(msg: PointCloud2, *, max_points: int) -> ViewerCloud:
    """A ``sensor_msgs/PointCloud2`` as a Foxglove ``PointCloud`` of at most ``max_points``.

    Raises:
        PointCloudError: no float32 x, y, z, or an inconsistent layout.
    """
    xyz, rgb = pointcloud2_to_xyz(msg)
    data, count, finite = pack_points(xyz, rgb, max_points=max_points)
    fields = [
        PackedElementField(name=name, offset=offset, type=_F32)
        for name, offset in (("x", 0), ("y", 4), ("z", 8))
    ]
    if rgb is not None:
        fields += [
            PackedElementField(name=name, offset=12 + k, type=_U8)
            for k, name in enumerate(("red", "green", "blue", "alpha"))
        ]
    cloud = PointCloud(
        timestamp=timestamp(stamp_to_ns(msg.header.stamp)),
        frame_id=msg.header.frame_id,
        pose=Pose(position=Vector3(), orientation=Quaternion(w=1.0)),
        point_stride=12 if rgb is None else 16,
        fields=fields,
        data=data,
    )
    return ViewerCloud(cloud, count, finite, int(msg.width) * int(msg.height))


def pose_in_frame(msg: PoseStamped) -> PoseInFrame:
    """A ``geometry_msgs/PoseStamped`` as a Foxglove ``PoseInFrame`` (normalised quaternion).

    Raises:
        PoseError: a NaN position or a quaternion that is not unit.
    """
    T, stamp_ns = pose_to_matrix(msg)
    x, y, z, w = matrix_to_quaternion(T[:3, :3])
    return PoseInFrame(
        timestamp=timestamp(stamp_ns),
        frame_id=msg.header.frame_id,
        pose=Pose(
            position=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
        ),
    )


def frame_transforms(edges: Sequence[StampedTransform]) -> FrameTransforms:
    """Edges of the frame tree as one Foxglove ``FrameTransforms`` (parent → child each)."""
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=timestamp(edge.stamp_ns),
                parent_frame_id=edge.parent_frame,
                child_frame_id=edge.child_frame,
                translation=Vector3(
                    x=float(edge.translation[0]),
                    y=float(edge.translation[1]),
                    z=float(edge.translation[2]),
                ),
                rotation=Quaternion(
                    x=float(edge.rotation[0]),
                    y=float(edge.rotation[1]),
                    z=float(edge.rotation[2]),
                    w=float(edge.rotation[3]),
                ),
            )
            for edge in edges
        ]
    )
