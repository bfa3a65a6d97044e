"""Viewer-side conversions: cloud packing and decimation, plot JSON of any type, the mailbox."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from geometry_msgs.msg import PointStamped, Vector3Stamped
from std_msgs.msg import Float32, Float64MultiArray

from endo_foxglove.convert import display_pixels, pack_points, point_cloud
from endo_foxglove.mailbox import NewestWins
from endo_foxglove.plot_message import PlotFieldError, json_schema, plot_message
from endo_io.errors import ImageEncodingError, PointCloudError
from endo_io.image import IRRADIANCE_PER_COUNT, array_to_image, encode_irradiance
from endo_io.pointcloud import xyz_to_pointcloud2


def test_pack_points_drops_non_finite_and_decimates_evenly():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(100, 120, 3)).astype(np.float32)
    xyz[::7, :, 1] = np.nan
    xyz[3, 5, 2] = np.inf
    finite = xyz.reshape(-1, 3)[np.isfinite(xyz.reshape(-1, 3)).all(axis=1)]
    data, count, n_finite = pack_points(xyz, None, max_points=1000)
    assert n_finite == len(finite) == 100 * 120 - 15 * 120 - 1
    step = -(-n_finite // 1000)
    assert count == len(finite[::step]) <= 1000
    np.testing.assert_array_equal(np.frombuffer(data, "<f4").reshape(-1, 3), finite[::step])
    # no decimation below the limit
    _, all_points, _ = pack_points(xyz, None, max_points=n_finite)
    assert all_points == n_finite


def test_pack_points_with_colour_gives_rgba_bytes_after_xyz():
    xyz = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [4.0, 5.0, 6.0]], np.float32)
    rgb = np.array([[10, 20, 30], [0, 0, 0], [200, 100, 50]], np.uint8)
    data, count, _ = pack_points(xyz, rgb, max_points=10)
    assert count == 2 and len(data) == 2 * 16
    raw = np.frombuffer(data, np.uint8).reshape(2, 16)
    np.testing.assert_array_equal(raw[:, 12:], [[10, 20, 30, 255], [200, 100, 50, 255]])
    np.testing.assert_array_equal(raw[:, :12].copy().view("<f4"), xyz[[0, 2]])


def test_point_cloud_reports_what_the_viewer_gets():
    xyz = np.zeros((4, 5, 3), np.float32)
    xyz[0, 0] = np.nan
    cloud = point_cloud(xyz_to_pointcloud2(xyz, 5, "world"), max_points=7)
    assert (cloud.total, cloud.finite) == (20, 19)
    assert cloud.published == len(range(0, 19, 3)) == 7
    with pytest.raises(PointCloudError):
        bad = xyz_to_pointcloud2(xyz, 5, "world")
        bad.fields = bad.fields[:2]  # no z
        point_cloud(bad, max_points=7)


@pytest.mark.parametrize(
    ("msg", "field", "expected"),
    [
        (Float32(data=0.25), "", 0.25),
        (Vector3Stamped(), "", 0.0),
        (PointStamped(), "point.y", 0.0),
        (Float64MultiArray(data=[1.5, 0.9]), "", 1.5),
        (Float64MultiArray(data=[1.5, 0.9]), "data[1]", 0.9),
    ],
)
def test_plot_message_has_a_top_level_scale(msg, field, expected):
    data = plot_message(msg, field)
    assert data["scale"] == pytest.approx(expected)
    json.dumps(data)  # JSON-ready
    schema = json_schema(type(msg)(), title="x")
    assert schema["type"] == "object" and "scale" in schema["properties"]


def test_plot_message_picks_x_of_a_vector_and_keeps_stamps_as_sec_nsec():
    msg = Vector3Stamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.vector.x, msg.vector.y = 1.75, 0.5
    data = plot_message(msg)
    assert data["scale"] == 1.75
    assert data["header"]["stamp"] == {"sec": 12, "nsec": 345}


def test_plot_message_nan_is_null_and_a_bad_path_is_named():
    assert plot_message(Float32(data=float("nan")))["scale"] is None
    with pytest.raises(PlotFieldError, match="no 'nope'"):
        plot_message(Float32(data=1.0), "nope")
    with pytest.raises(PlotFieldError, match="out of range"):
        plot_message(Float64MultiArray(data=[1.0]), "data[3]")


def test_newest_wins_keeps_one_item_per_key_and_counts_the_replaced():
    box: NewestWins[int] = NewestWins()
    for i in range(5):
        box.put("image", i)
    box.put("pose", 7)
    assert box.take(0.0) == [("image", 4), ("pose", 7)]
    assert box.superseded == {"image": 4}
    assert box.take(0.0) == []


def test_newest_wins_take_wakes_on_put_and_on_close():
    box: NewestWins[int] = NewestWins()
    got: list[list[tuple[str, int]]] = []
    thread = threading.Thread(target=lambda: got.append(box.take(10.0)))
    thread.start()
    box.put("a", 1)
    thread.join(timeout=5.0)
    assert got == [[("a", 1)]]
    box.close()
    assert box.take(10.0) == [] and box.closed


def test_a_corrected_image_is_served_as_float_irradiance_in_either_encoding():
    irradiance = np.random.default_rng(4).uniform(0.0, 1.7, (6, 8)).astype(np.float32)
    irradiance[2, 3] = np.nan
    for encoding in ("16UC1", "32FC1"):
        msg = array_to_image(encode_irradiance(irradiance, encoding).pixels, encoding, 5, "cam")
        shown, shown_as = display_pixels(msg, irradiance=True)
        assert shown_as == "32FC1" and shown.dtype == np.float32 and shown.shape == (6, 8)
        np.testing.assert_allclose(shown, irradiance, atol=0.5 * IRRADIANCE_PER_COUNT + 1e-6)
        assert np.isnan(shown[2, 3])
    # a raw camera's 16UC1 (counts, not irradiance) passes as it is
    counts = np.arange(48, dtype=np.uint16).reshape(6, 8)
    shown, shown_as = display_pixels(array_to_image(counts, "16UC1"))
    assert shown_as == "16UC1" and np.array_equal(shown, counts)
    with pytest.raises(ImageEncodingError):
        display_pixels(array_to_image(counts.astype(np.uint8), "mono8"), irradiance=True)
