import numpy as np
import pytest

from endo_calib.geometry import CardPose, CardPoseError, geometry_term
from endo_io.camera import CameraModel


@pytest.fixture(scope="module")
def camera():
    return CameraModel.pinhole(64, 48, 40.0, 40.0, 31.5, 23.5)


def test_fronto_parallel_card_is_cos_cubed_over_distance_squared(camera):
    g = geometry_term(camera, CardPose(distance_m=0.04))
    uz = camera.unit_rays()[..., 2]
    np.testing.assert_allclose(g, uz**3 / 0.04**2, rtol=1e-12)
    # centre pixel looks straight at the card: G = 1/d²
    assert g.max() == pytest.approx(1 / 0.04**2, rel=2e-3)


def test_tilted_card_matches_explicit_ray_plane_intersection(camera):
    normal = np.array([0.3, -0.2, -1.0])
    normal /= np.linalg.norm(normal)
    d = 0.05
    g = geometry_term(camera, CardPose(tuple(normal), d))
    rays = camera.unit_rays()
    # plane n·p = -d (n faces the camera); intersection p = t u
    t = -d / (rays @ normal)
    points = rays * t[..., None]
    r = np.linalg.norm(points, axis=-1)
    to_light = -points / r[..., None]
    cos_theta = to_light @ normal
    np.testing.assert_allclose(g, cos_theta / r**2, rtol=1e-10)


def test_distortion_is_undone_through_unit_rays():
    distorted = CameraModel.pinhole(
        64, 48, 40.0, 40.0, 31.5, 23.5, D=np.array([-0.3, 0.08, 0, 0, 0])
    )
    g = geometry_term(distorted, CardPose(distance_m=1.0))
    np.testing.assert_allclose(g, distorted.unit_rays()[..., 2] ** 3, rtol=1e-12)


@pytest.mark.parametrize(
    "pose",
    [CardPose((0.0, 0.0, 1.0)), CardPose((0.0, 0.0, 0.0)), CardPose(distance_m=0.0)],
)
def test_impossible_card_poses_are_named_errors(camera, pose):
    with pytest.raises(CardPoseError):
        geometry_term(camera, pose)
