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
    fit_tail,
)

if TYPE_CHECKING:
    from endo_io.camera import CameraModel

#: Channel names of colour input (RGB order) and of mono input.
RGB_CHANNELS = ("red", "green", "blue")
MONO_CHANNELS = ("mono",)


#: Alternations each start of the response/light alternation gets before the best goes on.
START_TRIAL_ITERATIONS = 3
#: Where the tail takes over from the free curve: this fraction of its window below its top.
TAIL_JOIN_FRACTION = 0.6
#: Partly saturated samples confirm a tail when it reaches the last code's
#: threshold within this many raw values of their onset.
TAIL_ONSET_TOLERANCE_DN = 0.5
#: The top tail is used when its RMS residual in its window is at most this
#: multiple (+ 0.05 DN) of the free piecewise-linear curve's there.
TAIL_MAX_RMS_RATIO = 1.5


@dataclass(frozen=True)
class ResponseExtent:
    """Which raw values the fitted response saw, and how the rest was found.

    observed_low, observed_high: the lowest and highest raw values covered by
    unsaturated, unclipped data. Above ``observed_high`` (and below
    ``observed_low``) g is extrapolated. top_model: how the top was found (one
    line). saturation_observed: partly saturated samples pinned the top code.
    """

    observed_low: int
    observed_high: int
    top_model: str
    saturation_observed: bool

    def as_dict(self, top_code: int) -> dict[str, object]:
        """The plain mapping saved in photometric.yaml (``response_range``)."""
        return {
            "observed": [self.observed_low, self.observed_high],
            "extrapolated_below": self.observed_low,
            "extrapolated_above": self.observed_high if self.observed_high < top_code else None,
            "top_model": self.top_model,
            "saturation_observed": self.saturation_observed,
        }


