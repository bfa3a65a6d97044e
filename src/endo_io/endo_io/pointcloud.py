"""``sensor_msgs/PointCloud2`` with x, y, z and optional packed rgb, as depth_image_proc makes them.

Layout written (the one ``PointCloud2Modifier::setPointCloud2FieldsByString``
gives depth_image_proc's ``point_cloud_xyz`` / ``point_cloud_xyzrgb``)::

    without rgb: x FLOAT32 @0, y FLOAT32 @4, z FLOAT32 @8, 4 pad bytes -> point_step 16
    with rgb:    x @0, y @4, z @8, 4 pad, rgb FLOAT32 @16, 12 pad  -> point_step 32

``rgb`` holds the bytes of the uint32 ``0x00RRGGBB`` (little-endian: B at
byte 0, G at 1, R at 2, 0 at 3) reinterpreted as float32, which is what PCL
and RViz read. Padding bytes are zero. ``is_bigendian`` is False,
``row_step = width * point_step``, an (H, W, 3) input gives an organised
H x W cloud and an (N, 3) one gives 1 x N. Invalid points stay in the cloud
as NaN (organised clouds keep their grid), and ``is_dense`` is True only
when every coordinate is finite.

:func:`xyz_to_pointcloud2_cdr` gives the same message's CDR bytes directly,
for a live node to publish as they are (one copy of the points instead of
three).

The reader accepts any layout that has float32 ``x``, ``y``, ``z`` (and
optionally ``rgb`` or ``rgba``, float32 or uint32), in any order, with any
padding, row padding or byte order.

The records' layout itself (:data:`XYZ_RECORD`, :data:`XYZRGB_RECORD`,
:func:`pack_rgb`) is :mod:`endo_io.point_records`, which needs no ROS, so
that an algorithm module can write records (the flow node's voxel map).
"""

from __future__ import annotations

import struct
from array import array as byte_array

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from endo_io.cdr import LITTLE_ENDIAN_ENCAPSULATION, cdr_string, header_cdr
from endo_io.errors import PointCloudError
from endo_io.point_records import (
    RGB_OFFSET,
    XYZ_RECORD,
    XYZRGB_RECORD,
    pack_rgb,
    unpack_rgb,
)
from endo_io.stamp import ns_to_stamp

_FIELD_SIZES = {
    PointField.INT8: 1, PointField.UINT8: 1, PointField.INT16: 2, PointField.UINT16: 2,
    PointField.INT32: 4, PointField.UINT32: 4, PointField.FLOAT32: 4, PointField.FLOAT64: 8,
}


def xyz_to_pointcloud2(
    points: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    rgb: np.ndarray | None = None,
) -> PointCloud2:
    """Return a PointCloud2 with float32 x, y, z and, if given, packed rgb.

    Args:
        points: (N, 3) or (H, W, 3) float32 (any float is cast) coordinates
            in metres in ``frame_id``; NaN marks an invalid point and is kept.
        stamp_ns: header stamp, integer nanoseconds (>= 0).
        frame_id: header frame id, e.g. ``endoscope_optical_frame``.
        rgb: None, or uint8 colours with the shape of ``points``.

    Returns:
        An H x W (organised) or 1 x N cloud in depth_image_proc's layout (see
        the module docstring).

    Raises:
        PointCloudError: a shape other than (N, 3) / (H, W, 3), a non-float
            dtype, or an ``rgb`` whose shape or dtype does not match.
    """
    xyz, colours = _checked(points, rgb)
    cloud = _packed_points(xyz, colours)
    height, width = cloud.shape
    dtype = cloud.dtype

    msg = PointCloud2()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = height, width
    offsets = {"x": 0, "y": 4, "z": 8} | ({} if rgb is None else {"rgb": RGB_OFFSET})
    msg.fields = [
        PointField(name=name, offset=offset, datatype=PointField.FLOAT32, count=1)
        for name, offset in offsets.items()
    ]
    msg.is_bigendian = False
    msg.point_step = dtype.itemsize
    msg.row_step = width * dtype.itemsize
    msg.data = byte_array("B", cloud.tobytes())
    msg.is_dense = bool(np.isfinite(xyz).all())
    return msg


