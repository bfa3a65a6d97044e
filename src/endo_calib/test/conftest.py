"""Synthetic gray-card data with a known response and light map (no simulator needed).

The generator follows the calibration model exactly: E = ρ·L(x)·G(x)·c, noise on
the linear signal (shot + read), then the response, then rounding to integers.
The acceptance tests against endo_sim's renderer are in test_acceptance_sim.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from endo_calib.geometry import CardPose, geometry_term
from endo_calib.gray_levels import GrayLevel
from endo_io.camera import CameraModel

LEVELS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


def gamma_response(e: np.ndarray) -> np.ndarray:
    """A 1/2.2 power law, f(0)=0, f(1)=1."""
    return np.clip(e, 0.0, 1.0) ** (1.0 / 2.2)


def s_response(e: np.ndarray, k: float = 7.0, mid: float = 0.45) -> np.ndarray:
    """A logistic S-curve rescaled to f(0)=0, f(1)=1."""

    def sig(z: np.ndarray | float) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.asarray(z)))

    e = np.clip(e, 0.0, 1.0)
    return (sig(k * (e - mid)) - sig(-k * mid)) / (sig(k * (1 - mid)) - sig(-k * mid))


def true_inverse(response, bits: int) -> np.ndarray:
    """g = f⁻¹ at every raw value of a ``bits``-bit camera."""
    grid = np.linspace(0.0, 1.0, 200001)
    top = (1 << bits) - 1
    return np.interp(np.arange(top + 1) / top, response(grid), grid)


@dataclass
class SyntheticCard:
    camera: CameraModel
    light: np.ndarray  # (H, W) or (H, W, 3) truth, max 1
    fov: np.ndarray
    scale: float
    response: object
    bits: int

    def irradiance(self, rho: float, pose: CardPose | None = None) -> np.ndarray:
        g = geometry_term(self.camera, pose or CardPose())
        light = self.light
        geo = g if light.ndim == 2 else g[..., None]
        fov = self.fov if light.ndim == 2 else self.fov[..., None]
        return rho * light * geo * self.scale * fov

    def frames(
        self,
        rho: float,
        n: int,
        rng: np.random.Generator,
        pose: CardPose | None = None,
        full_well: float = 10000.0,
        read: float = 0.001,
    ) -> list[np.ndarray]:
        e = self.irradiance(rho, pose)
        top = (1 << self.bits) - 1
        dtype = np.uint8 if self.bits == 8 else np.uint16
        out = []
        for _ in range(n):
            noisy = e + rng.normal(size=e.shape) * np.sqrt(e / full_well + read**2)
            out.append(np.clip(np.rint(top * self.response(noisy)), 0, top).astype(dtype))
        return out

    def levels(self, n: int, rng: np.random.Generator, reflectances=LEVELS) -> list[GrayLevel]:
        return [GrayLevel(rho, self.frames(rho, n, rng)) for rho in reflectances]


def make_card(
    response=gamma_response,
    width: int = 160,
    height: int = 120,
    bits: int = 8,
    colour: bool = False,
    peak: float = 0.97,
) -> SyntheticCard:
    camera = CameraModel.pinhole(
        width, height, width / 2, width / 2, (width - 1) / 2, (height - 1) / 2
    )
    rays = camera.unit_rays()
    theta = np.arccos(rays[..., 2])
    light = np.cos(theta) ** 2 * np.exp(-((theta / 0.8) ** 2)) * (1 + 0.08 * rays[..., 0])
    light /= light.max()
    if colour:
        tint = np.stack([light * (1 + 0.05 * rays[..., 1]), light, light**1.2], axis=-1)
        light = tint / tint.max(axis=(0, 1))
    fov = camera.fov_mask(0.58 * height)
    g = geometry_term(camera, CardPose())
    shading = (light if light.ndim == 2 else light.max(axis=-1)) * g
    scale = peak / (max(LEVELS) * shading[fov].max())
    return SyntheticCard(camera, light, fov, scale, response, bits)


class SyntheticKit:
    """What the tests use from this module, as one fixture (conftest is not importable)."""

    LEVELS = LEVELS
    make_card = staticmethod(make_card)
    true_inverse = staticmethod(true_inverse)
    gamma_response = staticmethod(gamma_response)
    s_response = staticmethod(s_response)


@pytest.fixture(scope="session")
def synth() -> type[SyntheticKit]:
    return SyntheticKit


@pytest.fixture(scope="session")
def gamma_card() -> SyntheticCard:
    return make_card(gamma_response)


@pytest.fixture(scope="session")
def gamma_fit(gamma_card):
    """A calibration fitted once on synthetic gamma data (shared by several tests).

    (calibration, levels, fit report).
    """
    from endo_calib import PhotometricCalibration, fit_gray_card

    levels = gamma_card.levels(10, np.random.default_rng(1))
    report = fit_gray_card(levels, gamma_card.camera)
    return PhotometricCalibration.from_fit(report), levels, report
