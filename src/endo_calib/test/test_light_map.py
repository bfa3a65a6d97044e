import numpy as np
import pytest

from endo_calib.errors import CalibrationMismatchError
from endo_calib.light_map import LightModel, fit_light_model, normalised_grid, resample_map


def _smooth_map(width, height):
    x, y = normalised_grid(width, height)
    xx, yy = np.meshgrid(x, y)
    return np.exp(-(xx**2 + 1.3 * yy**2)) * (1 + 0.1 * xx)


def test_light_model_fits_a_smooth_map_through_noise():
    light = _smooth_map(320, 240)
    rng = np.random.default_rng(0)
    noisy = light * (1 + rng.normal(0, 0.02, light.shape))
    weight = np.ones_like(light)
    model = fit_light_model(noisy, weight, degree=8)
    fitted = model.evaluate(320, 240)
    assert np.sqrt(np.mean((fitted / light - 1) ** 2)) < 0.002


def test_light_model_evaluates_consistently_at_binned_resolution():
    model = fit_light_model(_smooth_map(320, 240), np.ones((240, 320)), degree=8)
    full = model.evaluate(320, 240)
    binned = model.evaluate(160, 120)
    block_mean = full.reshape(120, 2, 160, 2).mean(axis=(1, 3))
    # a smooth map: value at the binned pixel centre = mean over its 2x2 block
    np.testing.assert_allclose(binned, block_mean, rtol=2e-4)
    assert isinstance(model, LightModel)


def test_resample_to_binned_resolution_is_area_mean_and_shrinks_the_mask():
    values = _smooth_map(64, 48)
    mask = np.ones((48, 64), bool)
    mask[:, :3] = False
    out, inside = resample_map(values, mask, 32, 24)
    np.testing.assert_allclose(out[:, 2:], values.reshape(24, 2, 32, 2).mean(axis=(1, 3))[:, 2:])
    assert not inside[:, :2].any() and inside[:, 2:].all()  # column 1 straddles the edge
    _, same_mask = resample_map(values, mask, 64, 48)
    np.testing.assert_array_equal(same_mask, mask)


def test_resample_to_another_aspect_ratio_is_refused():
    with pytest.raises(CalibrationMismatchError):
        resample_map(np.ones((48, 64)), np.ones((48, 64), bool), 64, 64)