def _checked(points: np.ndarray, rgb: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """``points`` and ``rgb`` as arrays, checked (see :func:`xyz_to_pointcloud2`)."""
    xyz = np.asarray(points)
    if xyz.ndim not in (2, 3) or xyz.shape[-1] != 3:
        raise PointCloudError(f"points must have shape (N, 3) or (H, W, 3), got {xyz.shape}")
    if not np.issubdtype(xyz.dtype, np.floating):
        raise PointCloudError(f"points must be floating point metres, got dtype {xyz.dtype}")
    if rgb is None:
        return xyz, None
    colours = np.asarray(rgb)
    if colours.shape != xyz.shape or colours.dtype != np.uint8:
        raise PointCloudError(
            f"rgb must be uint8 with the points' shape {xyz.shape}, "
            f"got {colours.dtype} {colours.shape}"
        )
    return xyz, colours


def _packed_points(xyz: np.ndarray, rgb: np.ndarray | None) -> np.ndarray:
    """The (H, W) records of checked points in the module's layout, padding bytes zero.

    Written as float32 / uint32 columns of one zeroed block (one pass per
    column instead of the structured fields' strided assignments).
    """
    height, width = xyz.shape[:2] if xyz.ndim == 3 else (1, xyz.shape[0])
    dtype = XYZ_RECORD if rgb is None else XYZRGB_RECORD
    words = np.zeros((height * width, dtype.itemsize // 4), np.float32)
    words[:, :3] = xyz.reshape(-1, 3)
    if rgb is not None:
        words.view(np.uint32)[:, RGB_OFFSET // 4] = pack_rgb(rgb.reshape(-1, 3))
    return words.view(dtype).reshape(height, width)


def xyz_to_pointcloud2_cdr(
    points: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    rgb: np.ndarray | None = None,
) -> bytes:
    """The CDR bytes of ``xyz_to_pointcloud2(points, stamp_ns, frame_id, rgb)``, built directly.

    Byte for byte what :func:`endo_io.bag.serde.serialize` gives for that
    message (little-endian CDR, padding bytes zero, padded to 4 bytes as DDS
    delivers it; tested), for ``Publisher.publish`` to send as it is: one
    copy of the points instead of the three that building the message
    (``tobytes``, the ``array``) and rclpy's serialisation take. Arguments
    and errors as :func:`xyz_to_pointcloud2`.
    """
    xyz, colours = _checked(points, rgb)
    return records_to_pointcloud2_cdr(_packed_points(xyz, colours), stamp_ns, frame_id,
                                      is_dense=bool(np.isfinite(xyz).all()))


def records_to_pointcloud2_cdr(
    cloud: np.ndarray, stamp_ns: int, frame_id: str, *, is_dense: bool
) -> bytes:
    """The CDR bytes of a PointCloud2 of point records already in this module's layout.

    Args:
        cloud: (H, W) or (N,) array of :data:`XYZ_RECORD` or
            :data:`XYZRGB_RECORD` (padding bytes zero); (N,) is a 1 x N cloud.
            A producer that writes the records itself (the voxel map's
            published cloud) skips :func:`xyz_to_pointcloud2_cdr`'s packing.
        stamp_ns, frame_id: the header.
        is_dense: the message's ``is_dense`` (no NaN point).

    Raises:
        PointCloudError: another dtype or shape.
    """
    if cloud.dtype not in (XYZ_RECORD, XYZRGB_RECORD) or cloud.ndim not in (1, 2):
        raise PointCloudError(f"records must be (N,) or (H, W) of XYZ_RECORD or XYZRGB_RECORD, "
                              f"got {cloud.dtype} {cloud.shape}")
    if cloud.ndim == 1:
        cloud = cloud.reshape(1, -1)
    head = header_cdr(stamp_ns, frame_id)[4:]  # offsets below count from the header's end
    height, width = cloud.shape
    colour = cloud.dtype == XYZRGB_RECORD
    offsets = {"x": 0, "y": 4, "z": 8} | ({"rgb": RGB_OFFSET} if colour else {})
    head += bytes(-len(head) % 4) + struct.pack("<III", height, width, len(offsets))
    for name, offset in offsets.items():
        head += cdr_string(name, len(head))
        head += bytes(-len(head) % 4) + struct.pack("<IB", offset, PointField.FLOAT32)
        head += bytes(-len(head) % 4) + struct.pack("<I", 1)
    head += struct.pack("<B", 0)  # is_bigendian
    head += bytes(-len(head) % 4)
    head += struct.pack("<III", cloud.dtype.itemsize, width * cloud.dtype.itemsize, cloud.nbytes)
    tail = struct.pack("<B", bool(is_dense))
    tail += bytes(-(len(head) + cloud.nbytes + len(tail)) % 4)
    return b"".join((LITTLE_ENDIAN_ENCAPSULATION, head,
                     np.ascontiguousarray(cloud).reshape(-1).view(np.uint8).data, tail))


def _field(msg: PointCloud2, name: str) -> PointField | None:
    for field in msg.fields:
        if field.name == name:
            return field
    return None


def pointcloud2_to_xyz(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray | None]:
    """Return the points and colours of a PointCloud2.

    Returns:
        ``(xyz, rgb)``: xyz float32 metres, (H, W, 3) for an organised cloud
        (``height > 1``) or (N, 3) for ``height == 1``; rgb uint8 of the same
        shape unpacked from an ``rgb``/``rgba`` field, or None when the cloud
        has neither. NaN points are returned as they are.

    Raises:
        PointCloudError: x, y or z missing or not FLOAT32 with count 1, an
            rgb field not 4 bytes wide, a field outside ``point_step``,
            ``row_step < width * point_step``, or a data length other than
            ``row_step * height``.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z"):
        field = _field(msg, name)
        if field is None:
            present = [f.name for f in msg.fields]
            raise PointCloudError(f"PointCloud2 has no {name!r} field (fields: {present})")
        if field.datatype != PointField.FLOAT32 or field.count != 1:
            raise PointCloudError(
                f"PointCloud2 field {name!r} must be FLOAT32 x1, got datatype "
                f"{field.datatype} x{field.count}"
            )
        names.append(name)
        formats.append(order + "f4")
        offsets.append(int(field.offset))
    colour = _field(msg, "rgb") or _field(msg, "rgba")
    if colour is not None:
        if colour.datatype not in (PointField.FLOAT32, PointField.UINT32) or colour.count != 1:
            raise PointCloudError(
                f"PointCloud2 field {colour.name!r} must be FLOAT32 or UINT32 x1, got datatype "
                f"{colour.datatype} x{colour.count}"
            )
        names.append("rgb")
        formats.append(order + "u4")  # the float's bits are the packed colour
        offsets.append(int(colour.offset))
    for name, offset in zip(names, offsets, strict=True):
        if offset + 4 > point_step:
            raise PointCloudError(
                f"PointCloud2 field {name!r} at offset {offset} does not fit in "
                f"point_step {point_step}"
            )
    if row_step < width * point_step:
        raise PointCloudError(
            f"PointCloud2 row_step {row_step} < width {width} x point_step {point_step}"
        )
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if raw.size != row_step * height:
        raise PointCloudError(
            f"PointCloud2 data has {raw.size} bytes, expected row_step {row_step} x "
            f"height {height} = {row_step * height}"
        )
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    rows = raw.reshape(height, row_step)[:, : width * point_step]
    cloud = rows.view(dtype) if height * width else np.zeros((height, width), dtype)
    shape = (height, width) if height > 1 else (height * width,)
    cloud = cloud.reshape(shape)
    xyz = np.empty((*shape, 3), dtype=np.float32)
    for axis, name in enumerate("xyz"):
        xyz[..., axis] = cloud[name]
    rgb = unpack_rgb(cloud["rgb"].astype(np.uint32)) if colour is not None else None
    return xyz, rgb
