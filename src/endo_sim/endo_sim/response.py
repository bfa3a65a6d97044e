"""Camera response: the non-linear map from sensor irradiance to pixel value.

Endoscope video is never linear: the camera control unit applies a
transfer curve before the 8-bit output. Photometric methods (shape from
shading, the gray-card calibration) must undo it, so the simulator applies a
known, invertible one. Two families are available:

``gamma``
    The ITU-R BT.709 opto-electronic transfer shape generalised to any
    exponent: linear below a toe break point ``b``, a power law above it,
    joined with a continuous value and slope::

        f(E) = s·E                        for E < b
        f(E) = (1 + a)·E^(1/γ) − a        for E ≥ b,
        a = b^p (1 − p) / (1 − b^p (1 − p)),  p = 1/γ,  s = (1 + a)·p·b^(p − 1).

    γ = 1/0.45, b = 0.018 reproduces BT.709 (a = 0.099, s = 4.5).

``s_curve``
    A film-like S-shaped curve: the gamma curve (no toe) followed by a
    symmetric contrast curve in logit space, with a toe and a shoulder::

        x = E^(1/γ),   f(E) = x^c / (x^c + (1 − x)^c).

Both are monotone on [0, 1] with f(0) = 0 and f(1) = 1 and have closed-form
inverses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from endo_sim.errors import SimulationParameterError

RESPONSE_KINDS = ("gamma", "s_curve")


@dataclass(frozen=True)
class CameraResponse:
    """A monotone camera response f: irradiance [0, 1] -> value [0, 1].

    kind: "gamma" or "s_curve". exponent: γ (2.2-like; the curve raises E to
    1/γ). toe: linear-segment break point of the gamma kind, in [0, 0.5)
    (0: pure power law). contrast: c ≥ 1 of the s_curve kind (1: no S shape).
    Build one with :meth:`gamma` or :meth:`s_curve`.
    """

    kind: str = "gamma"
    exponent: float = 1.0 / 0.45
    toe: float = 0.018
    contrast: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in RESPONSE_KINDS:
            raise SimulationParameterError(
                f"response kind must be one of {RESPONSE_KINDS}, got {self.kind!r}"
            )
        if not 0.2 <= self.exponent <= 5.0:
            raise SimulationParameterError(
                f"response exponent must be in [0.2, 5], got {self.exponent}"
            )
        if not 0.0 <= self.toe < 0.5:
            raise SimulationParameterError(f"response toe must be in [0, 0.5), got {self.toe}")
        if not 1.0 <= self.contrast <= 5.0:
            raise SimulationParameterError(
                f"response contrast must be in [1, 5], got {self.contrast}"
            )

    @classmethod
    def gamma(cls, exponent: float = 1.0 / 0.45, toe: float = 0.018) -> CameraResponse:
        """BT.709-shaped gamma response: E^(1/exponent) with a linear toe below ``toe``."""
        return cls(kind="gamma", exponent=exponent, toe=toe)

    @classmethod
    def s_curve(cls, exponent: float = 2.2, contrast: float = 1.6) -> CameraResponse:
        """Film-like S-shaped response: E^(1/exponent), then a logit-space contrast c."""
        return cls(kind="s_curve", exponent=exponent, toe=0.0, contrast=contrast)

    def _toe_coefficients(self) -> tuple[float, float, float]:
        """(a, s, b) of the gamma kind: offset, toe slope, break point."""
        p = 1.0 / self.exponent
        b = self.toe
        if b == 0.0:
            return 0.0, math.inf, 0.0
        bp = b**p
        a = bp * (1.0 - p) / (1.0 - bp * (1.0 - p))
        return a, (1.0 + a) * p * b ** (p - 1.0), b

    def __call__(self, irradiance: ArrayLike) -> NDArray[np.float64]:
        """f(E): irradiance (...) in [0, 1] (clipped) -> value (...) float64 in [0, 1]."""
        e = np.clip(np.asarray(irradiance, dtype=np.float64), 0.0, 1.0)
        p = 1.0 / self.exponent
        if self.kind == "gamma":
            a, slope, b = self._toe_coefficients()
            with np.errstate(invalid="ignore"):
                power = (1.0 + a) * np.power(e, p) - a
            return np.where(e < b, slope * e if b > 0.0 else 0.0, power)
        x = np.power(e, p)
        c = self.contrast
        xc = np.power(x, c)
        return xc / (xc + np.power(1.0 - x, c))

    def inverse(self, value: ArrayLike) -> NDArray[np.float64]:
        """g = f⁻¹: value (...) in [0, 1] (clipped) -> irradiance (...) float64 in [0, 1]."""
        v = np.clip(np.asarray(value, dtype=np.float64), 0.0, 1.0)
        if self.kind == "gamma":
            a, slope, b = self._toe_coefficients()
            power = np.power((v + a) / (1.0 + a), self.exponent)
            if b == 0.0:
                return power
            return np.where(v < slope * b, v / slope, power)
        c = self.contrast
        with np.errstate(divide="ignore"):
            ratio = np.power((1.0 - v) / np.maximum(v, 1e-300), 1.0 / c)
        x = np.where(v > 0.0, 1.0 / (1.0 + ratio), 0.0)
        return np.power(x, self.exponent)

    def inverse_lut(self, bit_depth: int) -> NDArray[np.float64]:
        """g(v) for every code v = 0 .. 2^bits − 1, normalised so that g(max) = 1.

        Returns (2^bits,) float64: the linear irradiance of each pixel value.
        """
        levels = (1 << int(bit_depth)) - 1
        return self.inverse(np.arange(levels + 1, dtype=np.float64) / levels)

    def code_thresholds(self, bit_depth: int) -> NDArray[np.float64]:
        """Irradiances at which the quantised output steps up, (2^bits − 1,) float64.

        Code k is output for E in [thr[k−1], thr[k]): it is round(f(E)·max)
        (ties up), computed exactly by comparing E with f⁻¹((k + ½)/max).
        """
        levels = (1 << int(bit_depth)) - 1
        return self.inverse((np.arange(levels, dtype=np.float64) + 0.5) / levels)

    def parameters(self) -> dict[str, float | str]:
        """The response as plain values (for the ground-truth YAML)."""
        out: dict[str, float | str] = {"kind": self.kind, "gamma": float(self.exponent)}
        if self.kind == "gamma":
            a, slope, b = self._toe_coefficients()
            out.update({"toe": float(b), "offset_a": float(a), "toe_slope": float(slope)})
        else:
            out["contrast"] = float(self.contrast)
        return out
