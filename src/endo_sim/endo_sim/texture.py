"""Tissue albedo: a smooth field with low-contrast, vessel-like texture.

Mucosa is not uniform: its reflectance drifts slowly over centimetres
(perfusion, mucus), is mottled at the sub-millimetre scale, and is crossed by
submucosal vessels that absorb in the green and blue (haemoglobin) and much
less in the red. That texture is what optical flow tracks, so the simulator
must have it, at the low contrast real tissue shows (a few to ~20 %).

A :class:`Texture` is a periodic image of albedo over a rectangle of
``period_m`` metres, sampled bilinearly with wrap-around by the scenes'
surface coordinates. :func:`tissue_texture` builds one deterministically from
a seed: band-limited noise is synthesised in the Fourier domain (periodic by
construction) and vessels are random branching, meandering polylines drawn
with anti-aliasing, tiled 3×3 so that they wrap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np
from scipy.signal import lfilter

from endo_sim.bands import run_in_bands
from endo_sim.errors import SimulationParameterError

#: Linear reflectance of colon mucosa per channel (R, G, B) and its grey value
#: as a monochrome sensor with a broad visible response sees it.
MUCOSA_RGB = (0.62, 0.30, 0.22)
MUCOSA_GREY = 0.40
#: Fractional darkening at the centre of a superficial vessel, per channel
#: (haemoglobin absorbs green and blue much more than red), and in grey.
VESSEL_DEPTH_RGB = (0.10, 0.40, 0.30)
VESSEL_DEPTH_GREY = 0.20


@dataclass(frozen=True, eq=False)
class Texture:
    """A periodic albedo image.

    albedo: (Ht, Wt, C) float32 in [0, 1], C = 1 or 3 (R, G, B). Row index
    runs along the first surface coordinate u, column index along v.
    period_m: (Pu, Pv) metres covered by the Ht rows and Wt columns.
    """

    albedo: np.ndarray
    period_m: tuple[float, float]

    def __post_init__(self) -> None:
        if self.albedo.ndim != 3 or self.albedo.shape[2] not in (1, 3):
            raise SimulationParameterError("texture albedo must be (Ht, Wt, 1) or (Ht, Wt, 3)")
        if self.albedo.dtype != np.float32:
            raise SimulationParameterError("texture albedo must be float32")
        if min(self.period_m) <= 0.0:
            raise SimulationParameterError("texture period must be positive")

    @property
    def channels(self) -> int:
        """Number of albedo channels (1 or 3)."""
        return int(self.albedo.shape[2])

    def sample(self, uv: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Albedo at surface coordinates.

        uv: (H, W, 2) float64 metres; valid: (H, W) bool (others get 0).
        Returns (H, W, C) float64.
        """
        out = np.zeros((*valid.shape, self.channels))
        run_in_bands(
            sample_texture,
            valid.shape[0],
            self.albedo,
            float(self.period_m[0]),
            float(self.period_m[1]),
            uv,
            valid,
            out,
        )
        return out


@nb.njit(cache=True, nogil=True)
def sample_texture(
    albedo: np.ndarray,
    period_u: float,
    period_v: float,
    uv: np.ndarray,
    valid: np.ndarray,
    out: np.ndarray,
    row_start: int,
    row_stop: int,
) -> None:
    """Bilinear wrapping lookup of ``albedo`` (Ht, Wt, C) at uv (H, W, 2) metres, into out."""
    rows = albedo.shape[0]
    cols = albedo.shape[1]
    channels = albedo.shape[2]
    scale_u = rows / period_u
    scale_v = cols / period_v
    for i in range(row_start, row_stop):
        for j in range(valid.shape[1]):
            if not valid[i, j]:
                continue
            # Texel centres at (k + 0.5)·texel; wrap in floating point (an
            # integer modulo is a slow division in this per-pixel loop).
            y = uv[i, j, 0] * scale_u - 0.5
            x = uv[i, j, 1] * scale_v - 0.5
            y -= rows * math.floor(y * (1.0 / rows))
            x -= cols * math.floor(x * (1.0 / cols))
            fy = math.floor(y)
            fx = math.floor(x)
            wy = y - fy
            wx = x - fx
            r0 = min(int(fy), rows - 1)
            c0 = min(int(fx), cols - 1)
            r1 = r0 + 1 if r0 + 1 < rows else 0
            c1 = c0 + 1 if c0 + 1 < cols else 0
            for c in range(channels):
                top = albedo[r0, c0, c] * (1.0 - wx) + albedo[r0, c1, c] * wx
                bottom = albedo[r1, c0, c] * (1.0 - wx) + albedo[r1, c1, c] * wx
                out[i, j, c] = top * (1.0 - wy) + bottom * wy


