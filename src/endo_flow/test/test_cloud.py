"""The world cloud: points on a known plane, its normal, and the numpy normals it replaced."""

from __future__ import annotations

import numpy as np

from endo_flow.cloud import (
    BandedCloud,
    binned_camera,
    surface_normals,
    world_cloud,
    world_clouds,
)
from endo_io.camera import CameraModel
from endo_io.pose import rigid_transform, transform_points


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


def test_one_back_projection_gives_the_live_and_the_full_resolution_clouds():
    """world_clouds at (4, 1): the 4th-pixel cloud is world_cloud's at 4, the other every pixel."""
    camera = _camera()
    T = rigid_transform(np.array([0.2, -0.1, 0.05]), np.array([0.02, -0.01, 0.04]))
    v, u = np.mgrid[0:480, 0:640]
    depth = (0.05 + 0.01 * np.sin(u / 50.0) + 0.005 * np.cos(v / 30.0)).astype(np.float32)
    depth[100:140, 200:260] = np.nan
    depth[300:, :100] = 0.5  # beyond the 0.3 m range: not kept
    image = np.random.default_rng(3).random(depth.shape).astype(np.float32)
    kw = {"min_depth_m": 1e-3, "max_depth_m": 0.3, "white": 1.0, "gamma": 1.0}
    live, full = world_clouds(depth, image, camera, T, decimations=(4, 1), **kw)
    alone = world_cloud(depth, image, binned_camera(camera, 4), T, decimation=4, **kw)
    # the same pixels, grey levels and normals (4 px apart) as the live cloud made alone
    np.testing.assert_allclose(live[0], alone[0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(live[1], alone[1])
    np.testing.assert_allclose(live[2], alone[2], rtol=0, atol=1e-6)
    # full resolution: one point per pixel in range
    in_range = np.isfinite(depth) & (depth <= 0.3)
    assert len(full[0]) == in_range.sum() == len(full[1]) == len(full[2])
    assert len(live[0]) == in_range[::4, ::4].sum()
    # the points are transform_points' (the pass does its arithmetic), to float32's rounding
    expected = transform_points(T, camera.depth_to_points(depth)[in_range])
    np.testing.assert_allclose(full[0], expected, rtol=0, atol=1e-7)
    # every point back in the camera has its pixel's depth
    local = (full[0].astype(np.float64) - T[:3, 3]) @ T[:3, :3]
    np.testing.assert_allclose(local[:, 2], depth[in_range], rtol=1e-6)
    # a decimation that does not divide the other: the grid at their gcd, 3 and 2 -> 1
    three, two = world_clouds(depth, image, camera, T, decimations=(3, 2), **kw)
    assert len(three[0]) == in_range[:480:3, :639:3].sum()
    assert len(two[0]) == in_range[::2, ::2].sum()
    np.testing.assert_allclose(
        three[0], world_cloud(depth, image, binned_camera(camera, 3), T, decimation=3, **kw)[0],
        rtol=0, atol=1e-9)


def test_a_cloud_taken_in_bands_is_the_whole_cloud():
    """BandedCloud's bands, end to end: world_cloud's points, grey levels and normals, exactly."""
    camera = _camera()
    T = rigid_transform(np.array([0.2, -0.1, 0.05]), np.array([0.02, -0.01, 0.04]))
    v, u = np.mgrid[0:480, 0:640]
    depth = (0.05 + 0.01 * np.sin(u / 50.0) + 0.005 * np.cos(v / 30.0)).astype(np.float32)
    depth[100:140, 200:260] = np.nan  # normals next to a hole, across band edges
    depth[300:, :100] = 0.5  # beyond the range
    image = np.random.default_rng(4).random(depth.shape).astype(np.float32)
    kw = {"min_depth_m": 1e-3, "max_depth_m": 0.3, "white": 1.0, "gamma": 1.0}
    for decimation, band_rows in ((1, 1), (1, 37), (1, 60), (2, 13), (3, 500)):
        model = binned_camera(camera, decimation)
        whole = world_cloud(depth, image, model, T, decimation=decimation, **kw)
        cloud = BandedCloud(depth, image, model, T, decimation=decimation, **kw)
        bands = []
        while not cloud.done:
            bands.append(cloud.take(band_rows))
        assert len(bands) == -(-model.height // band_rows)
        assert cloud.take(band_rows)[0].shape == (0, 3)  # nothing after the last band
        for part, expected in zip(zip(*bands, strict=True), whole, strict=True):
            np.testing.assert_array_equal(np.concatenate(part), expected)


def test_binned_models_are_shared_by_cameras_of_one_geometry():
    """Two instances of one camera (the warm-up's, the stream's) share the ray table."""
    first, second = _camera(), _camera()
    assert first is not second
    for factor in (1, 4):
        model = binned_camera(first, factor)
        assert binned_camera(second, factor) is model
        rays = model.unit_rays()
        assert binned_camera(second, factor).unit_rays() is rays
        # the rays are the camera's own at those pixels
        np.testing.assert_allclose(rays, first.unit_rays()[::factor, ::factor], atol=1e-12)
    other = CameraModel.pinhole(640, 480, 500.0, 515.0, 322.0, 238.5)
    assert binned_camera(other, 4) is not binned_camera(first, 4)


def test_the_pass_back_projects_as_depth_to_points_bit_for_bit():
    """The points made in the pass are CameraModel.depth_to_points's, to the last bit."""
    camera = CameraModel(width=64, height=48, K=np.array([[50.0, 0, 31.5], [0, 52.0, 23.5],
                                                          [0, 0, 1.0]]),
                         D=np.array([-0.2, 0.05, 0.001, -0.002, 0.0]), distortion_model="plumb_bob")
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.01, 0.08, (48, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.05] = np.nan
    depth[:3, :5] = -0.01  # below the range: not kept, and no neighbour's point
    image = rng.random(depth.shape).astype(np.float32)
    kw = {"min_depth_m": 1e-3, "max_depth_m": 0.3, "white": 1.0, "gamma": 1.0}
    for decimation in (1, 2):
        model = binned_camera(camera, decimation)
        sub = depth[::decimation, ::decimation]
        # identity pose: R @ p + t is p itself, stored as float32
        world, _, normals = world_cloud(depth, image, model, np.eye(4), decimation=decimation,
                                        **kw)
        points = model.depth_to_points(sub)
        kept = (sub >= 1e-3) & (sub <= 0.3) & np.isfinite(points).all(axis=2)
        np.testing.assert_array_equal(world, points[kept].astype(np.float32))
        np.testing.assert_array_equal(normals, surface_normals(points)[kept])