@dataclass
class ChannelFit:
    """Fit of one colour channel.

    inverse_response: the fitted g. forward: the fitted forward curve (raw value vs
    irradiance, in the fit's irradiance scale). light_map: (H, W) per-pixel L, max
    of the model 1, 0 outside the field of view. light_model: the smooth fit of L.
    light_weight: (H, W) inverse variance of each per-pixel L. extent: the raw
    values observed and how the rest was extrapolated. irradiance_scale: the
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
    extent: ResponseExtent | None = None


@dataclass(frozen=True)
class _Alternation:
    """State of the response/light alternation on the pixel subset."""

    light: NDArray[np.float64]
    forward: PiecewiseLinearResponse
    inverse: InverseResponse
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
    ResponseExtent,
]:
    """Alternating fit on (K, P) arrays of one channel; see the module docstring.

    coeff: (K, P) ρ_k·e_k·G_k/max G. Returns (g, f, M (P,), inverse variance of
    M (P,), residual RMS in DN, iterations, converged, the observed extent).
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
    # Start from a power law g0(v) = (v/top)^γ0: M is the weighted LS ratio
    # of g0(value) to coefficient. A start far from the truth leaves the light
    # map bent by the response, which the alternation undoes only slowly (a
    # linear start took more than 60 alternations on an S-shaped camera, a
    # 2.2 start as many on a logistic one); so a few starts, γ0 = 1, 2.2 and
    # the one the data suggest (_start_exponent), get START_TRIAL_ITERATIONS
    # alternations each and the one that fits best goes on.
    den = np.sum(s_weight * s_coeff * s_coeff, axis=0)

    def start(exponent: float) -> NDArray[np.float64]:
        num = np.sum(s_weight * s_coeff * (s_means / top) ** exponent, axis=0)
        return np.divide(num, den, out=np.zeros_like(num), where=s_ok)

    def alternate(m: NDArray[np.float64], iterations: int) -> _Alternation:
        previous: NDArray[np.float64] | None = None
        forward: PiecewiseLinearResponse | None = None
        g: InverseResponse | None = None
        for iteration in range(1, iterations + 1):
            # Gauge: irradiance scale with the brightest used groups at about 1
            # (a high percentile, so one stray pixel cannot set the scale).
            e = s_coeff * m[None, :]
            scale = float(np.percentile(e[s_valid], 99.9))
            if not np.isfinite(scale) or scale <= 0.0:
                raise FitError("gray-card data give no positive irradiance")
            m = m / scale
            e /= scale
            knots = _knots(e[s_valid], knot_count)
            forward = fit_forward_response(
                e[s_valid], s_means[s_valid], s_weight[s_valid], knots, smoothness, top_code=top
            )
            m = _update_light(forward, s_means, s_weight, s_coeff, m, s_ok, steps=2)
            g = forward.inverse_response(bit_depth)
            if previous is not None and float(np.max(np.abs(g.lut - previous))) < tolerance:
                return _Alternation(m, forward, g, iteration, True)
            previous = g.lut.copy()
        assert forward is not None and g is not None
        return _Alternation(m, forward, g, iterations, False)

    def misfit(state: _Alternation) -> float:
        resid = (s_means - state.forward(s_coeff * state.light[None, :]))[s_valid]
        return float(np.average(resid * resid, weights=s_weight[s_valid]))

    exponents = sorted({1.0, 2.2, round(_start_exponent(s_means, s_coeff, s_valid, top), 3)})
    trials = [alternate(start(x), START_TRIAL_ITERATIONS) for x in exponents]
    best = min(trials, key=misfit)
    iteration = best.iterations
    if not best.converged:
        more = alternate(best.light, max(1, max_iterations - START_TRIAL_ITERATIONS))
        best = replace(more, iterations=iteration + more.iterations)
    forward, g, iteration, converged = best.forward, best.inverse, best.iterations, best.converged
    assert forward is not None and g is not None
    # Every pixel: start from the inverse response, then Gauss–Newton on the forward curve.
    g_of_mean = g(np.clip(means, 0.0, top)) * float(forward.inverse(top))
    num = np.sum(weight * coeff * g_of_mean, axis=0)
    den = np.sum(weight * coeff * coeff, axis=0)
    m_all = np.divide(num, den, out=np.zeros_like(num), where=pixel_ok)
    m_all = _update_light(forward, means, weight, coeff, m_all, pixel_ok, steps=4)
    e = coeff * m_all[None, :]
    observed_top = float(forward.values[-1])
    onset = _saturation_onset(
        e.ravel(), groups.n_high.ravel(), groups.n_total.ravel(), float(forward.knots[-1])
    )
    # Above the brightest observed code the curve is extrapolated: along a
    # smooth tail when it describes the brightest data as well as the free
    # curve does (and, when partly saturated samples pin where the last code
    # begins, agrees with that onset within TAIL_ONSET_TOLERANCE_DN); else
    # through the onset with a shoulder; else straight on.
    tailed = _with_tail(forward, e[valid], means[valid], weight[valid], top, observed_top)
    if onset is not None:
        threshold = saturation_value - 0.5
        if tailed is not None and abs(_tail_value(tailed, onset) - threshold) <= (
            TAIL_ONSET_TOLERANCE_DN
        ):
            forward = tailed
            assert forward.tail is not None
            top_model = forward.tail.describe() + "; agrees with the saturation onset"
        else:
            anchor = (onset, threshold)
            forward = forward.with_top_knot(*anchor)
            top_model = "saturation onset (probit on partly saturated samples)"
            shoulder = fit_shoulder(e[valid], means[valid], top, anchor)
            if shoulder is not None:
                forward = replace(forward, shoulder=shoulder)
                top_model += f" + shoulder (beta = {shoulder.exponent:.3g})"
    elif tailed is not None:
        forward = tailed
        assert forward.tail is not None
        top_model = forward.tail.describe()
    else:
        top_model = "straight continuation of the top slope"
    g = forward.inverse_response(bit_depth)
    resid = (means - forward(e))[valid]
    rms = float(np.sqrt(np.mean(resid * resid))) if resid.size else float("nan")
    jac = forward.slope(e) * coeff
    m_weight = np.sum(weight * jac * jac, axis=0)
    low_code = float(forward(forward.data_low)) if forward.data_low > 0.0 else 0.0
    extent = ResponseExtent(
        observed_low=int(np.ceil(low_code)),
        observed_high=int(min(np.floor(observed_top), top)),
        top_model=top_model,
        saturation_observed=onset is not None,
    )
    return g, forward, m_all, m_weight, rms, iteration, converged, extent