def band_limited_noise(
    rng: np.random.Generator, shape: tuple[int, int], sigma_texels: float
) -> np.ndarray:
    """Periodic Gaussian noise low-passed by a Gaussian of ``sigma_texels``, unit variance.

    Returns (rows, cols) float64; filtering in the Fourier domain keeps it periodic.
    """
    white = rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    gain = np.exp(-2.0 * (math.pi * sigma_texels) ** 2 * (fx * fx + fy * fy))
    field = np.fft.irfft2(np.fft.rfft2(white) * gain, s=shape)
    field -= field.mean()
    std = float(field.std())
    return field / std if std > 0.0 else field


def _vessel_paths(
    rng: np.random.Generator, shape: tuple[int, int], texel_m: float, count: int
) -> list[tuple[np.ndarray, float, float]]:
    """Random branching, meandering vessel centrelines.

    Returns (points (N, 2) float texel coordinates x, y; width in texels;
    strength in [0, 1]) per vessel segment.
    """
    rows, cols = shape
    step = 0.4e-3 / texel_m  # one polyline vertex every 0.4 mm
    paths: list[tuple[np.ndarray, float, float]] = []
    stack = [
        (
            np.array([rng.uniform(0, cols), rng.uniform(0, rows)]),
            rng.uniform(0.0, 2.0 * math.pi),
            rng.uniform(0.35e-3, 0.8e-3) / texel_m,
            rng.uniform(0.5, 1.0),
            0,
        )
        for _ in range(count)
    ]
    while stack:
        start, heading, width, strength, depth = stack.pop()
        length = int(rng.uniform(60, 250) / (1 + depth))
        # Persistent (AR(1)) random turning gives smooth meanders.
        turn = lfilter([1.0], [1.0, -0.9], rng.normal(0.0, 0.02, length))
        headings = heading + np.cumsum(turn)
        steps = step * np.stack([np.cos(headings), np.sin(headings)], axis=-1)
        points = start + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
        if depth < 2:
            for k in np.flatnonzero(rng.random(length) < 0.01):
                side = 1.0 if rng.random() < 0.5 else -1.0
                stack.append(
                    (
                        points[k + 1].copy(),
                        float(headings[k]) + side * rng.uniform(0.4, 1.1),
                        max(width * rng.uniform(0.55, 0.8), 1.0),
                        strength * rng.uniform(0.7, 1.0),
                        depth + 1,
                    )
                )
        paths.append((points, width, strength))
    return paths


def _vessel_map(
    rng: np.random.Generator, shape: tuple[int, int], texel_m: float, density_per_cm2: float
) -> np.ndarray:
    """Periodic vessel absorption map in [0, 1], (rows, cols) float64."""
    rows, cols = shape
    area_cm2 = rows * cols * (texel_m * 100.0) ** 2
    count = max(1, round(density_per_cm2 * area_cm2))
    paths = _vessel_paths(rng, shape, texel_m, count)
    # Superficial vessels are sharp, deep ones wide and blurred: two layers.
    deep_flags = rng.random(len(paths)) < 0.35
    layers = []
    for deep in (False, True):
        # Draw on a 3×3 tiling so that vessels crossing an edge wrap around.
        canvas = np.zeros((3 * rows, 3 * cols), np.uint8)
        thickness_scale = 1.6 if deep else 1.0
        for (points, width, strength), is_deep in zip(paths, deep_flags, strict=True):
            if is_deep != deep:
                continue
            base = np.round((points + np.array([cols, rows])) * 16).astype(np.int32)
            thickness = max(1, round(width * thickness_scale))
            colour = round(255 * strength * (0.6 if deep else 1.0))
            shifted = [
                base + np.array([ox * 16, oy * 16], np.int32)
                for oy in (-rows, 0, rows)
                for ox in (-cols, 0, cols)
            ]
            cv2.polylines(canvas, shifted, False, colour, thickness, lineType=cv2.LINE_AA, shift=4)
        tile = canvas[rows : 2 * rows, cols : 2 * cols].astype(np.float32) / 255.0
        sigma = (0.5e-3 if deep else 0.08e-3) / texel_m
        border = 16 + int(4 * sigma)
        padded = np.pad(tile, border, mode="wrap")
        blurred = cv2.GaussianBlur(padded, (0, 0), sigma)
        layers.append(blurred[border : border + rows, border : border + cols])
    return np.clip(np.maximum(layers[0], layers[1]), 0.0, 1.0).astype(np.float64)


