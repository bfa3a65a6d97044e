"""The light map L(x): the light's spatial distribution times lens vignetting.

Two representations are kept:

* the per-pixel estimate inside the field of view, as fitted, and
* a smooth parametric model, a 2-D Legendre polynomial of total degree ``d`` in
  normalised image coordinates, fitted to the per-pixel estimate. It removes
  the per-pixel noise and evaluates at any resolution of the same sensor.

Normalised coordinates put pixel centres (OpenCV convention: integer pixel
coordinates are centres) at ``x_n = 2·(x + 0.5)/W − 1``, so a ``b×b``-binned or
rescaled image of the same sensor lands on the same ``[-1, 1]²`` square.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.polynomial import legendre
from numpy.typing import NDArray

from endo_calib.errors import CalibrationMismatchError, FitError

#: Longest side of the block-averaged map the polynomial is fitted to.
_FIT_GRID_PX = 160


def normalised_grid(width: int, height: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Normalised coordinates of pixel centres: x (W,) and y (H,) in (-1, 1)."""
    x = 2.0 * (np.arange(width, dtype=np.float64) + 0.5) / width - 1.0
    y = 2.0 * (np.arange(height, dtype=np.float64) + 0.5) / height - 1.0
    return x, y


def _exponents(degree: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


@dataclass(frozen=True, eq=False)
class LightModel:
    """A smooth light map: Σ c_ij·P_i(x_n)·P_j(y_n) over i + j ≤ degree.

    degree: total degree of the Legendre polynomial.
    coefficients: (n_terms,) float64 in the order of ``exponents`` (i outer, j inner).
    """

    degree: int
    coefficients: NDArray[np.float64]

    @property
    def exponents(self) -> list[tuple[int, int]]:
        """(i, j) Legendre orders of x and y for each coefficient."""
        return _exponents(self.degree)

    def evaluate(self, width: int, height: int) -> NDArray[np.float64]:
        """The model on a ``width``×``height`` pixel grid, (H, W) float64 (unmasked)."""
        x, y = normalised_grid(width, height)
        grid = np.zeros((self.degree + 1, self.degree + 1))
        for (i, j), c in zip(self.exponents, self.coefficients, strict=True):
            grid[i, j] = c
        # legval2d over an outer grid: rows follow y (second index), columns x.
        return np.asarray(legendre.leggrid2d(x, y, grid).T, dtype=np.float64)


def block_average(
    values: NDArray[np.floating], weights: NDArray[np.floating], block: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Weighted block means of an (H, W) map: ((H/b, W/b) means, (H/b, W/b) weight sums).

    The image is cropped to whole blocks. Blocks without weight have mean 0.
    """
    h, w = values.shape
    hb, wb = h // block, w // block
    v = np.asarray(values[: hb * block, : wb * block], dtype=np.float64)
    wt = np.asarray(weights[: hb * block, : wb * block], dtype=np.float64)
    sums = (v * wt).reshape(hb, block, wb, block).sum(axis=(1, 3))
    wsum = wt.reshape(hb, block, wb, block).sum(axis=(1, 3))
    means = np.divide(sums, wsum, out=np.zeros_like(sums), where=wsum > 0)
    return means, wsum


def fit_light_model(
    light: NDArray[np.floating], weight: NDArray[np.floating], degree: int = 8
) -> LightModel:
    """Weighted least-squares 2-D Legendre fit of a per-pixel light map.

    light: (H, W) per-pixel estimate (any scale; values where weight is 0 are ignored).
    weight: (H, W) ≥ 0, the inverse variance of each pixel (0 outside the field of view).
    degree: total polynomial degree (0..20).
    Returns the :class:`LightModel`.
    """
    if not 0 <= degree <= 20:
        raise FitError(f"light model degree must be 0..20, got {degree}")
    h, w = light.shape
    block = max(1, int(np.ceil(max(h, w) / _FIT_GRID_PX)))
    means, wsum = block_average(
        np.nan_to_num(light), np.where(np.isfinite(light), weight, 0.0), block
    )
    hb, wb = means.shape
    # Block centres in normalised coordinates of the full image.
    xc = 2.0 * ((np.arange(wb) + 0.5) * block) / w - 1.0
    yc = 2.0 * ((np.arange(hb) + 0.5) * block) / h - 1.0
    yy, xx = np.meshgrid(yc, xc, indexing="ij")
    use = wsum > 0
    terms = _exponents(degree)
    if use.sum() < len(terms):
        raise FitError(
            f"light model of degree {degree} needs {len(terms)} blocks with data, "
            f"got {int(use.sum())}"
        )
    vx = legendre.legvander(xx[use], degree)
    vy = legendre.legvander(yy[use], degree)
    design = np.stack([vx[:, i] * vy[:, j] for i, j in terms], axis=1)
    sw = np.sqrt(wsum[use] / wsum[use].max())
    coefficients, *_ = np.linalg.lstsq(design * sw[:, None], means[use] * sw, rcond=None)
    return LightModel(degree, coefficients)


def resample_map(
    values: NDArray[np.floating], mask: NDArray[np.bool_], width: int, height: int
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Resample a map given at calibration resolution to another resolution of the same sensor.

    Downsampling averages over the covered source area (what pixel binning does
    to the light reaching a binned pixel); upsampling interpolates bilinearly.
    A target pixel is inside the field of view only if its whole footprint is.

    values: (H, W) map, mask: (H, W) bool field of view. width, height: target size.
    Returns ((height, width) float64 map, 0 outside the field of view; (height, width) bool mask).
    Raises CalibrationMismatchError when the aspect ratios differ by more than one pixel.
    """
    h, w = values.shape
    if (width, height) == (w, h):
        return np.where(mask, values, 0.0), mask.copy()
    if abs(width * h / w - height) > 1.0 or abs(height * w / h - width) > 1.0:
        raise CalibrationMismatchError(
            f"image {width}x{height} has another aspect ratio than the calibration {w}x{h}"
        )
    shrink = width < w
    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    filled = np.where(mask, values, 0.0).astype(np.float64)
    resized = cv2.resize(filled, (width, height), interpolation=interpolation)
    coverage = cv2.resize(mask.astype(np.float64), (width, height), interpolation=interpolation)
    inside = coverage >= 1.0 - 1e-6
    return np.where(inside, resized, 0.0), inside
