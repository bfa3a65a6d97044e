"""Joint fit of the inverse response and the light map from gray-card frames.

Model (per colour channel): the mean raw value of gray level ``k`` at pixel
``x`` is

    v̄_k(x) = f(a_k(x) · M(x)),   a_k(x) = ρ_k · e_k · G_k(x),

with ``f`` the camera response, ``ρ_k`` the card reflectance, ``e_k`` a known
relative exposure (1 by default), ``G_k`` the geometry term of the card pose
(:mod:`endo_calib.geometry`) and ``M(x) = c·L(x)`` the light map up to one
scale. Because the ratios of the ρ_k are known, the values at one pixel
across levels tie ``f`` at irradiances in known ratios, which fixes ``f`` (and
so ``g = f⁻¹``) up to the irradiance scale without an exposure sweep.

The fit alternates two weighted least-squares steps on the per-(pixel, level)
means, until the inverse response stops changing:

1. given M, fit the monotone forward curve ``f`` (:func:`fit_forward_response`);
2. given f, re-estimate each pixel's ``M(x)`` by Gauss–Newton on its levels.

Weights are ``n / σ²(v̄)``, the inverse variance of each mean, from a noise
model fitted to the frame-to-frame variance. A (pixel, level) group is left
out when any of its frames is saturated or clipped at black, since clipping
biases its mean.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import scipy.optimize
import scipy.special
from numpy.typing import NDArray

from endo_calib.errors import (
    FitError,
    ImageSizeMismatchError,
    InsufficientLevelsError,
    SaturatedCardError,
)
from endo_calib.geometry import CardPose, geometry_term
from endo_calib.gray_levels import GrayCardAccumulator, GrayLevel, LevelStatistics
from endo_calib.light_map import LightModel, fit_light_model
from endo_calib.response import (
    LOW_DATA_QUANTILE,
    InverseResponse,
    PiecewiseLinearResponse,
    fit_forward_response,
    fit_shoulder,
)

if TYPE_CHECKING:
    from endo_io.camera import CameraModel

#: Channel names of colour input (RGB order) and of mono input.
RGB_CHANNELS = ("red", "green", "blue")
MONO_CHANNELS = ("mono",)


@dataclass
class ChannelFit:
    """Fit of one colour channel.

    inverse_response: the fitted g. forward: the fitted forward curve (raw value vs
    irradiance, in the fit's irradiance scale). light_map: (H, W) per-pixel L, max
    of the model 1, 0 outside the field of view. light_model: the smooth fit of L.
    light_weight: (H, W) inverse variance of each per-pixel L. irradiance_scale: the
    forward curve's irradiance of level k at x is coefficient_k(x)·L(x)·scale, with
    coefficient_k = ρ_k·e_k·G_k/max G (``FitReport.coefficients``). residual_rms: RMS of
    v̄ − f(a·M) over the used groups in DN. iterations: alternations run.
    """

    inverse_response: InverseResponse
    forward: PiecewiseLinearResponse
    light_map: NDArray[np.float64]
    light_model: LightModel
    light_weight: NDArray[np.float64]
    irradiance_scale: float
    residual_rms: float
    iterations: int
    converged: bool


@dataclass
class FitReport:
    """What the fit saw and how well it fits (for the CLI, the YAML and the report).

    levels: per level (reflectance, exposure, frames, fraction of FOV pixels used).
    channels: per channel name the :class:`ChannelFit`.
    fov_mask: (H, W) bool pixels used. bit_depth, saturation_value: of the raw data.
    geometry: per level (H, W) G_k / max G. level_means: per level (H, W, C) mean raw
    values with censoring undone (NaN where unusable, 0 outside the field of view).
    """

    levels: list[dict[str, float]]
    channels: dict[str, ChannelFit]
    fov_mask: NDArray[np.bool_]
    bit_depth: int
    saturation_value: int
    geometry: list[NDArray[np.float64]] = field(default_factory=list)
    level_means: list[NDArray[np.float64]] = field(default_factory=list)

    def coefficient(self, k: int) -> NDArray[np.float64]:
        """(H, W) ρ_k·e_k·G_k(x)/max G of level k: its irradiance per unit light."""
        level = self.levels[k]
        return level["reflectance"] * level["exposure"] * self.geometry[k]


def _noise_model(
    mean: NDArray[np.float64], var: NDArray[np.float64], top: float
) -> NDArray[np.float64]:
    """Coefficients of the frame-to-frame variance as a quadratic in the mean value.

    mean, var: (N,) per-group mean (DN) and sample variance (DN²) of groups
    without censored samples. Fits var ≈ p2·u² + p1·u + p0, u = v/top, to the
    medians of 64 value bins. Returns (3,) coefficients for ``np.polyval``; a
    constant when too few bins hold data.
    """
    if mean.size == 0:
        return np.array([0.0, 0.0, 1.0])
    bins = np.linspace(0.0, top, 65)
    which = np.clip(np.digitize(mean, bins) - 1, 0, bins.size - 2)
    order = np.argsort(which, kind="stable")
    edges = np.searchsorted(which[order], np.arange(bins.size))
    centres, medians = [], []
    for b in range(bins.size - 1):
        sel = order[edges[b] : edges[b + 1]]
        if sel.size >= 20:
            centres.append(float(np.median(mean[sel])) / top)
            medians.append(float(np.median(var[sel])))
    if len(centres) < 3:
        return np.array([0.0, 0.0, max(float(np.median(var)), 1.0 / 12.0)])
    # The median of a scaled χ² is below its mean by a factor common to all
    # groups; it cancels in the relative weights, so it is left in.
    return np.polyfit(np.asarray(centres), np.asarray(medians), 2)


def _variance(
    coef: NDArray[np.float64], mean: NDArray[np.float64], top: float
) -> NDArray[np.float64]:
    """Noise variance (DN²) at mean values, floored at the quantisation variance 1/12."""
    return np.maximum(np.polyval(coef, mean / top), 1.0 / 12.0)


def _knots(irradiance: NDArray[np.float64], count: int) -> NDArray[np.float64]:
    """Knot grid for the forward curve.

    The union of ``count`` quantiles of the data (dense where the data are, e.g.
    the steep dark end of a gamma curve), ``count`` evenly spaced irradiances up
    to the brightest sample (so that sparse bright data still get short
    segments where the curve bends), and a geometric run from the darkest
    sample (the ``LOW_DATA_QUANTILE`` quantile) to 0. Knots closer than a
    tenth of the even spacing are merged.

    irradiance: (N,) irradiances of the used groups (scale: max ≈ 1).
    Returns (n+1,) strictly increasing float64 knots starting at 0.
    """
    lo = float(np.quantile(irradiance, LOW_DATA_QUANTILE))
    hi = float(np.max(irradiance))
    quantiles = np.quantile(irradiance, np.linspace(0.0, 1.0, count))
    even = np.linspace(lo, hi, count)
    below = lo * np.array([0.125, 0.25, 0.5])
    candidates = np.unique(np.concatenate([[0.0], below, quantiles, even, [lo, hi]]))
    min_gap = 0.1 * (hi - lo) / count
    keep = [0.0]
    for k in candidates[1:]:
        if k - keep[-1] >= min_gap:
            keep.append(float(k))
    keep[-1] = hi
    return np.asarray(keep)


@dataclass
class _Groups:
    """Per-(level, pixel) estimates of one channel: (K, P) arrays."""

    mean: NDArray[np.float64]  # DN
    weight: NDArray[np.float64]  # 1/DN², inverse variance of the mean (0: unused)
    usable: NDArray[np.bool_]
    n_high: NDArray[np.float64]  # saturated samples
    n_total: NDArray[np.float64]  # all samples


def _group_estimates(
    stats: list[LevelStatistics],
    channel: int,
    pixels: NDArray[np.bool_],
    bit_depth: int,
    saturation_value: int,
    black_value: int,
    margin_sigmas: float = 2.5,
) -> _Groups:
    """Means and weights of the (level, pixel) groups of one channel inside ``pixels``.

    A group is usable when none of its samples is saturated or clipped at
    black: a clipped sample biases the mean, and near black the noise of a
    compressive response is far from normal. Weights are n/σ²(mean) with σ²
    from a noise model fitted to the frame-to-frame variance.
    """
    top = float((1 << bit_depth) - 1)

    def take(name: str) -> NDArray[np.float64]:
        return np.stack([getattr(lv, name)[..., channel][pixels] for lv in stats]).astype(
            np.float64
        )

    total, total_sq = take("total"), take("total_sq")
    n_ok, n_high, n_low = take("n_ok"), take("n_high"), take("n_low")
    usable = (n_ok >= 1) & (n_low == 0) & (n_high == 0)
    mean = total / np.maximum(n_ok, 1.0)
    clean = usable & (n_ok >= 2)
    var = (total_sq[clean] - n_ok[clean] * mean[clean] ** 2) / (n_ok[clean] - 1.0)
    coef = _noise_model(mean[clean], np.maximum(var, 0.0), top)
    # Keeping the groups that merely happened not to clip would select low-noise
    # draws next to the limits and bias their means low (high near black); a
    # group whose mean lies within a few noise σ of a limit is left out instead.
    sigma = np.sqrt(_variance(coef, np.clip(mean, 0.0, top), top))
    usable &= mean + margin_sigmas * sigma < saturation_value - 0.5
    usable &= mean - margin_sigmas * sigma > black_value + 0.5
    weight = np.where(usable, n_ok / _variance(coef, np.clip(mean, 0.0, top), top), 0.0)
    return _Groups(mean, weight, usable, n_high, n_ok + n_high + n_low)


def _saturation_onset(
    irradiance: NDArray[np.float64],
    n_high: NDArray[np.float64],
    n_total: NDArray[np.float64],
    data_top: float,
    max_rel_error: float = 0.003,
) -> float | None:
    """Irradiance at which half the samples saturate, from partly saturated groups.

    The unsaturated data stop a little short of saturation, and a compressive
    response changes fastest there, so extrapolating to the top raw value is
    the weakest part of the fit. The groups that saturate in some frames fix
    that point instead: the fraction of saturated samples of a group at
    irradiance E is Φ((E − E*)/s), and E*, where the latent value crosses the
    saturation threshold, is found by maximum likelihood (probit regression).

    irradiance, n_high, n_total: (N,) per group, in the fit's irradiance scale.
    data_top: the highest irradiance of the unsaturated data.
    max_rel_error: the estimate is used only if its standard error (from the
    curvature of the likelihood) is below this fraction of ``data_top``.
    Returns E*, or None when the data do not pin it down or it is not above
    ``data_top``.
    """
    near = (irradiance > 0.8 * data_top) & (n_total > 0)
    e, k, n = irradiance[near], n_high[near], n_total[near]
    straddle = (k > 0) & (k < n)
    if straddle.sum() < 3 or (k == 0).sum() < 3:
        return None
    scale = data_top

    def negative_log_likelihood(params: NDArray[np.float64]) -> float:
        z = (e - params[0] * scale) / (np.exp(params[1]) * scale)
        return -float(np.sum(k * scipy.special.log_ndtr(z) + (n - k) * scipy.special.log_ndtr(-z)))

    start = np.array([float(np.median(e[straddle])) / scale, np.log(0.01)])
    result = scipy.optimize.minimize(
        negative_log_likelihood,
        start,
        method="Nelder-Mead",
        options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 2000},
    )
    if not result.success:
        return None
    # Standard error of E* from a finite-difference Hessian of the likelihood.
    x0, h = result.x, np.array([1e-4, 1e-3])
    hess = np.zeros((2, 2))
    f0 = negative_log_likelihood(x0)
    for i in range(2):
        for j in range(2):
            di, dj = np.eye(2)[i] * h[i], np.eye(2)[j] * h[j]
            hess[i, j] = (
                negative_log_likelihood(x0 + di + dj)
                - negative_log_likelihood(x0 + di - dj)
                - negative_log_likelihood(x0 - di + dj)
                + negative_log_likelihood(x0 - di - dj)
            ) / (4 * h[i] * h[j])
    del f0
    try:
        covariance = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return None
    onset = float(x0[0]) * scale
    if not (covariance[0, 0] > 0.0 and np.sqrt(covariance[0, 0]) < max_rel_error):
        return None
    if not data_top < onset < 1.5 * data_top:
        return None
    return onset


def _fit_channel(
    groups: _Groups,
    coeff: NDArray[np.float64],
    bit_depth: int,
    saturation_value: int,
    *,
    knot_count: int,
    smoothness: float,
    max_iterations: int,
    tolerance: float,
    sample_pixels: int,
) -> tuple[
    InverseResponse,
    PiecewiseLinearResponse,
    NDArray[np.float64],
    NDArray[np.float64],
    float,
    int,
    bool,
]:
    """Alternating fit on (K, P) arrays of one channel; see the module docstring.

    coeff: (K, P) ρ_k·e_k·G_k/max G. Returns (g, f, M (P,), inverse variance of
    M (P,), residual RMS in DN, iterations, converged).
    """
    top = float((1 << bit_depth) - 1)
    means, weight, valid = groups.mean, groups.weight, groups.usable
    pixel_ok = np.sum(weight * coeff * coeff, axis=0) > 0
    # The response has few parameters: alternate on a fixed subset of pixels,
    # then solve every pixel's M once with the final response.
    n_pixels = means.shape[1]
    if n_pixels > sample_pixels:
        subset = np.sort(np.random.default_rng(0).choice(n_pixels, sample_pixels, replace=False))
    else:
        subset = np.arange(n_pixels)
    s_means, s_weight, s_coeff = means[:, subset], weight[:, subset], coeff[:, subset]
    s_valid, s_ok = valid[:, subset], pixel_ok[subset]
    if not s_valid.any():
        raise FitError("no usable gray-card samples")
    # Start from a linear response: M is the weighted LS ratio of value to coefficient.
    num = np.sum(s_weight * s_coeff * s_means / top, axis=0)
    den = np.sum(s_weight * s_coeff * s_coeff, axis=0)
    m = np.divide(num, den, out=np.zeros_like(num), where=s_ok)
    previous: NDArray[np.float64] | None = None
    converged = False
    forward: PiecewiseLinearResponse | None = None
    g: InverseResponse | None = None
    iteration = 0
    for iteration in range(1, max_iterations + 1):  # noqa: B007 - reported below
        # Gauge: irradiance scale with the brightest used groups at about 1
        # (a high percentile, so one stray pixel cannot set the scale).
        e = s_coeff * m[None, :]
        scale = float(np.percentile(e[s_valid], 99.9))
        if not np.isfinite(scale) or scale <= 0.0:
            raise FitError("gray-card data give no positive irradiance")
        m /= scale
        e /= scale
        knots = _knots(e[s_valid], knot_count)
        forward = fit_forward_response(
            e[s_valid], s_means[s_valid], s_weight[s_valid], knots, smoothness, top_code=top
        )
        m = _update_light(forward, s_means, s_weight, s_coeff, m, s_ok, steps=2)
        g = forward.inverse_response(bit_depth)
        if previous is not None and float(np.max(np.abs(g.lut - previous))) < tolerance:
            converged = True
            break
        previous = g.lut.copy()
    assert forward is not None and g is not None
    # Every pixel: start from the inverse response, then Gauss–Newton on the forward curve.
    g_of_mean = g(np.clip(means, 0.0, top)) * float(forward.inverse(top))
    num = np.sum(weight * coeff * g_of_mean, axis=0)
    den = np.sum(weight * coeff * coeff, axis=0)
    m_all = np.divide(num, den, out=np.zeros_like(num), where=pixel_ok)
    m_all = _update_light(forward, means, weight, coeff, m_all, pixel_ok, steps=4)
    e = coeff * m_all[None, :]
    onset = _saturation_onset(
        e.ravel(), groups.n_high.ravel(), groups.n_total.ravel(), float(forward.knots[-1])
    )
    anchor = None
    if onset is not None:
        anchor = (onset, saturation_value - 0.5)
        forward = forward.with_top_knot(*anchor)
    shoulder = fit_shoulder(e[valid], means[valid], top, anchor)
    if shoulder is not None:
        forward = replace(forward, shoulder=shoulder)
    g = forward.inverse_response(bit_depth)
    resid = (means - forward(e))[valid]
    rms = float(np.sqrt(np.mean(resid * resid))) if resid.size else float("nan")
    jac = forward.slope(e) * coeff
    m_weight = np.sum(weight * jac * jac, axis=0)
    return g, forward, m_all, m_weight, rms, iteration, converged


def _update_light(
    forward: PiecewiseLinearResponse,
    means: NDArray[np.float64],
    weight: NDArray[np.float64],
    coeff: NDArray[np.float64],
    m: NDArray[np.float64],
    pixel_ok: NDArray[np.bool_],
    steps: int = 3,
) -> NDArray[np.float64]:
    """Damped Gauss–Newton steps on each pixel's M(x) with the response held fixed.

    A pixel whose levels sit where the response is nearly flat (a clipped top)
    has almost no slope to go by; the damping and a bound of a factor 2 per
    step keep such a pixel from jumping far off.
    """
    for _ in range(steps):
        e = coeff * m[None, :]
        resid = means - forward(e)
        jac = forward.slope(e) * coeff
        num = np.sum(weight * jac * resid, axis=0)
        den = np.sum(weight * jac * jac, axis=0)
        damping = 1e-3 * float(np.median(den[pixel_ok])) if pixel_ok.any() else 0.0
        step = np.divide(num, den + damping, out=np.zeros_like(num), where=(den + damping) > 0)
        step = np.clip(step, -0.5 * m, m)
        m = np.where(pixel_ok, np.maximum(m + step, 1e-12), 0.0)
    return m


def _derive_fov(
    usable_levels: NDArray[np.int_], brightest: NDArray[np.float64], darkest: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Field of view from the data.

    usable_levels: (H, W) number of usable levels; brightest, darkest: (H, W) mean
    raw value of the levels with the highest and lowest ρ·e. Inside the field of
    view the card's brightness follows its reflectance; outside, every level
    shows the same dark noise. A pixel is inside when it has ≥ 2 usable levels
    and its brightest-minus-darkest contrast is ≥ 5% of the image's 99th percentile.
    """
    usable = usable_levels >= 2
    contrast = brightest - darkest
    if not usable.any():
        return usable
    reference = float(np.percentile(contrast[usable], 99.0))
    return usable & (contrast >= 0.05 * reference) & (contrast > 0.0)


def fit_gray_card(
    data: Iterable[GrayLevel] | GrayCardAccumulator,
    camera: CameraModel | None = None,
    *,
    geometry: Sequence[NDArray[np.float64]] | None = None,
    bit_depth: int | None = None,
    saturation_value: int | None = None,
    fov_mask: NDArray[np.bool_] | None = None,
    light_model_degree: int = 8,
    min_level_fraction: float = 0.25,
    knot_count: int = 48,
    smoothness: float = 1e-6,
    max_iterations: int = 60,
    tolerance: float = 2e-4,
    sample_pixels: int = 40000,
) -> FitReport:
    """Fit the inverse response and the light map of a camera from gray-card frames.

    data: the gray levels (each with its frames and pose), or an accumulator they
        were streamed into. At least two distinct reflectances are needed.
    camera: the camera model whose ``unit_rays()`` give the geometry term of each
        level's card pose. Alternatively pass ``geometry``.
    geometry: per level (in the accumulator's order) the (H, W) geometry term G_k,
        any common scale; overrides ``camera``.
    bit_depth: raw bit depth (inferred when None: 8 for uint8, else from the maximum).
    saturation_value: raw values ≥ this count as saturated (2^bits − 1 when None).
    fov_mask: (H, W) bool pixels to use; derived from the data when None.
    light_model_degree: total degree of the smooth Legendre light model.
    min_level_fraction: a level with usable (unsaturated, not black) data at fewer
        than this fraction of the field of view raises SaturatedCardError.
    knot_count, smoothness: forward-curve knots and slope-change penalty.
    max_iterations, tolerance: stop when the LUT changes less than ``tolerance``.
    sample_pixels: pixels (a fixed random subset) the response is alternated on;
        every pixel's light value is solved with the final response.

    Returns the :class:`FitReport`: per channel the fitted response and light
    map, and the diagnostics. ``PhotometricCalibration.from_fit(report)`` turns
    it into the calibration that corrects frames and is saved to disk.
    Raises InsufficientLevelsError, SaturatedCardError, ImageSizeMismatchError
    or FitError on bad input.
    """
    if isinstance(data, GrayCardAccumulator):
        acc = data
        if bit_depth is not None and acc.bit_depth != bit_depth:
            raise FitError(f"accumulator has bit depth {acc.bit_depth}, {bit_depth} was asked for")
        if saturation_value is not None and saturation_value != acc.saturation_value:
            raise FitError("give saturation_value to the accumulator, which censors while adding")
    else:
        acc = GrayCardAccumulator(bit_depth, saturation_value)
        for level in data:
            acc.add_level(level)
    levels = list(acc.levels.values())
    if not levels:
        raise InsufficientLevelsError("no gray-card frames were given")
    if len({lv.reflectance * lv.exposure for lv in levels}) < 2:
        raise InsufficientLevelsError(
            f"need at least two gray levels of different reflectance, got {len(levels)} level(s) "
            f"with reflectance {sorted({lv.reflectance for lv in levels})}"
        )
    assert acc.shape is not None
    height, width, n_channels = acc.shape
    bits = acc.bit_depth
    sat_value = acc.saturation_value

    # Geometry per level.
    if geometry is not None:
        g_terms = [np.asarray(gk, dtype=np.float64) for gk in geometry]
        if len(g_terms) != len(levels):
            raise FitError(f"{len(g_terms)} geometry maps for {len(levels)} levels")
    elif camera is not None:
        if (camera.width, camera.height) != (width, height):
            raise ImageSizeMismatchError(
                f"frames are {width}x{height} but the camera model is "
                f"{camera.width}x{camera.height}"
            )
        cache: dict[CardPose, NDArray[np.float64]] = {}
        g_terms = []
        for lv in levels:
            if lv.pose not in cache:
                cache[lv.pose] = geometry_term(camera, lv.pose)
            g_terms.append(cache[lv.pose])
    else:
        raise FitError("fit_gray_card needs a camera model or explicit geometry maps")
    for gk in g_terms:
        if gk.shape != (height, width):
            raise ImageSizeMismatchError(
                f"geometry map {gk.shape[1]}x{gk.shape[0]} does not match the frames "
                f"{width}x{height}"
            )
    g_ref = max(float(np.max(gk)) for gk in g_terms)
    if not np.isfinite(g_ref) or g_ref <= 0.0:
        raise FitError("the card is not in view of any pixel (geometry term is zero)")

    coeff_maps = np.stack(
        [lv.reflectance * lv.exposure * gk / g_ref for lv, gk in zip(levels, g_terms, strict=True)]
    )  # (K, H, W)
    # Per-pixel usability (all channels): no saturated or black-clipped sample.
    n_frames = np.array([lv.count for lv in levels], dtype=np.float64)[:, None, None, None]
    n_high = np.stack([lv.n_high for lv in levels]).astype(np.float64)
    n_low = np.stack([lv.n_low for lv in levels]).astype(np.float64)
    n_ok = np.stack([lv.n_ok for lv in levels]).astype(np.float64)
    usable = (n_ok >= 1) & (n_low == 0) & (n_high == 0) & (coeff_maps > 0.0)[..., None]
    saturated = n_high > 0
    # Means with saturated samples counted at the saturation value and black
    # ones at 0: only for telling the field of view from the dark surround.
    plain_means = (np.stack([lv.total for lv in levels]) + n_high * sat_value) / n_frames

    if fov_mask is None:
        strength = [lv.reflectance * lv.exposure for lv in levels]
        bright, dark = int(np.argmax(strength)), int(np.argmin(strength))
        fov = _derive_fov(
            usable.all(axis=3).sum(axis=0),
            plain_means[bright].mean(axis=-1),
            plain_means[dark].mean(axis=-1),
        )
    else:
        fov = np.asarray(fov_mask, dtype=bool)
        if fov.shape != (height, width):
            raise ImageSizeMismatchError(
                f"FOV mask {fov.shape[1]}x{fov.shape[0]} does not match the frames {width}x{height}"
            )
    if not fov.any():
        raise SaturatedCardError("no pixel has at least two unsaturated, non-black gray levels")

    level_info = []
    for k, lv in enumerate(levels):
        frac = float(usable[k][fov].all(axis=-1).mean())
        sat_frac = float(saturated[k][fov].any(axis=-1).mean())
        level_info.append(
            {
                "reflectance": lv.reflectance,
                "exposure": lv.exposure,
                "frames": lv.count,
                "usable_fraction": frac,
                "saturated_fraction": sat_frac,
            }
        )
        if frac < min_level_fraction:
            cause = "saturated" if sat_frac >= 0.5 * (1.0 - frac) else "black"
            advice = (
                "lower the exposure or move the card back"
                if cause == "saturated"
                else "raise the exposure or move the card closer"
            )
            raise SaturatedCardError(
                f"gray level {lv.reflectance:g}: only {100 * frac:.0f}% of the field of view is "
                f"usable ({100 * sat_frac:.0f}% saturated); the card is {cause}: {advice}"
            )
    del n_high, n_low, n_ok, plain_means

    names = MONO_CHANNELS if n_channels == 1 else RGB_CHANNELS
    coeff = coeff_maps[:, fov]  # (K, P)
    fits: dict[str, ChannelFit] = {}
    level_means = np.zeros((len(levels), height, width, n_channels))
    for c, name in enumerate(names):
        groups = _group_estimates(levels, c, fov, bits, sat_value, acc.black_value)
        level_means[:, fov, c] = np.where(groups.usable, groups.mean, np.nan)
        g, forward, m, m_weight, rms, iters, converged = _fit_channel(
            groups,
            coeff,
            bits,
            sat_value,
            knot_count=knot_count,
            smoothness=smoothness,
            max_iterations=max_iterations,
            tolerance=tolerance,
            sample_pixels=sample_pixels,
        )
        per_pixel = np.zeros((height, width))
        per_pixel[fov] = m
        weight_map = np.zeros((height, width))
        weight_map[fov] = m_weight
        model = fit_light_model(per_pixel, weight_map, light_model_degree)
        peak = float(np.max(model.evaluate(width, height)[fov]))
        if not np.isfinite(peak) or peak <= 0.0:
            raise FitError(f"channel {name}: light model has no positive peak")
        model = LightModel(model.degree, model.coefficients / peak)
        fits[name] = ChannelFit(
            inverse_response=g,
            forward=forward,
            light_map=per_pixel / peak,
            light_model=model,
            light_weight=weight_map * peak * peak,
            irradiance_scale=peak,
            residual_rms=rms,
            iterations=iters,
            converged=converged,
        )
    return FitReport(
        levels=level_info,
        channels=fits,
        fov_mask=fov,
        bit_depth=bits,
        saturation_value=sat_value,
        geometry=[gk / g_ref for gk in g_terms],
        level_means=[level_means[k] for k in range(len(levels))],
    )
