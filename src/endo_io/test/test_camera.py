"""endo_io.camera: rays, projection, binning/ROI, CameraInfo and YAML round trips."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from sensor_msgs.msg import CameraInfo

from endo_io.camera import CameraModel
from endo_io.errors import CameraModelError
from endo_io.stamp import stamp_to_ns

DATA = Path(__file__).parent / "data"

# Endoscope-like lenses, strong but one-to-one over the whole 320 x 240 image.
MODELS = {
    "plumb_bob": [-0.28, 0.09, 0.0012, -0.0008, -0.01],
    "rational_polynomial": [0.4, -0.05, 0.0007, 0.0011, 0.002, 0.7, 0.01, 0.001],
    "equidistant": [-0.03, 0.012, -0.004, 0.0006],
    "": [],
}


def model(distortion_model: str, width: int = 320, height: int = 240) -> CameraModel:
    s = width / 320
    return CameraModel.pinhole(
        width, height, 230.0 * s, 228.5 * s, 161.3 * s, 118.7 * s,
        D=np.array(MODELS[distortion_model]), distortion_model=distortion_model,
    )


def pixel_grid(width: int, height: int) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([u, v], axis=-1)


@pytest.mark.parametrize("distortion_model", sorted(MODELS))
def test_rays_reproject_onto_the_pixel_grid(distortion_model):
    cam = model(distortion_model)
    rays = cam.unit_rays()
    assert rays.shape == (240, 320, 3)
    assert rays.dtype == np.float64
    assert not np.isnan(rays).any()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-15)
    assert np.all(rays[..., 2] > 0.0)
    depth = np.random.default_rng(0).uniform(0.005, 0.15, size=(240, 320, 1))  # metres
    error = np.abs(cam.project(rays * depth) - pixel_grid(320, 240))
    assert error.max() < 1e-6


@pytest.mark.parametrize("distortion_model", sorted(MODELS))
def test_project_matches_opencv(distortion_model):
    cam = model(distortion_model)
    rng = np.random.default_rng(1)
    points = rng.normal(0.0, 0.03, size=(500, 3))
    points[:, 2] = np.abs(points[:, 2]) + 0.02
    if distortion_model == "equidistant":
        expected, _ = cv2.fisheye.projectPoints(
            points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.D
        )
    else:
        expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, cam.D)
    np.testing.assert_allclose(cam.project(points), expected.reshape(-1, 2), atol=1e-9)
    # (..., 3) shapes are kept; points behind or on the image plane give NaN
    grid_points = points[:6].reshape(2, 3, 3).copy()
    grid_points[1, 2, 2] = -0.1
    grid_points[0, 1, 2] = 0.0
    uv = cam.project(grid_points)
    assert uv.shape == (2, 3, 2)
    assert np.isnan(uv[1, 2]).all()
    assert np.isnan(uv[0, 1]).all()
    assert np.isfinite(uv[0, 0]).all()


def test_pinhole_rays_closed_form():
    cam = CameraModel.pinhole(64, 48, 100.0, 50.0, 20.0, 10.0)
    rays = cam.pixels_to_rays(np.array([[20.0, 10.0], [120.0, 10.0], [20.0, 60.0]]))
    s = 1 / math.sqrt(2)
    np.testing.assert_allclose(rays, [[0, 0, 1], [s, 0, s], [0, s, s]], atol=1e-15)
    np.testing.assert_allclose(cam.unit_rays()[10, 20], [0.0, 0.0, 1.0], atol=1e-15)


def test_equidistant_ray_angle_closed_form():
    # with zero coefficients the fisheye is r = f * theta: 100 px at f = 100 is 1 rad
    cam = CameraModel.pinhole(
        300, 300, 100.0, 100.0, 150.0, 150.0, distortion_model="equidistant"
    )
    ray = cam.pixels_to_rays(np.array([250.0, 150.0]))
    np.testing.assert_allclose(ray, [math.sin(1.0), 0.0, math.cos(1.0)], atol=1e-15)
    # beyond 90 degrees the ray points backwards (pi/2 + 0.2 rad)
    ray = cam.pixels_to_rays(np.array([150.0, 150.0 + 100 * (math.pi / 2 + 0.2)]))
    np.testing.assert_allclose(
        ray, [0.0, math.cos(0.2), -math.sin(0.2)], atol=1e-12
    )


def test_unit_rays_are_cached_and_read_only():
    cam = model("plumb_bob")
    rays = cam.unit_rays()
    assert cam.unit_rays() is rays
    with pytest.raises(ValueError, match="read-only"):
        rays[0, 0, 0] = 1.0


def test_rays_are_nan_exactly_where_the_distortion_has_no_inverse():
    k1, k2, k3 = -0.35, 0.12, -0.02  # barrel: r_d(r) rises to a maximum, then falls
    cam = CameraModel.pinhole(
        320, 240, 160.0, 160.0, 160.0, 120.0, D=np.array([k1, k2, 0.0, 0.0, k3])
    )
    r = np.linspace(0.0, 3.0, 300_001)
    r_d_max = np.max(r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6))
    radius = np.hypot(*(pixel_grid(320, 240) - [160.0, 120.0]).transpose(2, 0, 1)) / 160.0
    invalid = np.isnan(cam.unit_rays()).any(axis=-1)
    assert invalid.any()
    assert not invalid[radius < r_d_max * 0.999].any()
    assert invalid[radius > r_d_max * 1.001].all()


def full_resolution_info(distortion_model: str) -> CameraInfo:
    info = model(distortion_model, 640, 480).to_camera_info()
    info.header.frame_id = "endoscope_optical_frame"
    return info


@pytest.mark.parametrize("distortion_model", ["plumb_bob", "rational_polynomial", "equidistant"])
@pytest.mark.parametrize(
    ("binning", "roi"),
    [((2, 2), (64, 32, 512, 384)), ((4, 2), (0, 0, 0, 0)), ((1, 1), (5, 7, 300, 200))],
)
def test_binned_roi_rays_equal_full_resolution_rays(distortion_model, binning, roi):
    info = full_resolution_info(distortion_model)
    full = CameraModel.from_camera_info(info)
    info.binning_x, info.binning_y = binning
    info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = roi
    binned = CameraModel.from_camera_info(info)
    bx, by = binning
    rx, ry, rw, rh = roi if any(roi) else (0, 0, 640, 480)
    assert (binned.width, binned.height) == (rw // bx, rh // by)
    assert binned.fx == full.fx / bx
    assert binned.cx == (full.cx - rx) / bx
    assert binned.cy == (full.cy - ry) / by
    # published pixel (u, v) is full-resolution pixel (u * bx + rx, v * by + ry)
    rows = slice(ry, ry + binned.height * by, by)
    cols = slice(rx, rx + binned.width * bx, bx)
    rays_full = full.unit_rays()[rows, cols]
    np.testing.assert_allclose(binned.unit_rays(), rays_full, atol=1e-12)


def assert_camera_info_equal(a: CameraInfo, b: CameraInfo) -> None:
    assert stamp_to_ns(a.header.stamp) == stamp_to_ns(b.header.stamp)
    assert a.header.frame_id == b.header.frame_id
    assert (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model)
    assert list(a.d) == list(b.d)
    for name in ("k", "r", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert (a.binning_x, a.binning_y) == (b.binning_x, b.binning_y)
    assert a.roi == b.roi


@pytest.mark.parametrize("distortion_model", ["plumb_bob", "rational_polynomial", "equidistant"])
def test_camera_info_round_trip(distortion_model):
    info = full_resolution_info(distortion_model)
    info.header.stamp.sec, info.header.stamp.nanosec = 1_700_000_000, 123
    info.p[0:4] = [612.25, 0.0, 318.4, -3.5]  # a P that is not [K | 0]
    info.r = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).ravel()
    cam = CameraModel.from_camera_info(info)
    assert_camera_info_equal(cam.to_camera_info(1_700_000_000_000_000_123), info)
    assert CameraModel.from_camera_info(cam.to_camera_info()) == cam

    info.binning_x, info.binning_y = 2, 4
    info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 33, 17, 601, 401
    binned = CameraModel.from_camera_info(info)
    assert (binned.width, binned.height) == (300, 100)
    assert_camera_info_equal(binned.to_camera_info(1_700_000_000_000_000_123), info)
    assert CameraModel.from_camera_info(binned.to_camera_info()) == binned
    assert binned != cam


def test_fixture_written_by_camera_calibration_loads(tmp_path):
    cam = CameraModel.load_yaml(DATA / "camera_calibration_plumb_bob.yaml")
    assert (cam.width, cam.height, cam.camera_name) == (640, 480, "narrow_stereo")
    assert cam.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(
        cam.K, [[683.47125, 0, 322.61844], [0, 681.92893, 241.34017], [0, 0, 1]]
    )
    np.testing.assert_array_equal(cam.D, [-0.382931, 0.151442, 0.000712, -0.001238, 0.0])
    np.testing.assert_array_equal(cam.R, np.eye(3))
    np.testing.assert_array_equal(cam.P[:, 2], [321.99412, 240.88323, 1.0])
    assert cam.frame_id == "endoscope_optical_frame"
    # our writer gives the same keys in the same order, and reads back identically
    cam.save_yaml(tmp_path / "out.yaml")
    assert CameraModel.load_yaml(tmp_path / "out.yaml") == cam
    ours = yaml.safe_load((tmp_path / "out.yaml").read_text())
    theirs = yaml.safe_load((DATA / "camera_calibration_plumb_bob.yaml").read_text())
    assert list(ours) == list(theirs)
    assert ours == theirs

    fisheye = CameraModel.load_yaml(DATA / "camera_calibration_equidistant.yaml", frame_id="f")
    assert (fisheye.width, fisheye.distortion_model, fisheye.frame_id) == (800, "equidistant", "f")
    np.testing.assert_array_equal(fisheye.D, [-0.011294, 0.046876, -0.043237, 0.007884])
    # inside a 380 px circle (~ 85 degrees off axis) every pixel has a ray in front
    inside = fisheye.fov_mask(380.0)
    rays = fisheye.unit_rays()[inside]
    assert np.isfinite(rays).all()
    assert (rays[:, 2] > 0).all()


def test_yaml_round_trip_is_bit_exact(tmp_path):
    K = np.array([[1 / 3 * 1000, 1e-05, 320.1234567890123], [0, 500.5, 1e-300], [0, 0, 1]])
    cam = CameraModel(
        640, 480, K, np.array([1e-05, -2.5e-17, 0.1, 3.0, -1e16]), "plumb_bob",
        camera_name="scope_7",
    )
    cam.save_yaml(tmp_path / "cal.yaml")
    text = (tmp_path / "cal.yaml").read_text()
    assert "1.0e-05" in text  # YAML 1.1 reads a bare 1e-05 as a string
    assert CameraModel.load_yaml(tmp_path / "cal.yaml") == cam


@pytest.mark.parametrize(
    "name", ["narrow_stereo/left", "", "a: b", "123", "yes", "#x", "two\nlines"]
)
def test_yaml_camera_name_survives(tmp_path, name):
    cam = CameraModel(64, 48, np.diag([50.0, 50.0, 1.0]), camera_name=name)
    cam.save_yaml(tmp_path / "cal.yaml")
    assert CameraModel.load_yaml(tmp_path / "cal.yaml").camera_name == name


def test_binned_model_saves_the_full_sensor_calibration(tmp_path):
    info = full_resolution_info("plumb_bob")
    info.binning_x = info.binning_y = 2
    binned = CameraModel.from_camera_info(info)
    binned.save_yaml(tmp_path / "cal.yaml")
    loaded = CameraModel.load_yaml(tmp_path / "cal.yaml")
    assert (loaded.width, loaded.height, loaded.binning_x) == (640, 480, 1)
    np.testing.assert_array_equal(loaded.K, binned.K_full)


def test_resized_keeps_pixel_centres_like_cv2_resize():
    cam = CameraModel.pinhole(640, 480, 400.0, 400.0, 319.5, 239.5)
    half = cam.resized(320, 240)
    # the image centre stays the image centre; focal lengths halve
    assert (half.fx, half.fy, half.cx, half.cy) == (200.0, 200.0, 159.5, 119.5)
    distorted = model("rational_polynomial", 640, 480)
    small = distorted.resized(160, 120)
    uv = pixel_grid(160, 120)
    np.testing.assert_allclose(
        small.unit_rays(), distorted.pixels_to_rays((uv + 0.5) * 4.0 - 0.5), atol=1e-12
    )
    assert small.to_camera_info().width == 160
    with pytest.raises(CameraModelError, match="aspect ratio"):
        cam.resized(320, 200)


def test_fov_mask():
    cam = CameraModel.pinhole(200, 100, 100.0, 100.0, 120.25, 40.75)
    assert cam.fov_mask().all()
    mask = cam.fov_mask(30.0)
    assert mask.shape == (100, 200)
    assert mask[41, 120] and mask[41, 150] and not mask[41, 151]
    assert abs(int(mask.sum()) - math.pi * 30.0**2) < 2 * math.pi * 30.0  # area up to the rim
    with pytest.raises(CameraModelError, match="radius"):
        cam.fov_mask(0.0)


def uncalibrated_info() -> CameraInfo:
    info = CameraInfo()  # what a driver publishes before calibration: K all zero
    info.width, info.height = 640, 480
    return info


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: CameraModel.from_camera_info(uncalibrated_info()), "focal lengths must be"),
        (lambda: CameraModel.pinhole(64, 48, 0.0, 50.0, 32.0, 24.0), "fx=0"),
        (lambda: CameraModel.pinhole(64, 48, 50.0, 50.0, 32.0, 24.0, D=np.zeros(4)),
         "'plumb_bob' needs 5 coefficients, got 4"),
        (lambda: CameraModel.pinhole(64, 48, 50.0, 50.0, 32.0, 24.0, D=np.zeros(5),
                                     distortion_model="rational_polynomial"),
         "'rational_polynomial' needs 8"),
        (lambda: CameraModel.pinhole(64, 48, 50.0, 50.0, 32.0, 24.0, D=np.zeros(5),
                                     distortion_model="equidistant"), "'equidistant' needs 4"),
        (lambda: CameraModel.pinhole(64, 48, 50.0, 50.0, 32.0, 24.0, D=np.ones(2),
                                     distortion_model=""), "'' needs 0"),
        (lambda: CameraModel.pinhole(64, 48, 50.0, 50.0, 32.0, 24.0, distortion_model="kannala"),
         "unsupported distortion model 'kannala'"),
        (lambda: CameraModel(64, 48, np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 2]])),
         "K must be"),
        (lambda: CameraModel(64, 48, np.eye(3) * np.nan), "NaN"),
        (lambda: CameraModel(64, 48, np.diag([50.0, 50.0, 1.0]), binning_x=2, full_width=64),
         "image size 64x48 does not match roi 64x48 binned 2x1 = 32x48"),
        (lambda: CameraModel(64, 48, np.diag([50.0, 50.0, 1.0]), roi=(10, 0, 64, 48),
                             full_width=64), "outside the 64x48 sensor"),
        (lambda: CameraModel(0, 48, np.diag([50.0, 50.0, 1.0])), "0x48"),
    ],
)
def test_bad_models_are_rejected(make, match):
    with pytest.raises(CameraModelError, match=match):
        make()


def test_camera_info_with_mismatched_sizes_is_rejected():
    info = full_resolution_info("plumb_bob")
    info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 400, 0, 300, 480
    with pytest.raises(CameraModelError, match="outside the 640x480 sensor"):
        CameraModel.from_camera_info(info)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda t: t.replace("image_width: 640\n", ""), "missing image_width"),
        (lambda t: t.replace("  cols: 5", "  cols: 4"), "5 values for 1x4"),
        (lambda t: t.replace("plumb_bob", "fisheye"), "unsupported distortion model 'fisheye'"),
        (lambda t: t.replace("683.47125", "0.0"), "fx=0"),
        (lambda t: "[1, 2", "not valid YAML"),
        (lambda t: t.replace("camera_matrix:", "camera_matrix: 3\nunused:"), "camera_matrix needs"),
    ],
)
def test_bad_yaml_is_rejected(tmp_path, edit, match):
    text = (DATA / "camera_calibration_plumb_bob.yaml").read_text()
    path = tmp_path / "bad.yaml"
    path.write_text(edit(text))
    with pytest.raises(CameraModelError, match=match):
        CameraModel.load_yaml(path)
