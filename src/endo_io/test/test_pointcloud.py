"""Layout, round trips and bad input for endo_io.pointcloud."""

from __future__ import annotations

import struct
from array import array as byte_array

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField

from endo_io.bag.serde import serialize
from endo_io.errors import PointCloudError
from endo_io.pointcloud import pointcloud2_to_xyz, xyz_to_pointcloud2, xyz_to_pointcloud2_cdr
from endo_io.stamp import stamp_to_ns


def random_cloud(shape: tuple[int, ...], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0.0, 0.05, size=(*shape, 3)).astype(np.float32)
    xyz[..., 2] += 0.1
    flat = xyz.reshape(-1, 3)
    flat[3] = np.nan  # invalid pixel: all three NaN, as depth_image_proc writes
    flat[5, 2] = np.nan
    rgb = rng.integers(0, 255, size=(*shape, 3), endpoint=True, dtype=np.uint8)
    return xyz, rgb


def bit_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_layout_matches_depth_image_proc_byte_for_byte():
    xyz = np.array([[0.5, -0.25, 1.0], [np.nan, np.nan, np.nan]], dtype=np.float32)
    rgb = np.array([[255, 128, 1], [0, 0, 0]], dtype=np.uint8)
    msg = xyz_to_pointcloud2(xyz, 5, "endoscope_optical_frame", rgb)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, PointField.FLOAT32, 1),
        ("y", 4, PointField.FLOAT32, 1),
        ("z", 8, PointField.FLOAT32, 1),
        ("rgb", 16, PointField.FLOAT32, 1),
    ]
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 2, 32, 64)
    assert not msg.is_bigendian
    assert not msg.is_dense
    nan = struct.unpack("<f", np.float32(np.nan).tobytes())[0]
    expected = (
        struct.pack("<fff4xBBBB12x", 0.5, -0.25, 1.0, 1, 128, 255, 0)  # B, G, R, 0
        + struct.pack("<fff4xI12x", nan, nan, nan, 0)
    )
    assert bytes(msg.data) == expected
    # the packed colour read as a uint32 is 0x00RRGGBB
    assert struct.unpack_from("<I", bytes(msg.data), 16)[0] == 0x00FF8001

    plain = xyz_to_pointcloud2(xyz[:1], 5, "f")
    assert [(f.name, f.offset) for f in plain.fields] == [("x", 0), ("y", 4), ("z", 8)]
    assert (plain.point_step, plain.row_step, plain.is_dense) == (16, 16, True)
    assert bytes(plain.data) == struct.pack("<fff4x", 0.5, -0.25, 1.0)


@pytest.mark.parametrize("shape", [(40,), (6, 8)])
@pytest.mark.parametrize("with_rgb", [False, True])
def test_round_trip_is_exact_with_nan_points(shape, with_rgb):
    xyz, rgb = random_cloud(shape)
    msg = xyz_to_pointcloud2(xyz, 1_700_000_000_000_000_007, "cam", rgb if with_rgb else None)
    assert stamp_to_ns(msg.header.stamp) == 1_700_000_000_000_000_007
    assert msg.header.frame_id == "cam"
    assert (msg.height, msg.width) == ((1, 40) if len(shape) == 1 else (6, 8))
    assert msg.is_dense is False
    out_xyz, out_rgb = pointcloud2_to_xyz(deserialize_message(serialize_message(msg), PointCloud2))
    assert bit_equal(out_xyz, xyz)  # NaN bits included
    if with_rgb:
        assert bit_equal(out_rgb, rgb)
    else:
        assert out_rgb is None


def test_float64_points_are_cast_and_empty_clouds_work():
    xyz = np.array([[0.1, 0.2, 0.3]])
    out, _ = pointcloud2_to_xyz(xyz_to_pointcloud2(xyz, 0, "f"))
    assert bit_equal(out, xyz.astype(np.float32))
    msg = xyz_to_pointcloud2(np.zeros((0, 3), np.float32), 0, "f")
    assert (msg.height, msg.width, len(msg.data)) == (1, 0, 0)
    out, rgb = pointcloud2_to_xyz(msg)
    assert out.shape == (0, 3)
    assert rgb is None


