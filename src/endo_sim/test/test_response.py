"""Camera response curves: shape, closed-form inverses, code thresholds."""

from __future__ import annotations

import numpy as np
import pytest

from endo_sim.errors import SimulationParameterError
from endo_sim.response import CameraResponse

RESPONSES = [
    CameraResponse.gamma(),
    CameraResponse.gamma(2.2, toe=0.0),
    CameraResponse.s_curve(),
    CameraResponse.s_curve(1.8, 2.5),
]


@pytest.mark.parametrize("response", RESPONSES, ids=lambda r: f"{r.kind}-{r.exponent:.2f}")
def test_monotone_endpoints_and_inverse(response: CameraResponse) -> None:
    e = np.linspace(0.0, 1.0, 100001)
    v = response(e)
    assert v[0] == 0.0
    assert v[-1] == pytest.approx(1.0, abs=1e-15)
    assert np.all(np.diff(v) > 0.0)
    # The S-curve's shoulder is flat (f' -> 0 at E = 1): 1e-8 there is rounding.
    np.testing.assert_allclose(response.inverse(v), e, rtol=1e-9, atol=1e-8)


def test_bt709_coefficients() -> None:
    a, slope, b = CameraResponse.gamma()._toe_coefficients()
    assert a == pytest.approx(0.0993, abs=5e-4)
    assert slope == pytest.approx(4.5, abs=0.02)
    assert b == 0.018
    # Continuous at the break point.
    r = CameraResponse.gamma()
    assert r(np.array([b - 1e-12]))[0] == pytest.approx(r(np.array([b + 1e-12]))[0], abs=1e-9)


def test_s_curve_is_s_shaped() -> None:
    r = CameraResponse.s_curve(exponent=1.0, contrast=2.0)
    e = np.linspace(0.01, 0.99, 99)
    second = np.diff(r(e), 2)
    # Convex toe, concave shoulder.
    assert np.all(second[:40] > 0.0)
    assert np.all(second[-40:] < 0.0)


@pytest.mark.parametrize("bits", [8, 12])
def test_thresholds_quantise_by_rounding(bits: int) -> None:
    r = CameraResponse.gamma()
    thresholds = r.code_thresholds(bits)
    levels = (1 << bits) - 1
    assert thresholds.shape == (levels,)
    e = np.random.default_rng(3).uniform(0.0, 1.0, 20000)
    codes = np.searchsorted(thresholds, e, side="right")
    scaled = r(e) * levels
    expected = np.floor(scaled + 0.5)
    # Equal except within rounding of a half-code tie.
    near_tie = np.abs(scaled - np.floor(scaled) - 0.5) < 1e-9
    assert np.all((codes == expected) | near_tie)
    assert np.count_nonzero(near_tie) == 0
    lut = r.inverse_lut(bits)
    assert lut.shape == (levels + 1,) and lut[0] == 0.0 and lut[-1] == pytest.approx(1.0)


def test_rejects_bad_parameters() -> None:
    with pytest.raises(SimulationParameterError):
        CameraResponse(kind="linear")
    with pytest.raises(SimulationParameterError):
        CameraResponse.s_curve(contrast=0.5)
