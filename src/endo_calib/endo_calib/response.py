"""Camera response: the forward fit model and the inverse-response LUT.

A raw value is ``v = f(E)`` with ``f`` monotone. The calibration hands out the
inverse ``g = f⁻¹`` as a look-up table with one entry per raw value
(``2^bits`` entries), normalised so that ``g(0) = 0`` and ``g(v_max) = 1``.

The fit, however, models the *forward* response ``f`` as a monotone
piecewise-linear function of irradiance on a knot grid, parametrised by
non-negative increments (so monotonicity is a simple bound). The reason is
statistical: the noise of a camera lives in the raw values (read noise,
quantisation, and shot noise passed through the response), so regressing the
observed value on a known irradiance, E[v | E] ≈ f(E), is unbiased, whereas
averaging irradiances per observed value, E[E | v], is biased by about one
noise standard deviation at both ends of the observed range. The LUT is the
exact inverse of the fitted forward curve.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from endo_calib.errors import CalibrationError, FitError

#: Quantile of the fitted irradiances taken as the bottom of the data.
LOW_DATA_QUANTILE = 0.001
#: Windows below the top raw value (fractions of the range) tried for the shoulder fit.
SHOULDER_WINDOWS = (0.02, 0.03, 0.05)
#: Window below the highest observed code (fraction of the full scale) the top tail is fitted to.
TAIL_WINDOW_FRACTION = 0.3
#: Bit depths a raw image may have (values stored in uint8 or uint16).
SUPPORTED_BIT_DEPTHS = (8, 10, 12, 14, 16)


class InverseResponseError(CalibrationError, ValueError):
    """An inverse-response table is not monotone, not normalised, or has the wrong length."""


@dataclass(frozen=True, eq=False)
class InverseResponse:
    """The inverse camera response ``g`` as a table over raw values.

    lut:
        (2^bit_depth,) float64, ``lut[v] = g(v)``: linear irradiance of raw
        value ``v``, non-decreasing, ``lut[0] = 0``, ``lut[-1] = 1``.
    bit_depth:
        Significant bits of the raw values (8, 10, 12, 14 or 16).
    """

    lut: NDArray[np.float64]
    bit_depth: int

    def __post_init__(self) -> None:
        lut = np.array(self.lut, dtype=np.float64).reshape(-1)
        if self.bit_depth not in SUPPORTED_BIT_DEPTHS:
            raise InverseResponseError(
                f"bit depth {self.bit_depth} not one of {SUPPORTED_BIT_DEPTHS}"
            )
        if lut.size != 1 << self.bit_depth:
            raise InverseResponseError(
                f"inverse response has {lut.size} entries, {1 << self.bit_depth} expected "
                f"for {self.bit_depth}-bit raw values"
            )
        if not np.all(np.isfinite(lut)):
            raise InverseResponseError("inverse response has non-finite entries")
        if np.any(np.diff(lut) < 0.0):
            raise InverseResponseError("inverse response is not monotone non-decreasing")
        if abs(lut[0]) > 1e-9 or abs(lut[-1] - 1.0) > 1e-6:
            raise InverseResponseError(
                "inverse response must run from g(0)=0 to g(max)=1, "
                f"got {lut[0]:.6g}..{lut[-1]:.6g}"
            )
        lut.setflags(write=False)
        object.__setattr__(self, "lut", lut)

    @classmethod
    def from_values(cls, values: ArrayLike) -> InverseResponse:
        """Build from any monotone table of 2^bits values, rescaled to g(0)=0, g(max)=1.

        values: (2^bits,) float, non-decreasing with values[-1] > values[0].
        """
        table = np.asarray(values, dtype=np.float64).reshape(-1)
        bits = table.size.bit_length() - 1
        if table.size < 2 or 1 << bits != table.size:
            raise InverseResponseError(
                f"an inverse response needs 2^bits entries, got {table.size}"
            )
        span = table[-1] - table[0]
        if not np.isfinite(span) or span <= 0.0:
            raise InverseResponseError("inverse response table is flat or not finite")
        return cls((table - table[0]) / span, bits)

    @classmethod
    def linear(cls, bit_depth: int = 8) -> InverseResponse:
        """The identity response (a linear camera)."""
        n = 1 << bit_depth
        return cls(np.arange(n, dtype=np.float64) / (n - 1), bit_depth)

    @property
    def max_value(self) -> int:
        """The largest raw value, 2^bits − 1."""
        return (1 << self.bit_depth) - 1

    def __call__(self, values: ArrayLike) -> NDArray[np.float64]:
        """g at raw values (any shape, integer or fractional; linear between entries).

        Values are clipped to [0, max_value]. Returns float64 irradiance in [0, 1].
        """
        v = np.asarray(values)
        if np.issubdtype(v.dtype, np.integer):
            return np.take(self.lut, np.clip(v, 0, self.max_value))
        grid = np.arange(self.lut.size, dtype=np.float64)
        return np.interp(np.asarray(v, dtype=np.float64), grid, self.lut)

    def forward(self, irradiance: ArrayLike) -> NDArray[np.float64]:
        """The response f = g⁻¹: raw value (fractional, float64) of irradiance in [0, 1]."""
        grid = np.arange(self.lut.size, dtype=np.float64)
        lut, keep = np.unique(self.lut, return_index=True)
        return np.interp(np.asarray(irradiance, dtype=np.float64), lut, grid[keep])


@dataclass(frozen=True)
class Shoulder:
    """The top of a response: E(v) = E_s − A·(top − v)^β.

    saturation_irradiance: E_s, where the response reaches the top raw value.
    scale: A > 0. exponent: β in [0.2, 2]; 1 is a straight end (a gamma
    camera), β < 1 the ever-flatter shoulder of an S-shaped or knee response,
    whose last raw values span a large stretch of irradiance.
    """

    saturation_irradiance: float
    scale: float
    exponent: float

    def inverse(self, raw: NDArray[np.float64], top_code: float) -> NDArray[np.float64]:
        """E at raw values (≤ top_code; above it E_s)."""
        u = np.clip(top_code - np.asarray(raw, dtype=np.float64), 0.0, None)
        return self.saturation_irradiance - self.scale * u**self.exponent


def fit_shoulder(
    irradiance: NDArray[np.float64],
    raw: NDArray[np.float64],
    top_code: float,
    anchor: tuple[float, float] | None = None,
    min_points: int = 500,
) -> Shoulder | None:
    """Fit :class:`Shoulder` to the (irradiance, mean raw value) samples near the top.

    Where the response meets its top raw value cannot be observed (every
    irradiance beyond the threshold of the last code reads the same), so it is
    extrapolated, and the shape of the last few codes decides how far. The fit
    minimises raw-value residuals v − (top − ((E_s − E)/A)^(1/β)) over samples
    within a window below the top, the narrowest of ``SHOULDER_WINDOWS`` (as
    fractions of the range) that holds ``min_points`` samples: one exponent
    describes only the last few codes of a curve; ``anchor`` (E*, v*), the
    saturation onset, enters with a large weight.

    irradiance, raw: (N,) samples. Returns None when too few samples are near
    the top (the caller then continues the curve in a straight line).
    """
    e_all = np.asarray(irradiance, dtype=np.float64).ravel()
    v_all = np.asarray(raw, dtype=np.float64).ravel()
    for fraction in SHOULDER_WINDOWS:
        near = v_all >= top_code * (1.0 - fraction)
        if near.sum() >= min_points:
            break
    else:
        return None
    e, v = e_all[near], v_all[near]
    weight = np.ones_like(e)
    if anchor is not None:
        e = np.append(e, anchor[0])
        v = np.append(v, anchor[1])
        weight = np.append(weight, max(100.0, 0.02 * e.size))
    e_top = float(np.max(e))
    root_w = np.sqrt(weight)

    def residuals(params: NDArray[np.float64]) -> NDArray[np.float64]:
        e_sat, log_scale, beta = params
        gap = np.clip(e_sat - e, 1e-15, None)
        return root_w * (v - (top_code - (gap / np.exp(log_scale)) ** (1.0 / beta)))

    # Imported here: a process that only corrects images (endo-process's workers) skips it.
    import scipy.optimize

    best = None
    for beta in (0.4, 0.6, 0.8, 1.0):
        e_sat = 1.03 * e_top
        start = np.array([e_sat, np.log((e_sat - e_top) / 0.5**beta), beta])
        result = scipy.optimize.least_squares(
            residuals, start, bounds=([e_top * (1 + 1e-9), -50.0, 0.2], [2.0 * e_top, 50.0, 2.0])
        )
        if best is None or result.cost < best.cost:
            best = result
    if best is None or not best.success:
        return None
    e_sat, log_scale, beta = (float(x) for x in best.x)
    return Shoulder(e_sat, float(np.exp(log_scale)), beta)


@dataclass(frozen=True)
class LogitPowerTail:
    """A smooth monotone top of a response: v/T = x^c / (x^c + (1 − x)^c), x = (E/E_s)^(1/γ).

    The family holds a pure power law (c = 1: a gamma camera, finite slope at
    the top) and film-like S shoulders (c > 1: the curve flattens into full
    scale, so the last codes span a large stretch of irradiance). It is fitted
    to the brightest observed codes and carries the curve from the highest
    code observed unsaturated up to the top code T, where it reaches E_s.

    saturation_irradiance: E_s > 0, the irradiance at which the curve reaches T.
    contrast: c in [0.5, 6]. exponent: γ in [0.3, 6].
    """

    saturation_irradiance: float
    contrast: float
    exponent: float

    def __call__(self, irradiance: ArrayLike, top_code: float) -> NDArray[np.float64]:
        """Raw value (float64, DN) at irradiance (clipped to [0, E_s])."""
        y = np.clip(np.asarray(irradiance, dtype=np.float64) / self.saturation_irradiance, 0, 1)
        x = y ** (1.0 / self.exponent)
        xc = x**self.contrast
        return top_code * xc / np.maximum(xc + (1.0 - x) ** self.contrast, 1e-300)

    def inverse(self, raw: ArrayLike, top_code: float) -> NDArray[np.float64]:
        """Irradiance at raw values (clipped to [0, top_code]); E_s at the top code."""
        v = np.clip(np.asarray(raw, dtype=np.float64) / top_code, 0.0, 1.0)
        with np.errstate(divide="ignore"):
            ratio = ((1.0 - v) / np.maximum(v, 1e-300)) ** (1.0 / self.contrast)
        x = np.where(v > 0.0, 1.0 / (1.0 + ratio), 0.0)
        return self.saturation_irradiance * x**self.exponent

    def describe(self) -> str:
        """One line naming the family and its parameters (for the YAML and the report)."""
        return (
            f"logit-power tail: v/T = x^c/(x^c+(1-x)^c), x = (E/E_s)^(1/gamma), "
            f"c = {self.contrast:.4g}, gamma = {self.exponent:.4g}"
        )


@dataclass(frozen=True)
class TailFit:
    """A fitted :class:`LogitPowerTail` and how well it describes its window.

    tail: the fitted tail. rms_dn: weighted RMS raw-value residual in the window.
    window: (low, high) raw values of the samples it was fitted to.
    """

    tail: LogitPowerTail
    rms_dn: float
    window: tuple[float, float]


def fit_tail(
    irradiance: NDArray[np.float64],
    raw: NDArray[np.float64],
    weight: NDArray[np.float64],
    top_code: float,
    observed_top: float,
    *,
    window_fraction: float = TAIL_WINDOW_FRACTION,
    max_samples: int = 8000,
    min_samples: int = 200,
) -> TailFit | None:
    """Fit :class:`LogitPowerTail` to the brightest observed samples.

    The data stop at ``observed_top`` (the highest code observed unsaturated);
    the curve above it cannot be measured and is extrapolated along this
    family, fitted to the samples within ``window_fraction`` of the full scale
    below ``observed_top`` (raw-value residuals, weights ``weight``).

    irradiance, raw, weight: (N,) samples (fit's irradiance scale, DN, 1/DN²).
    top_code: 2^bits − 1. Returns None when the window holds fewer than
    ``min_samples`` samples or the least-squares fit fails.
    """
    e_all = np.asarray(irradiance, dtype=np.float64).ravel()
    v_all = np.asarray(raw, dtype=np.float64).ravel()
    w_all = np.asarray(weight, dtype=np.float64).ravel()
    low = observed_top - window_fraction * top_code
    near = np.flatnonzero((v_all >= low) & (v_all <= observed_top) & (w_all > 0.0))
    if near.size < min_samples:
        return None
    if near.size > max_samples:
        near = np.sort(np.random.default_rng(0).choice(near, max_samples, replace=False))
    e, v = e_all[near], v_all[near]
    root_w = np.sqrt(w_all[near] / np.mean(w_all[near]))
    e_top = float(np.max(e))

    def residuals(params: NDArray[np.float64]) -> NDArray[np.float64]:
        tail = LogitPowerTail(float(params[0]), float(params[1]), float(params[2]))
        return root_w * (tail(e, top_code) - v)

    import scipy.optimize  # here: a process that only corrects images skips it

    best = None
    for contrast in (1.0, 1.6, 2.5):
        for exponent in (1.5, 2.2, 3.0):
            start = np.array([1.2 * e_top, contrast, exponent])
            try:
                result = scipy.optimize.least_squares(
                    residuals,
                    start,
                    bounds=([e_top * (1 + 1e-6), 0.5, 0.3], [20.0 * e_top, 6.0, 6.0]),
                    x_scale=np.array([e_top, 1.0, 1.0]),
                )
            except ValueError:
                continue
            if best is None or result.cost < best.cost:
                best = result
    if best is None or not np.all(np.isfinite(best.x)):
        return None
    tail = LogitPowerTail(float(best.x[0]), float(best.x[1]), float(best.x[2]))
    rms = float(np.sqrt(2.0 * best.cost / e.size))
    return TailFit(tail, rms, (float(np.min(v)), float(observed_top)))


@dataclass(frozen=True, eq=False)
class PiecewiseLinearResponse:
    """A monotone forward response ``f``: raw value (DN) against irradiance.

    knots: (n+1,) float64 irradiances, strictly increasing, knots[0] = 0.
    values: (n+1,) float64 raw values at the knots, non-decreasing, values[0] = 0.
    data_low: the lowest irradiance the curve was fitted to (0: unknown). Below
        it the inverse follows a power law (see :meth:`inverse`).
    top_code: the largest raw value, 2^bits − 1 (0: unknown).
    shoulder: the fitted top of the curve from partly saturated data, used
        between the last knot and ``top_code``.
    tail: without a shoulder, the smooth tail fitted to the brightest observed
        codes that carries the curve above them (None and no shoulder: a
        straight continuation of the top slope).
    tail_from: the raw value above which the tail replaces the free curve
        (joined continuously there); 0: the last knot's value.
    """

    knots: NDArray[np.float64]
    values: NDArray[np.float64]
    data_low: float = 0.0
    top_code: float = 0.0
    shoulder: Shoulder | None = None
    tail: LogitPowerTail | None = None
    tail_from: float = 0.0

    def __call__(self, irradiance: ArrayLike) -> NDArray[np.float64]:
        """f(E): (...) irradiance (same units as the knots) to (...) float64 raw values."""
        e = np.asarray(irradiance, dtype=np.float64)
        knots, values = self._extended()
        return np.interp(e, knots, values)

    def slope(self, irradiance: ArrayLike) -> NDArray[np.float64]:
        """df/dE at ``irradiance``, float64, smoothed.

        The segment slopes interpolated linearly between segment midpoints (a
        continuous Jacobian for Gauss–Newton).
        """
        e = np.asarray(irradiance, dtype=np.float64)
        slopes = np.diff(self.values) / np.diff(self.knots)
        mids = 0.5 * (self.knots[:-1] + self.knots[1:])
        return np.interp(e, mids, slopes)

    def _extended(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Knots and values with a far point that continues the last segment's slope."""
        k, v = self.knots, self.values
        far = k[-1] + 1e6 * max(k[-1], 1.0)
        top = v[-1] + (far - k[-1]) * (v[-1] - v[-2]) / (k[-1] - k[-2])
        return np.append(k, far), np.append(v, top)

    def inverse(self, raw: ArrayLike) -> NDArray[np.float64]:
        """E = f⁻¹(v) for (...) raw values.

        Flat stretches of ``f`` map to their lowest irradiance. Above the last
        knot (the brightest data) the curve is continued by a quadratic fitted to
        the knots of the top 15% of the irradiance range, which follows the
        bend of a compressive (gamma or S-shaped) top better than the noisy
        slope of the last segment; a straight line is used when that quadratic
        would not rise.
        """
        v = np.asarray(raw, dtype=np.float64)
        rising = np.concatenate([[True], np.diff(self.values) > 0.0])
        ys, es = self.values[rising], self.knots[rising]
        inside = np.interp(v, ys, es)
        if self.tail is not None and self.shoulder is None and 0.0 < self.tail_from < ys[-1]:
            # The free curve's last few codes rest on few samples; the tail,
            # fitted to the whole window, takes over inside it.
            e_join = float(np.interp(self.tail_from, ys, es))
            above = (
                e_join
                + self.tail.inverse(v, self.top_code)
                - self.tail.inverse(np.asarray(self.tail_from), self.top_code)
            )
            result = np.where(v > self.tail_from, above, inside)
        else:
            result = np.where(v > ys[-1], self._extrapolate_top(v), inside)
        if self.data_low > 0.0:
            # Below the darkest data a straight chord to (0, 0) would misjudge
            # a curved toe (g ∝ v^2.2 for a gamma camera); continue with the
            # power law of the lowest fitted stretch instead.
            v_low = float(np.interp(self.data_low, self.knots, self.values))
            v_two = 2.0 * v_low
            if v_low > 0.0 and v_two < ys[-1]:
                e_two = float(np.interp(v_two, ys, es))
                exponent = float(np.clip(np.log(e_two / self.data_low) / np.log(2.0), 0.5, 4.0))
                below = self.data_low * (np.clip(v, 0.0, None) / v_low) ** exponent
                result = np.where(v < v_low, below, result)
        return result

    def _extrapolate_top(self, raw: NDArray[np.float64]) -> NDArray[np.float64]:
        """Irradiance above the last knot for raw values beyond its value.

        With a fitted :class:`Shoulder` or :class:`LogitPowerTail` the curve
        continues along it (shifted to join the last knot); otherwise along a
        straight line with the mean slope of the top 15% of the irradiance range.
        """
        k, y = self.knots, self.values
        e_top, v_top = float(k[-1]), float(y[-1])
        if self.shoulder is not None and self.top_code > v_top:
            return (
                e_top
                + self.shoulder.inverse(raw, self.top_code)
                - self.shoulder.inverse(np.asarray(v_top), self.top_code)
            )
        if self.tail is not None and self.top_code > v_top:
            return (
                e_top
                + self.tail.inverse(raw, self.top_code)
                - self.tail.inverse(np.asarray(v_top), self.top_code)
            )
        sel = k >= 0.85 * e_top
        if sel.sum() < 4:
            sel = np.zeros_like(sel)
            sel[-min(4, k.size) :] = True
        mean_slope = float(np.polyfit(k[sel], y[sel], 1)[0])
        if not mean_slope > 0.0:
            mean_slope = float((y[-1] - y[0]) / (k[-1] - k[0]))
        return e_top + np.maximum(raw - v_top, 0.0) / mean_slope

    def with_top_knot(self, irradiance: float, raw: float) -> PiecewiseLinearResponse:
        """This curve with one more knot (irradiance, raw) beyond its last one.

        Used to pin the curve at the saturation onset found from partly
        saturated data; ignored (self returned) unless it extends the curve upwards.
        """
        if irradiance <= self.knots[-1] or raw <= self.values[-1]:
            return self
        return replace(
            self, knots=np.append(self.knots, irradiance), values=np.append(self.values, raw)
        )

    def inverse_response(
        self, bit_depth: int, saturation_irradiance: float | None = None
    ) -> InverseResponse:
        """The normalised inverse LUT of this curve for ``bit_depth``-bit raw values.

        saturation_irradiance: the irradiance that maps to the top raw value; by
        default f⁻¹(2^bits − 1), extrapolated with the top slope when the data
        stop short of it.
        """
        top = (1 << bit_depth) - 1
        table = self.inverse(np.arange(top + 1, dtype=np.float64))
        scale = (
            float(self.inverse(float(top)))
            if saturation_irradiance is None
            else saturation_irradiance
        )
        table = np.clip(table - table[0], 0.0, None)
        table = np.maximum.accumulate(table) / scale
        table[-1] = 1.0
        return InverseResponse(np.minimum(table, 1.0), bit_depth)


def _segment(
    knots: NDArray[np.float64], e: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Segment index and fractional position of irradiances on the knot grid (t > 1 above)."""
    seg = np.clip(np.searchsorted(knots, e, side="right") - 1, 0, knots.size - 2)
    t = (e - knots[seg]) / (knots[seg + 1] - knots[seg])
    return seg, t


def fit_forward_response(
    irradiance: NDArray[np.floating],
    raw: NDArray[np.floating],
    weight: NDArray[np.floating],
    knots: NDArray[np.float64],
    smoothness: float = 1e-4,
    min_slope_fraction: float = 1e-3,
    top_code: float = 0.0,
) -> PiecewiseLinearResponse:
    """Weighted least-squares fit of a monotone piecewise-linear response.

    Minimises Σ w·(v − f(E))² + λ·W·Σ_j (h̄_j·Δs_j)² over f with f(0) = 0 and
    non-negative increments, where Δs_j is the change of slope at interior knot
    j, h̄_j the mean length of its two segments and W = Σ w; λ = ``smoothness``
    keeps knots without data on a straight continuation of their neighbours.

    irradiance, raw, weight: (N,) samples: irradiance E (≥ 0, knot units), the
    observed mean raw value (DN) and its weight (1/variance of the mean, 1/DN²).
    knots: (n+1,) strictly increasing irradiances with knots[0] = 0.
    min_slope_fraction: lower bound of every segment's slope, as a fraction of
    the mean slope max(v)/max(E), which makes f strictly increasing.
    top_code: the largest raw value (2^bits − 1), for the shoulder above the
    data (0: unknown, a straight continuation is used).
    Returns the fitted :class:`PiecewiseLinearResponse` (``data_low``: the
    ``LOW_DATA_QUANTILE`` quantile of E, robust to a few stray dark samples).
    """
    import scipy.linalg  # here, as scipy.optimize: not loaded by a process that only corrects
    import scipy.optimize

    knots = np.asarray(knots, dtype=np.float64)
    n = knots.size - 1
    if n < 2 or knots[0] != 0.0 or np.any(np.diff(knots) <= 0.0):
        raise FitError("response knots must start at 0 and increase strictly (>= 3 knots)")
    e = np.asarray(irradiance, dtype=np.float64).ravel()
    v = np.asarray(raw, dtype=np.float64).ravel()
    w = np.asarray(weight, dtype=np.float64).ravel()
    total = float(w.sum())
    if e.size == 0 or total <= 0.0:
        raise FitError("no samples to fit the response to")
    seg, t = _segment(knots, e)
    size = n + 1
    # Normal equations of the hat basis: tridiagonal, accumulated per segment.
    diag = np.bincount(seg, w * (1 - t) ** 2, size) + np.bincount(seg + 1, w * t * t, size)
    off = np.bincount(seg, w * t * (1 - t), size)[:n]
    rhs = np.bincount(seg, w * (1 - t) * v, size) + np.bincount(seg + 1, w * t * v, size)
    normal = np.diag(diag) + np.diag(off, 1) + np.diag(off, -1)
    # Slope-change penalty: row j acts on knots j-1, j, j+1.
    h = np.diff(knots)
    rows = np.zeros((n - 1, size))
    idx = np.arange(n - 1)
    hbar = 0.5 * (h[:-1] + h[1:])
    rows[idx, idx] = hbar / h[:-1]
    rows[idx, idx + 1] = -hbar / h[:-1] - hbar / h[1:]
    rows[idx, idx + 2] = hbar / h[1:]
    system = normal + smoothness * total * (rows.T @ rows)
    # Unknowns: increments d_j = y_j - y_{j-1} >= 0, j = 1..n (y_0 = 0 fixed).
    cumulative = np.tril(np.ones((n, n)))
    q = cumulative.T @ system[1:, 1:] @ cumulative
    c = cumulative.T @ rhs[1:]
    q += np.eye(n) * (1e-12 * np.trace(q) / n)
    try:
        chol = scipy.linalg.cholesky(q, lower=True)
    except np.linalg.LinAlgError as error:
        raise FitError(f"response fit is singular: {error}") from error
    target = scipy.linalg.solve_triangular(chol, c, lower=True)
    # A floor on every slope (min_slope_fraction of the mean slope of the data)
    # keeps f strictly increasing: a flat stretch has no inverse and would stall
    # the light update, which follows the slope.
    mean_slope = max(float(np.max(v) - 0.0), 1e-12) / max(float(np.max(e)), 1e-12)
    floor = min_slope_fraction * mean_slope * h
    shifted, _ = scipy.optimize.nnls(chol.T, target - chol.T @ floor, maxiter=50 * n)
    values = np.concatenate([[0.0], np.cumsum(shifted + floor)])
    return PiecewiseLinearResponse(
        knots, values, float(np.quantile(e, LOW_DATA_QUANTILE)), float(top_code)
    )
