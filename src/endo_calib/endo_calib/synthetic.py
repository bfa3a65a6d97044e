"""A photometric calibration of a made-up camera, for trying and testing the correction.

What the correction node, its tests and ``bench/bench_calib.py`` use when no
gray-card recording is at hand: a power-law inverse response and a Gaussian
light fall-off inside a circular field of view, per channel, built directly
(no fit). Every number is a keyword, so that each caller states the camera it
needs.

>>> calibration = synthetic_calibration(64, 48, colour=True)
>>> irradiance = calibration.correct(raw_rgb8)
"""

from __future__ import annotations

import numpy as np

from endo_calib.calibration import ChannelCalibration, PhotometricCalibration
from endo_calib.light_map import fit_light_model, normalised_grid
from endo_calib.response import InverseResponse


def synthetic_calibration(
    width: int,
    height: int,
    *,
    bits: int = 8,
    colour: bool = False,
    gamma: float = 2.2,
    gamma_step: float = 0.0,
    falloff_step: float = 0.2,
    fov_radius2: float = 0.9,
    light_model_degree: int | None = None,
    light_source: str = "pixels",
) -> PhotometricCalibration:
    """Build a calibration: ``g(v) = (v / v_max)^γ_c``, ``L(x) = exp(−r²(1 + k·c))``.

    Args:
        width, height: image size, pixels.
        bits: raw bit depth (the inverse response has ``2**bits`` entries).
        colour: three channels (red, green, blue) instead of one (mono).
        gamma: exponent of the first channel's inverse response.
        gamma_step: added to the exponent per channel index c.
        falloff_step: k, the light map's extra fall-off per channel index.
        fov_radius2: the field of view is ``r² < fov_radius2`` in normalised
            coordinates (:func:`~endo_calib.light_map.normalised_grid`); the
            light map is 0 outside.
        light_model_degree: fit a smooth light model of this degree to each
            map (None: no model).
        light_source: ``"pixels"`` or ``"model"`` (then a degree is needed),
            what the correction divides by.

    Returns:
        The :class:`~endo_calib.calibration.PhotometricCalibration`.
    """
    x, y = normalised_grid(width, height)
    xx, yy = np.meshgrid(x, y)
    r2 = xx**2 + yy**2
    fov = r2 < fov_radius2
    names = ("red", "green", "blue") if colour else ("mono",)
    values = np.arange(1 << bits) / ((1 << bits) - 1)
    channels = []
    for c, name in enumerate(names):
        light = np.where(fov, np.exp(-r2 * (1 + falloff_step * c)), 0.0)
        lut = values ** (gamma + gamma_step * c)
        model = (
            None
            if light_model_degree is None
            else fit_light_model(light, fov.astype(float), light_model_degree)
        )
        channels.append(ChannelCalibration(name, InverseResponse(lut, bits), light, model))
    return PhotometricCalibration(channels, fov, None, light_source)
