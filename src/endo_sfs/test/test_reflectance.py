"""Reflectance models against closed forms and their per-pixel inversion."""

from __future__ import annotations

import numpy as np
import pytest

from endo_sfs.reflectance import (
    colocated_cosine,
    colocated_radiance,
    lambertian_radiance,
    oren_nayar_coefficients,
    oren_nayar_radiance,
)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_coefficients_match_the_published_formulas():
    assert oren_nayar_coefficients(0.0) == (1.0, 0.0)
    a, b = oren_nayar_coefficients(0.3)
    assert a == pytest.approx(1 - 0.5 * 0.09 / (0.09 + 0.33))
    assert b == pytest.approx(0.45 * 0.09 / (0.09 + 0.09))
    assert (a, b) == pytest.approx((0.892857, 0.225), abs=1e-6)
    with pytest.raises(ValueError, match="roughness"):
        oren_nayar_coefficients(-0.1)


def test_lambertian_is_clamped_cosine():
    n = _unit([[0, 0, -1], [0, 0, -1], [0, 0, -1]])
    light = _unit([[0, 0, -1], [1, 0, -1], [0, 0, 1]])
    np.testing.assert_allclose(lambertian_radiance(n, light), [1.0, np.sqrt(0.5), 0.0])


def test_oren_nayar_with_zero_roughness_is_lambertian():
    rng = np.random.default_rng(1)
    n, light, view = (_unit(rng.normal(size=(500, 3))) for _ in range(3))
    np.testing.assert_allclose(
        oren_nayar_radiance(n, light, view, 0.0), lambertian_radiance(n, light), atol=1e-15
    )


def test_oren_nayar_colocated_reduces_to_seed_paper_equation_1():
    # Light at the viewer: A cos θ + B sin² θ for every tilt and azimuth.
    rng = np.random.default_rng(2)
    n = _unit(rng.normal(size=(1000, 3)))
    view = _unit(rng.normal(size=(1000, 3)))
    a, b = oren_nayar_coefficients(0.3)
    c = np.sum(n * view, axis=-1)
    expected = np.where(c > 0, a * c + b * (1 - c**2), 0.0)
    np.testing.assert_allclose(oren_nayar_radiance(n, view, view, 0.3), expected, atol=1e-12)
    np.testing.assert_allclose(colocated_radiance(c, 0.3), expected, atol=1e-12)


def test_oren_nayar_general_geometry_against_hand_computed_value():
    # n = z; light at θ_i = 60° azimuth 0; viewer at θ_r = 30° azimuth 45°.
    ti, tr, phi = np.radians(60), np.radians(30), np.radians(45)
    n = np.array([0.0, 0.0, 1.0])
    light = np.array([np.sin(ti), 0.0, np.cos(ti)])
    view = np.array([np.sin(tr) * np.cos(phi), np.sin(tr) * np.sin(phi), np.cos(tr)])
    a, b = oren_nayar_coefficients(0.5)
    expected = np.cos(ti) * (a + b * np.cos(phi) * np.sin(ti) * np.tan(tr))
    assert oren_nayar_radiance(n, light, view, 0.5) == pytest.approx(expected, rel=1e-12)
    # Opposite azimuths: the max(0, cos Δφ) term vanishes.
    view_back = np.array([-np.sin(tr), 0.0, np.cos(tr)])
    assert oren_nayar_radiance(n, light, view_back, 0.5) == pytest.approx(a * np.cos(ti))
    # Light behind the surface: no radiance.
    assert oren_nayar_radiance(n, -light, view, 0.5) == 0.0


@pytest.mark.parametrize("sigma", [0.0, 0.1, 0.3, 0.6])
def test_colocated_inversion_recovers_the_cosine(sigma):
    c = np.linspace(0.0, 1.0, 1001)
    recovered = colocated_cosine(colocated_radiance(c, sigma), sigma)
    recovered[0] = colocated_cosine(colocated_radiance(1e-9, sigma), sigma)
    np.testing.assert_allclose(recovered[1:], c[1:], atol=1e-12)


def test_colocated_inversion_clamps_out_of_range_intensities():
    a, b = oren_nayar_coefficients(0.3)
    out = colocated_cosine([b * 0.5, a * 1.2, 5.0, -1.0, np.nan], 0.3)
    np.testing.assert_array_equal(out[:4], [0.0, 1.0, 1.0, 0.0])
    assert np.isnan(out[4])