def hand_built_cloud(xyz: np.ndarray, rgb: np.ndarray, *, bigendian: bool, datatype: int):
    """A 2 x 3 cloud laid out unlike ours: rgb first, z before y, padding, padded rows."""
    order = ">" if bigendian else "<"
    dtype = np.dtype(
        {
            "names": ["rgb", "intensity", "z", "x", "y"],
            "formats": [order + "u4", order + "f4", order + "f4", order + "f4", order + "f4"],
            "offsets": [0, 4, 12, 20, 28],
            "itemsize": 36,
        }
    )
    points = np.zeros(xyz.shape[:2], dtype)
    points["x"], points["y"], points["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    points["rgb"] = (
        (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    )
    points["intensity"] = 7.0
    row_pad = np.full((xyz.shape[0], 5), 0xEE, np.uint8)
    rows = np.hstack([points.view(np.uint8).reshape(xyz.shape[0], -1), row_pad])
    msg = PointCloud2()
    msg.height, msg.width = xyz.shape[:2]
    msg.fields = [
        PointField(name="rgb", offset=0, datatype=datatype, count=1),
        PointField(name="intensity", offset=4, datatype=PointField.FLOAT32, count=1),
        PointField(name="z", offset=12, datatype=PointField.FLOAT32, count=1),
        PointField(name="x", offset=20, datatype=PointField.FLOAT32, count=1),
        PointField(name="y", offset=28, datatype=PointField.FLOAT32, count=1),
    ]
    msg.is_bigendian = bigendian
    msg.point_step = 36
    msg.row_step = 36 * xyz.shape[1] + 5
    msg.data = byte_array("B", rows.tobytes())
    return msg


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("datatype", [PointField.FLOAT32, PointField.UINT32])
def test_reader_accepts_other_field_orders_padding_and_byte_order(bigendian, datatype):
    xyz, rgb = random_cloud((2, 3), seed=4)
    out_xyz, out_rgb = pointcloud2_to_xyz(
        hand_built_cloud(xyz, rgb, bigendian=bigendian, datatype=datatype)
    )
    assert bit_equal(out_xyz, xyz)
    assert bit_equal(out_rgb, rgb)


def make_xyz_message() -> PointCloud2:
    return xyz_to_pointcloud2(np.ones((2, 3, 3), np.float32), 0, "f")


def test_reader_rejects_missing_or_mistyped_fields():
    msg = make_xyz_message()
    msg.fields = [f for f in msg.fields if f.name != "y"]
    with pytest.raises(PointCloudError, match="no 'y' field"):
        pointcloud2_to_xyz(msg)
    msg = make_xyz_message()
    msg.fields[2].datatype = PointField.FLOAT64
    with pytest.raises(PointCloudError, match="'z' must be FLOAT32 x1, got datatype 8"):
        pointcloud2_to_xyz(msg)
    msg = make_xyz_message()
    msg.fields[0].count = 3
    with pytest.raises(PointCloudError, match="'x' must be FLOAT32 x1"):
        pointcloud2_to_xyz(msg)
    msg = make_xyz_message()
    msg.fields.append(PointField(name="rgb", offset=12, datatype=PointField.UINT8, count=1))
    with pytest.raises(PointCloudError, match="'rgb' must be FLOAT32 or UINT32"):
        pointcloud2_to_xyz(msg)


def test_reader_rejects_inconsistent_layout():
    msg = make_xyz_message()
    msg.fields[2].offset = 14
    with pytest.raises(PointCloudError, match="offset 14 does not fit in point_step 16"):
        pointcloud2_to_xyz(msg)
    msg = make_xyz_message()
    msg.row_step = 40
    with pytest.raises(PointCloudError, match="row_step 40 < width 3 x point_step 16"):
        pointcloud2_to_xyz(msg)
    msg = make_xyz_message()
    msg.data = msg.data[:-16]
    with pytest.raises(PointCloudError, match=r"80 bytes, expected row_step 48 x height 2 = 96"):
        pointcloud2_to_xyz(msg)


@pytest.mark.parametrize(
    ("points", "rgb", "match"),
    [
        (np.zeros((4, 2), np.float32), None, "shape"),
        (np.zeros((2, 2, 2, 3), np.float32), None, "shape"),
        (np.zeros((4, 3), np.int32), None, "floating"),
        (np.zeros((4, 3), np.float32), np.zeros((4, 3), np.float32), "rgb must be uint8"),
        (np.zeros((4, 3), np.float32), np.zeros((2, 2, 3), np.uint8), "rgb must be uint8"),
    ],
)
def test_writer_rejects_bad_arrays(points, rgb, match):
    with pytest.raises(PointCloudError, match=match):
        xyz_to_pointcloud2(points, 0, "f", rgb)


@pytest.mark.parametrize("frame_id", ["", "w", "world", "endoscope_optical_frame"])
@pytest.mark.parametrize("shape", [(7,), (3, 4), (0,)])
@pytest.mark.parametrize("coloured", [True, False])
def test_cdr_is_the_serialized_message_byte_for_byte(frame_id, shape, coloured):
    xyz, rgb = random_cloud(shape) if shape != (0,) else (np.zeros((0, 3), np.float32),
                                                          np.zeros((0, 3), np.uint8))
    colours = rgb if coloured else None
    stamp_ns = 1_700_000_123_456_789_012
    direct = xyz_to_pointcloud2_cdr(xyz, stamp_ns, frame_id, colours)
    assert direct == serialize(xyz_to_pointcloud2(xyz, stamp_ns, frame_id, colours))
    assert len(direct) % 4 == 0
    back = deserialize_message(direct, PointCloud2)
    assert (back.header.frame_id, stamp_to_ns(back.header.stamp)) == (frame_id, stamp_ns)
    got_xyz, got_rgb = pointcloud2_to_xyz(back)
    assert bit_equal(got_xyz.reshape(-1, 3), xyz.reshape(-1, 3))
    if coloured:
        assert np.array_equal(got_rgb.reshape(-1, 3), rgb.reshape(-1, 3))


def test_cdr_casts_float64_and_checks_like_the_message():
    xyz = np.array([[0.1, 0.2, 0.3]])  # float64: cast as the message casts it
    assert xyz_to_pointcloud2_cdr(xyz, 5, "f") == serialize(xyz_to_pointcloud2(xyz, 5, "f"))
    with pytest.raises(PointCloudError, match="shape"):
        xyz_to_pointcloud2_cdr(np.zeros((4, 2), np.float32), 0, "f")
    with pytest.raises(PointCloudError, match="rgb"):
        xyz_to_pointcloud2_cdr(xyz, 0, "f", np.zeros((1, 3), np.int32))
