"""Ray casting against analytic geometry: depth to 1e-6 m, first hits, projection."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from endo_io.camera import CameraModel
from endo_io.pose import rigid_transform
from endo_sim.abdomen import AbdomenGeometry, AbdomenScene
from endo_sim.colon import ColonGeometry, ColonScene
from endo_sim.handeye import centred_board
from endo_sim.photometry import Photometry
from endo_sim.planar import PlaneScene
from endo_sim.render import Renderer
from endo_sim.texture import Texture
from endo_sim.trajectory import AbdomenTrajectory, ColonTrajectory

CAMERA = CameraModel.pinhole(160, 120, 80.0, 80.0, 79.5, 59.5)
FLAT = Photometry(noise=False)


def grey_texture(period) -> Texture:
    return Texture(np.full((8, 8, 1), 0.4, np.float32), period)


def test_tilted_plane_depth_matches_pinhole_geometry() -> None:
    camera_pose = rigid_transform([0.1, -0.2, 0.3], [0.01, 0.02, -0.03])
    normal_world = np.array([0.2, 0.1, -1.0]) / np.linalg.norm([0.2, 0.1, -1.0])
    point_world = np.array([0.0, 0.0, 0.02])
    scene = PlaneScene(point_world, normal_world, 0.5)
    depth = Renderer(CAMERA, FLAT).render(scene, camera_pose).depth
    # Plane in the camera frame: n_c·X = h; pinhole X = z·((u−cx)/fx, (v−cy)/fy, 1).
    rotation, origin = camera_pose[:3, :3], camera_pose[:3, 3]
    n_c = rotation.T @ normal_world
    h = float(n_c @ (rotation.T @ (point_world - origin)))
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    z = h / (n_c[0] * (u - 79.5) / 80.0 + n_c[1] * (v - 59.5) / 80.0 + n_c[2])
    valid = z > 0
    np.testing.assert_allclose(depth[valid], z[valid], rtol=0, atol=1e-6)
    assert np.max(np.abs(depth[valid] - z[valid])) < 1e-8


def test_cylinder_depth_matches_closed_form() -> None:
    radius = 0.02
    geometry = ColonGeometry(
        radius_m=radius, taenia_modulation=0.0, fold_height_m=0.0, bend_amplitude_m=0.0
    )
    scene = ColonScene(geometry, grey_texture((0.2, 2 * math.pi * radius)), seed=3)
    camera_pose = rigid_transform([0.25, 0.4, 0.1], [0.004, -0.006, 0.05])
    renderer = Renderer(CAMERA, FLAT)
    frame = renderer.render(scene, camera_pose)
    rays = renderer.rays @ camera_pose[:3, :3].T
    o = camera_pose[:3, 3]
    # |o_xy + t d_xy| = R  ->  a t² + 2 b t + c = 0, the positive root.
    a = rays[..., 0] ** 2 + rays[..., 1] ** 2
    b = o[0] * rays[..., 0] + o[1] * rays[..., 1]
    c = o[0] ** 2 + o[1] ** 2 - radius**2
    t = (-b + np.sqrt(b * b - a * c)) / a
    expected = t * renderer.rays[..., 2]
    got = frame.depth.astype(np.float64)
    finite = np.isfinite(got)
    assert finite.mean() > 0.95
    assert np.max(np.abs(got[finite] - expected[finite])) < 1e-6
    # float32 output aside, the distances themselves are exact to ~1e-9 m.
    hits = scene.trace(camera_pose, renderer.rays, renderer.mask)
    assert np.nanmax(np.abs(hits.distance - t)) < 1e-8


def _skipped_surfaces(
    scene_field, camera_pose, rays, distance, step=5e-5
) -> list[tuple[float, float]]:
    """(hit distance, depth of penetration) for rays that cross the wall before their hit."""
    skipped = []
    o = camera_pose[:3, 3]
    for ray, t in zip(rays, distance, strict=True):
        samples = np.arange(step, t - step, step)
        field = scene_field(o + samples[:, None] * (camera_pose[:3, :3] @ ray))
        if np.any(field <= 0.0):
            skipped.append((float(t), float(-field.min())))
    return skipped


def test_colon_hits_are_on_the_wall_and_first() -> None:
    geometry = ColonGeometry()
    scene = ColonScene(geometry, grey_texture((0.2, 2 * math.pi * geometry.radius_m)), seed=7)
    trajectory = ColonTrajectory(scene, seed=7, duration_ns=10**10)
    renderer = Renderer(CAMERA, FLAT, fov_radius_px=60.0)
    rng = np.random.default_rng(0)
    for t_ns in (0, 3 * 10**9, 7 * 10**9):
        camera_pose = trajectory.pose_at(t_ns)
        hits = scene.trace(camera_pose, renderer.rays, renderer.mask)
        ok = np.isfinite(hits.distance)
        assert ok[renderer.mask].mean() > 0.97
        rays = renderer.rays[ok]
        points = camera_pose[:3, 3] + (hits.distance[ok][:, None] * rays) @ camera_pose[:3, :3].T
        # On the wall: the radial gap F is zero to far better than 1e-6 m.
        assert np.max(np.abs(scene.field(points))) < 1e-7
        # Normals face the camera.
        assert np.all(np.sum(hits.normal[ok] * rays, axis=-1) < 0.0)
        pick = rng.choice(len(rays), 400, replace=False)
        skipped = _skipped_surfaces(scene.field, camera_pose, rays[pick], hits.distance[ok][pick])
        # A ray may miss only a sliver of a distant fold tip that its grid
        # neighbours (8 px apart) did not see (see colon.py): far away, and a
        # few pixel footprints thin at most.
        assert len(skipped) <= 0.03 * len(pick)
        for distance, penetration in skipped:
            assert distance > 0.08 and penetration < 5 * distance / CAMERA.fx


def test_abdomen_hits_are_on_the_wall_within_working_distance() -> None:
    geometry = AbdomenGeometry()
    scene = AbdomenScene(geometry, grey_texture((0.2, 0.2)), seed=2)
    trajectory = AbdomenTrajectory(geometry.curvature_radius_m, seed=2, duration_ns=20 * 10**9)
    renderer = Renderer(CAMERA, FLAT, fov_radius_px=60.0)
    centre_depths = []
    for t_ns in range(0, 20 * 10**9, 2 * 10**9):
        camera_pose = trajectory.pose_at(t_ns)
        frame = renderer.render(scene, camera_pose)
        hits = scene.trace(camera_pose, renderer.rays, renderer.mask)
        ok = np.isfinite(hits.distance)
        assert np.array_equal(ok, renderer.mask)
        points = (
            camera_pose[:3, 3]
            + (hits.distance[ok][:, None] * renderer.rays[ok]) @ camera_pose[:3, :3].T
        )
        wall = scene.wall_height(points[:, 0], points[:, 1])
        assert np.max(np.abs(wall - points[:, 2])) < 1e-9
        centre_depths.append(float(frame.depth[60, 80]))
    assert min(centre_depths) >= 0.020 and max(centre_depths) <= 0.080


@pytest.mark.parametrize("k1", [0.0, -0.15])
def test_rendered_points_project_back_to_their_pixels(k1: float) -> None:
    camera = CameraModel.pinhole(
        320, 240, 200.0, 200.0, 159.5, 119.5, D=np.array([k1, 0.0, 0.0, 0.0, 0.0])
    )
    camera_pose = rigid_transform([0.2, -0.1, 0.3], [0.001, 0.002, -0.04])
    scene = PlaneScene(np.zeros(3), np.array([0.1, 0.0, -1.0]), 0.5)
    renderer = Renderer(camera, FLAT, fov_radius_px=115.0)
    hits = scene.trace(camera_pose, renderer.rays, renderer.mask)
    v, u = np.nonzero(np.isfinite(hits.distance))
    points = hits.distance[v, u][:, None] * renderer.rays[v, u]
    pixels = camera.project(points)
    error = np.abs(pixels - np.stack([u, v], axis=-1))
    assert np.max(error) < 1e-6


@pytest.mark.parametrize("k1", [0.0, -0.12])
def test_projected_checkerboard_corners_land_where_the_camera_model_says(k1: float) -> None:
    camera = CameraModel.pinhole(
        320, 240, 200.0, 200.0, 159.5, 119.5, D=np.array([k1, 0.0, 0.0, 0.0, 0.0])
    )
    board = centred_board()
    camera_pose = rigid_transform([0.15, -0.1, 0.4], [0.002, -0.001, -0.05])
    image = Renderer(camera, FLAT).render(board, camera_pose).image
    found, corners = cv2.findChessboardCorners(image, board.inner_corners)
    assert found
    corners = cv2.cornerSubPix(
        image,
        corners,
        (5, 5),
        (-1, -1),
        (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4),
    ).reshape(-1, 2)
    world = board.corners_world()
    camera_points = (world - camera_pose[:3, 3]) @ camera_pose[:3, :3]
    expected = camera.project(camera_points)
    # OpenCV may number the corners from either end of the board.
    if np.abs(corners - expected).max() > np.abs(corners[::-1] - expected).max():
        corners = corners[::-1]
    offset = corners - expected
    error = np.linalg.norm(offset, axis=-1)
    # Sub-pixel corner detection on an anti-aliased board: unbiased, ~0.06 px RMS.
    assert np.sqrt(np.mean(error**2)) < 0.1
    assert error.max() < 0.2
    assert np.all(np.abs(offset.mean(axis=0)) < 0.02)
