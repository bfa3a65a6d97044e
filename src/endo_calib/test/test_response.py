import numpy as np
import pytest

from endo_calib.response import (
    InverseResponse,
    InverseResponseError,
    fit_forward_response,
)


def test_inverse_response_validates_its_table():
    with pytest.raises(InverseResponseError):
        InverseResponse(np.linspace(0, 1, 100), 8)  # wrong length
    bad = np.linspace(0, 1, 256)
    bad[100] = 0.1
    with pytest.raises(InverseResponseError):
        InverseResponse(bad, 8)  # not monotone
    with pytest.raises(InverseResponseError):
        InverseResponse(np.linspace(0.1, 1, 256), 8)  # g(0) != 0
    g = InverseResponse.from_values(np.linspace(3.0, 258.0, 256))
    assert g.lut[0] == 0.0 and g.lut[-1] == 1.0
    assert g.bit_depth == 8


def test_lookup_and_forward_are_inverse_of_each_other():
    lut = (np.arange(4096) / 4095.0) ** 2.2
    g = InverseResponse(lut, 12)
    assert g(np.array([0, 4095, 2048], np.uint16)).tolist() == [0.0, 1.0, lut[2048]]
    e = np.array([0.01, 0.2, 0.7])
    np.testing.assert_allclose(g(g.forward(e)), e, atol=1e-6)


def test_forward_fit_recovers_a_gamma_curve_from_noisy_means():
    rng = np.random.default_rng(3)
    e = rng.uniform(0.005, 1.0, 20000)
    v = 255 * e ** (1 / 2.2) + rng.normal(0, 0.3, e.size)
    knots = np.concatenate([[0.0], np.geomspace(0.002, 1.0, 40)])
    curve = fit_forward_response(e, v, np.ones_like(e), knots)
    grid = np.linspace(0.01, 1.0, 200)
    # piecewise-linear chord error plus noise stays well below one raw value
    assert np.max(np.abs(curve(grid) - 255 * grid ** (1 / 2.2))) < 0.6
    assert np.all(np.diff(curve.values) > 0)
    g = curve.inverse_response(8)
    truth = (np.arange(256) / 255.0) ** 2.2
    assert np.max(np.abs(g.lut - truth)[5:251]) < 0.005


def test_forward_fit_stays_monotone_when_data_say_otherwise():
    e = np.linspace(0.0, 1.0, 500)
    v = 200 * e + 30 * np.sin(12 * e)  # dips downwards in places
    curve = fit_forward_response(e, v, np.ones_like(e), np.linspace(0, 1, 30))
    assert np.all(np.diff(curve.values) > 0)
    assert curve.values[0] == 0.0