def _start_exponent(
    means: NDArray[np.float64],
    coeff: NDArray[np.float64],
    valid: NDArray[np.bool_],
    top: float,
) -> float:
    """Exponent γ0 of the power law g0(v) = (v/top)^γ0 that best fits the data.

    With g0, every level of a pixel gives the same light value:
    log c_k = γ0·log v_k − log M. Removing each pixel's mean over its usable
    levels leaves one least-squares slope for all pixels.

    means, coeff, valid: (K, P) mean raw values, ρ·e·G coefficients, usable groups.
    Returns γ0 clipped to [0.8, 4] (2.2 when the data cannot tell).
    """
    use = valid & (means > 0.0) & (coeff > 0.0)
    counts = use.sum(axis=0)
    pixels = counts >= 2
    if not pixels.any():
        return 2.2
    log_v = np.where(use, np.log(np.where(use, means, 1.0) / top), 0.0)[:, pixels]
    log_c = np.where(use, np.log(np.where(use, coeff, 1.0)), 0.0)[:, pixels]
    used = use[:, pixels]
    n = counts[pixels]
    dv = np.where(used, log_v - log_v.sum(axis=0) / n, 0.0)
    dc = np.where(used, log_c - log_c.sum(axis=0) / n, 0.0)
    denominator = float(np.sum(dv * dv))
    if not denominator > 0.0:
        return 2.2
    return float(np.clip(np.sum(dv * dc) / denominator, 0.8, 4.0))


def _with_tail(
    forward: PiecewiseLinearResponse,
    irradiance: NDArray[np.float64],
    raw: NDArray[np.float64],
    weight: NDArray[np.float64],
    top: float,
    observed_top: float,
) -> PiecewiseLinearResponse | None:
    """``forward`` with a fitted top tail, or None when the tail does not describe the data.

    The tail is kept when its RMS residual in its window is at most
    TAIL_MAX_RMS_RATIO times (+ 0.05 DN) the free curve's there.
    irradiance, raw, weight: (N,) the usable samples.
    """
    tail = fit_tail(irradiance, raw, weight, top, observed_top)
    if tail is None:
        return None
    low, high = tail.window
    near = (raw >= low) & (raw <= high)
    free = raw[near] - forward(irradiance[near])
    free_rms = float(np.sqrt(np.average(free * free, weights=weight[near])))
    if tail.rms_dn > TAIL_MAX_RMS_RATIO * free_rms + 0.05:
        return None
    join = high - TAIL_JOIN_FRACTION * (high - low)
    return replace(forward, tail=tail.tail, tail_from=join)


def _tail_value(forward: PiecewiseLinearResponse, irradiance: float) -> float:
    """Raw value of ``forward``'s tail (as joined to the free curve) at ``irradiance``."""
    tail = forward.tail
    assert tail is not None
    rising = np.concatenate([[True], np.diff(forward.values) > 0.0])
    e_join = float(np.interp(forward.tail_from, forward.values[rising], forward.knots[rising]))
    shift = float(tail.inverse(np.asarray(forward.tail_from), forward.top_code)) - e_join
    return float(tail(irradiance + shift, forward.top_code))


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
    tolerance: float = 5e-5,
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
        g, forward, m, m_weight, rms, iters, converged, extent = _fit_channel(
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
            extent=extent,
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
