"""The world cloud: points on a known plane, its normal, and the numpy normals it replaced."""

from __future__ import annotations

import numpy as np

from endo_flow.cloud import binned_camera, surface_normals, world_cloud
from endo_io.camera import CameraModel
from endo_io.pose import rigid_transform


def numpy_surface_normals(points: np.ndarray) -> np.ndarray:
    """The previous numpy implementation, kept as the reference."""
    p = np.asarray(points, np.float32)
    normals = np.full(p.shape, np.nan, np.float32)
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    n = normals[1:-1, 1:-1]
    n[..., 0] = du[..., 1] * dv[..., 2] - du[..., 2] * dv[..., 1]
    n[..., 1] = du[..., 2] * dv[..., 0] - du[..., 0] * dv[..., 2]
    n[..., 2] = du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]
    centre = p[1:-1, 1:-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        facing = (n * centre).sum(axis=-1)
        n /= (np.sqrt((n * n).sum(axis=-1)) * np.where(facing > 0.0, -1.0, 1.0))[..., None]
    return normals


def _camera() -> CameraModel:
    return CameraModel.pinhole(640, 480, 520.0, 515.0, 322.0, 238.5,
                               D=np.array([-0.2, 0.05, 0.001, -0.001, 0.0]))


def test_normals_equal_the_numpy_version_bit_for_bit():
    rng = np.random.default_rng(2)
    points = rng.normal(0.0, 0.02, (37, 53, 3)) + np.array([0.0, 0.0, 0.05])
    points[rng.random((37, 53)) < 0.05] = np.nan
    np.testing.assert_array_equal(surface_normals(points), numpy_surface_normals(points))


def test_a_plane_gives_points_on_it_and_its_normal():
    camera = _camera()
    T = rigid_transform(np.array([0.1, -0.2, 0.3]), np.array([0.01, 0.02, -0.03]))
    # a plane in the camera frame: n·p = d, tilted 30° about x, 40 mm ahead on the axis
    normal = np.array([0.0, np.sin(np.radians(30.0)), -np.cos(np.radians(30.0))])
    d = -0.04 * np.cos(np.radians(30.0))
    rays = camera.unit_rays()
    depth = (d / (rays @ normal) * rays[..., 2]).astype(np.float32)
    depth[:40] = np.nan  # a missing band: no points there, NaN normals next to it
    image = np.full(depth.shape, 0.5, np.float32)
    world, grey, normals = world_cloud(depth, image, binned_camera(camera, 4), T, decimation=4,
                                       min_depth_m=1e-3, max_depth_m=0.3, white=1.0, gamma=1.0)
    assert len(world) == 120 * 160 - 10 * 160
    plane_normal_world = T[:3, :3] @ normal
    centre = T[:3, 3]
    # float32 output: 40 mm points to ~4e-9 m
    np.testing.assert_allclose((world - centre) @ plane_normal_world, d, atol=1e-8)
    finite = np.isfinite(normals).all(axis=1)
    assert finite.sum() > 0.9 * len(world)
    # the plane's normal, facing the camera (n·p = d < 0); float32 central differences
    np.testing.assert_allclose(normals[finite], np.tile(plane_normal_world, (finite.sum(), 1)),
                               atol=3e-5)
    assert (grey == 128).all()
