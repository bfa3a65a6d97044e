"""The renderer's photometry against closed forms (planes, noise-free unless stated)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from endo_io.camera import CameraModel
from endo_sfs.reflectance import oren_nayar_coefficients
from endo_sim.photometry import Photometry
from endo_sim.planar import PlaneScene
from endo_sim.render import Renderer
from endo_sim.response import CameraResponse

CAMERA = CameraModel.pinhole(160, 120, 100.0, 100.0, 79.5, 59.5)
DISTANCE = 0.04
RHO = 0.5


def card(normal=(0.0, 0.0, -1.0), albedo=RHO, gloss=0.0, distance=DISTANCE) -> PlaneScene:
    return PlaneScene(
        np.array([0.0, 0.0, distance]), np.array(normal), albedo, specular_weight=gloss
    )


def quiet(**kwargs) -> Photometry:
    kwargs.setdefault("noise", False)
    kwargs.setdefault("roughness", 0.0)
    return Photometry(**kwargs)


@pytest.mark.parametrize("bits", [8, 12])
@pytest.mark.parametrize("response", [CameraResponse.gamma(), CameraResponse.s_curve()])
def test_fronto_parallel_plane_follows_rho_cos_over_r2(bits: int, response: CameraResponse) -> None:
    photometry = quiet(bit_depth=bits, response=response)
    renderer = Renderer(CAMERA, photometry)
    frame = renderer.render(card(), np.eye(4))
    cos = CAMERA.unit_rays()[..., 2]
    # Light map: spot cos^p × vignetting cos^q of the pixel's field angle.
    light = cos ** (photometry.spot_exponent + photometry.vignetting_exponent)
    np.testing.assert_allclose(renderer.light_map, light, rtol=1e-14)
    # ρ·cosθ/r² with r = d/cosθ and incidence angle θ (co-located light).
    expected = photometry.exposure * RHO * light * cos / (DISTANCE / cos) ** 2
    np.testing.assert_allclose(frame.irradiance[..., 0], expected, rtol=1e-12)
    # Through the response: the code is round(f(E)·max) ...
    levels = photometry.max_code
    scaled = response(expected) * levels
    assert np.array_equal(frame.image, np.floor(scaled + 0.5).astype(frame.image.dtype))
    # ... so the irradiance recovered with the inverse response is within half a code.
    code = frame.image.astype(np.float64)
    low = response.inverse((code - 0.5) / levels)
    high = response.inverse((code + 0.5) / levels)
    assert np.all((low <= expected) & (expected <= high))
    recovered = response.inverse_lut(bits)[frame.image]
    half_step = np.maximum(recovered - low, high - recovered)
    assert np.all(np.abs(recovered - expected) <= half_step)
    # Relative error of the recovered irradiance: about half a code's worth.
    worst = float(np.max(np.abs(recovered - expected) / expected))
    assert worst < (0.05 if bits == 8 else 0.004)
    # Depth: along the optical axis, the plane is at z = d everywhere.
    np.testing.assert_allclose(frame.depth, DISTANCE, rtol=1e-7)


def test_oren_nayar_on_a_tilted_plane() -> None:
    sigma = 0.4
    photometry = quiet(roughness=sigma)
    renderer = Renderer(CAMERA, photometry)
    normal = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    scene = card(normal=normal)
    hits = scene.trace(np.eye(4), renderer.rays, renderer.mask)
    irradiance = renderer.irradiance(hits)[..., 0]
    rays = CAMERA.unit_rays()
    t = (DISTANCE * normal[2]) / (rays @ normal)
    c = -(rays @ normal)
    a, b = oren_nayar_coefficients(sigma)
    # Co-located light: θ_i = θ_r, φ_i = φ_r, so Oren–Nayar is A·c + B·(1 − c²).
    expected = photometry.exposure * RHO * renderer.light_map * (a * c + b * (1 - c * c)) / t**2
    np.testing.assert_allclose(irradiance, expected, rtol=1e-7)


def test_offset_light_closed_form() -> None:
    offset = np.array([0.004, -0.002, 0.0])
    photometry = quiet(light_offset_m=tuple(offset), spot_exponent=1.5)
    renderer = Renderer(CAMERA, photometry)
    irradiance = renderer.render(card(), np.eye(4)).irradiance[..., 0]
    rays = CAMERA.unit_rays()
    points = rays * (DISTANCE / rays[..., 2])[..., None]
    from_light = points - offset
    r = np.linalg.norm(from_light, axis=-1)
    cos_incidence = from_light[..., 2] / r  # plane normal (0, 0, -1), light direction −from/r
    spot = (from_light[..., 2] / r) ** 1.5
    vignetting = rays[..., 2] ** photometry.vignetting_exponent
    expected = photometry.exposure * RHO * vignetting * spot * cos_incidence / r**2
    np.testing.assert_allclose(irradiance, expected, rtol=1e-10)


def test_specular_highlight_saturates() -> None:
    photometry = quiet(specular_strength=2.0, specular_shininess=60.0)
    renderer = Renderer(CAMERA, photometry)
    frame = renderer.render(card(gloss=1.0, distance=0.025), np.eye(4))
    rays = CAMERA.unit_rays()
    c = rays[..., 2]
    r = 0.025 / c
    expected = photometry.exposure * renderer.light_map * (RHO * c + 2.0 * c**60) / r**2
    np.testing.assert_allclose(frame.irradiance[..., 0], expected, rtol=1e-8)
    centre = frame.image[55:65, 75:85]
    assert np.all(centre == 255)
    assert expected[60, 80] > 1.5  # well past full scale
    assert frame.image[5, 5] < 255


def test_shot_and_read_noise_statistics() -> None:
    photometry = Photometry(
        roughness=0.0, bit_depth=12, full_well_electrons=5000.0, read_noise_electrons=4.0
    )
    renderer = Renderer(CAMERA, photometry)
    scene = card()
    rng = np.random.default_rng(11)
    frames = np.stack([renderer.render(scene, np.eye(4), rng).image for _ in range(40)])
    clean = renderer.render(scene, np.eye(4), rng).irradiance[..., 0]
    linear = photometry.response.inverse_lut(12)[frames]
    region = (slice(50, 70), slice(70, 90))
    e0 = clean[region]
    residual = linear[:, region[0], region[1]] - e0
    sigma = np.sqrt(e0 * 5000.0 + 16.0) / 5000.0
    z = residual / sigma
    assert abs(float(z.mean())) < 0.03
    assert float(z.std()) == pytest.approx(1.0, abs=0.04)


def test_field_of_view_mask_and_depth_nan() -> None:
    renderer = Renderer(CAMERA, quiet(), fov_radius_px=50.0)
    frame = renderer.render(card(), np.eye(4))
    v, u = np.mgrid[0:120, 0:160]
    outside = (u - 79.5) ** 2 + (v - 59.5) ** 2 > 50.0**2
    assert np.all(frame.image[outside] == 0)
    assert np.all(np.isnan(frame.depth[outside]))
    assert np.all(np.isfinite(frame.depth[~outside]))
    assert frame.depth.dtype == np.float32 and frame.encoding == "mono8"


def test_same_generator_state_same_frame() -> None:
    renderer = Renderer(CAMERA, Photometry())
    a = renderer.render(card(), np.eye(4), np.random.default_rng(5)).image
    b = renderer.render(card(), np.eye(4), np.random.default_rng(5)).image
    c = renderer.render(card(), np.eye(4), np.random.default_rng(6)).image
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert math.isclose(float(a.mean()), float(c.mean()), rel_tol=0.01)
