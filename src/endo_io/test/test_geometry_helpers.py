"""endo_io.pose's rigid_transform / transform_points / rotation_angle, and depth_to_points."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from endo_io.camera import CameraModel
from endo_io.errors import CameraModelError, PoseError
from endo_io.image import irradiance_to_mono8
from endo_io.pose import check_rotation, rigid_transform, rotation_angle, transform_points


def test_rigid_transform_matches_scipy():
    rng = np.random.default_rng(3)
    for _ in range(20):
        rotvec = rng.normal(size=3) * rng.uniform(0.0, 3.0)
        t = rng.normal(size=3)
        T = rigid_transform(rotvec, t)
        np.testing.assert_allclose(T[:3, :3], Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-14)
        np.testing.assert_array_equal(T[:3, 3], t)
        np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(rigid_transform((0, 0, 0), (1, 2, 3))[:3, :3], np.eye(3))
    with pytest.raises(PoseError):
        rigid_transform((0.0, np.nan, 0.0), (0, 0, 0))
    with pytest.raises(PoseError):
        rigid_transform((0.0, 0.0), (0, 0, 0))


def test_transform_points_any_leading_shape():
    T = rigid_transform((0.0, 0.0, np.pi / 2), (1.0, 0.0, 0.0))
    points = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 3.0]])
    np.testing.assert_allclose(transform_points(T, points), [[1.0, 1.0, 0.0], [-1.0, 0.0, 3.0]],
                               atol=1e-15)
    image = np.broadcast_to(points[0], (4, 5, 3)).copy()
    image[0, 0] = np.nan
    out = transform_points(T, image)
    assert out.shape == (4, 5, 3)
    assert np.all(np.isnan(out[0, 0]))
    np.testing.assert_allclose(out[1, 2], [1.0, 1.0, 0.0], atol=1e-15)
    with pytest.raises(PoseError):
        transform_points(T, np.zeros((3, 2)))


def test_rotation_angle_accurate_near_zero_and_pi():
    for angle in (0.0, 1e-9, 1e-4, 0.5, 3.0, np.pi - 1e-7, np.pi):
        R = Rotation.from_rotvec(angle * np.array([0.6, 0.0, 0.8])).as_matrix()
        assert abs(float(rotation_angle(R)) - angle) < 1e-8 + 1e-9 * angle
    rotvecs = np.random.default_rng(1).normal(size=(50, 3))
    rotvecs /= np.maximum(1.0, np.linalg.norm(rotvecs, axis=1, keepdims=True) / 3.0)
    batch = rotation_angle(Rotation.from_rotvec(rotvecs).as_matrix())
    np.testing.assert_allclose(batch, np.linalg.norm(rotvecs, axis=1), atol=1e-12)


def test_check_rotation_rejects_reflection_and_non_orthonormal():
    check_rotation(np.eye(3))
    with pytest.raises(PoseError, match="reflection"):
        check_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(PoseError, match="orthonormal"):
        check_rotation(np.eye(3) * 1.01)


def test_depth_to_points_inverts_project():
    camera = CameraModel.pinhole(64, 48, fx=50.0, fy=52.0, cx=31.5, cy=23.0)
    depth = np.linspace(0.02, 0.08, 64 * 48).reshape(48, 64)
    depth[5, 7] = np.nan
    depth[6, 8] = 0.0
    points = camera.depth_to_points(depth)
    assert points.shape == (48, 64, 3)
    finite = np.isfinite(depth) & (depth > 0)
    np.testing.assert_allclose(points[..., 2][finite], depth[finite], rtol=1e-12)
    assert np.all(np.isnan(points[~finite]))
    v, u = np.mgrid[0:48, 0:64]
    uv = camera.project(points)
    np.testing.assert_allclose(uv[finite], np.stack([u, v], -1)[finite], atol=1e-9)
    with pytest.raises(CameraModelError):
        camera.depth_to_points(depth.T)


def test_irradiance_to_mono8_fixed_tone_curve():
    irradiance = np.array([[np.nan, -1.0, 0.0, 0.25], [1.0, 4.0, 16.0, np.inf]], np.float32)
    out = irradiance_to_mono8(irradiance, white=4.0, gamma=0.5)
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, [[0, 0, 0, 64], [128, 255, 255, 255]])
    with pytest.raises(ValueError):
        irradiance_to_mono8(irradiance, white=0.0)