@dataclass(frozen=True)
class TextureOptions:
    """How much the tissue albedo varies (:func:`tissue_texture`).

    drift: amplitude of ln albedo's slow drift (unit noise at 4 mm scale;
    0.08: perfusion and mucus over centimetres). mottle: relative amplitude
    of the fine mottling (unit noise at 0.3 mm; 0.04). vessel_density_per_cm2:
    vessel trees started per cm² (0.3; 0: no vessels). The defaults are the
    mucosa every scene has unless told otherwise; a smaller drift and no
    vessels give a uniform, low-texture tissue (a smooth peritoneum) whose
    shading the shape-from-shading model of one albedo describes.
    """

    drift: float = 0.08
    mottle: float = 0.04
    vessel_density_per_cm2: float = 0.3

    def __post_init__(self) -> None:
        if not (0.0 <= self.drift <= 0.5 and 0.0 <= self.mottle <= 0.5):
            raise SimulationParameterError("texture drift and mottle must be in [0, 0.5]")
        if not 0.0 <= self.vessel_density_per_cm2 <= 10.0:
            raise SimulationParameterError("vessel density must be in [0, 10] per cm²")


def tissue_texture(
    seed: int,
    period_m: tuple[float, float],
    texel_m: float = 0.125e-3,
    channels: int = 1,
    options: TextureOptions | None = None,
) -> Texture:
    """A mucosa-like periodic albedo texture, deterministic from ``seed``.

    period_m: (Pu, Pv) metres; the texel size is adjusted so that an integer
    number of texels spans each period exactly (needed for seamless wrap).
    texel_m: approximate texel size (default 0.125 mm: finer than a pixel's
    footprint at 20 mm for a 320 px focal length). channels: 1 (grey) or 3 (RGB).
    options: the amplitudes (:class:`TextureOptions`; defaults if None).

    Albedo = base · exp(drift·n_low) · (1 + mottle·n_fine) · (1 − depth_c·vessels),
    with n_low unit noise at 4 mm scale and n_fine at 0.3 mm, clipped to [0.02, 0.95].
    The noise fields are drawn whatever the amplitudes, so a seed gives the same
    pattern at every amplitude.
    """
    opts = options or TextureOptions()
    if channels not in (1, 3):
        raise SimulationParameterError(f"texture channels must be 1 or 3, got {channels}")
    rows = max(8, round(period_m[0] / texel_m))
    cols = max(8, round(period_m[1] / texel_m))
    shape = (rows, cols)
    texel = 0.5 * (period_m[0] / rows + period_m[1] / cols)
    rng = np.random.default_rng([int(seed), 0x7E27])
    low = band_limited_noise(rng, shape, 4e-3 / texel)
    fine = band_limited_noise(rng, shape, 0.3e-3 / texel)
    vessels = (_vessel_map(rng, shape, texel, opts.vessel_density_per_cm2)
               if opts.vessel_density_per_cm2 > 0.0 else np.zeros(shape))
    modulation = np.exp(opts.drift * low) * (1.0 + opts.mottle * fine)
    if channels == 1:
        base: tuple[float, ...] = (MUCOSA_GREY,)
        depth: tuple[float, ...] = (VESSEL_DEPTH_GREY,)
    else:
        base, depth = MUCOSA_RGB, VESSEL_DEPTH_RGB
    albedo = np.stack(
        [b * modulation * (1.0 - k * vessels) for b, k in zip(base, depth, strict=True)], axis=-1
    )
    return Texture(
        np.ascontiguousarray(np.clip(albedo, 0.02, 0.95), dtype=np.float32),
        (float(period_m[0]), float(period_m[1])),
    )
