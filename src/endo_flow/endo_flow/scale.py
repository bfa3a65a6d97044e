"""The depth scale s (metric depth = s · depth_relative): per-frame observations and a filter.

Shape from shading with the near-light model gives depth up to one factor,
1/√ρ with ρ = albedo × light power × exposure (docs/sfs.md). Triangulated
tracks give metric depth z at a few pixels, so each frame observes
ln s = ln z − ln d_rel at those pixels. :func:`observe_scale` turns them into
one robust observation: an M-estimate of the location of the log ratios
(weighted, e.g. by the tracks' parallax), started by Huber iterations from
the median and finished by Tukey's biweight, which gives wild tracks no
weight at all (Huber alone is pulled 2 % by 30 % one-sided outliers), with
its standard error.

:class:`ScaleFilter` is a scalar Kalman filter on ln s, a random walk:

* **predict**: the variance grows by ``process_noise² · dt``;
* **update**: an observation whose innovation is more than ``gate_sigma``
  standard deviations off is rejected and counted (a wild observation);
* **steps**: a gain or exposure change multiplies ρ and so s by a constant
  (a 20 % gain step moves s by √1.2, +9.5 %). A two-sided CUSUM of the
  normalised innovations (accepted or gated), C⁺ = max(0, C⁺ + min(ν/σ, clip) − k) and
  C⁻ likewise, signals a step when one side exceeds ``step_threshold``; the
  filter then jumps to the median of the observations since that side last
  was 0, with their spread as its variance (state RECOVERING), instead of
  creeping towards it at the steady-state gain;
* **known steps**: the pipeline sees an exposure change directly (every
  tracked point brightens by the same factor g from one frame to the next)
  and calls :meth:`ScaleFilter.rescale` with ln √g, so the estimate is right
  on the next frame; the CUSUM is the fallback for steps nothing announces,
  and its threshold is high so that the slow drifts of SFS's own scale over
  a sequence (a few percent) are averaged, not followed;
* **hold**: without observations (a still camera, pure rotation, a tracker
  dropout) the estimate stays where it is; after ``hold_after_s`` the state
  says so (HOLDING).

States: INITIALIZING until the standard deviation first falls below
``converged_std``; then TRACKING, HOLDING or RECOVERING. :attr:`usable` is
True from the first convergence on (the scale of a held or recovering
filter is still the best available).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from endo_io.stamp import NS_PER_S

#: Tukey biweight threshold in robust standard deviations (95 % efficiency).
TUKEY_C = 4.685


class ScaleState(enum.IntEnum):
    """What the scale filter is doing (values are stable: published on the scale topic)."""

    INITIALIZING = 0
    TRACKING = 1
    HOLDING = 2
    RECOVERING = 3


@dataclass(frozen=True)
class ScaleObservation:
    """One frame's robust observation of ln s.

    Attributes:
        log_scale: Huber location of ln(z / d_rel).
        std: its standard deviation (ln units), the statistical error
            combined with the caller's floor.
        spread: robust standard deviation of the individual log ratios.
        count: number of point pairs used.
        inliers: number within the Huber threshold.
    """

    log_scale: float
    std: float
    spread: float
    count: int
    inliers: int


@dataclass(frozen=True)
class ScaleEstimate:
    """The filtered scale.

    Attributes:
        value: s, metres per unit of depth_relative (NaN before any
            observation).
        log_std: standard deviation of ln s (≈ relative std of s).
        state: what the filter is doing.
        usable: the filter has converged at least once.
    """

    value: float
    log_std: float
    state: ScaleState
    usable: bool


def observe_scale(
    metric_depth: np.ndarray,
    relative_depth: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    min_points: int = 8,
    huber_k: float = 1.5,
    floor_std: float = 0.0,
    iterations: int = 10,
) -> ScaleObservation | None:
    """Robust ln s from pairs of metric and relative depth at the same pixels.

    Args:
        metric_depth: (N,) float triangulated depth, metres (> 0).
        relative_depth: (N,) float depth_relative at the same pixels (> 0).
        weights: (N,) float >= 0 relative confidence of each pair, or None.
        min_points: fewer finite, positive pairs give None.
        huber_k: Huber threshold in robust standard deviations (first half
            of the iterations; the second half uses Tukey's biweight).
        floor_std: added in quadrature to the statistical error (ln units):
            errors the pairs share (the camera poses) do not average out.
        iterations: IRLS iterations.

    Returns:
        The observation, or None with fewer than ``min_points`` pairs.
    """
    z = np.asarray(metric_depth, np.float64)
    d = np.asarray(relative_depth, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        log_ratio = np.log(z) - np.log(d)
    return observe_log_ratios(log_ratio, weights, min_points=min_points, huber_k=huber_k,
                              floor_std=floor_std, iterations=iterations)


def median(values: np.ndarray) -> float:
    """``float(np.median(values))``, bit for bit, of a 1-D float array without NaN.

    ``np.median`` partitions the same way but costs ~15 µs per call in its
    wrappers, and the robust location takes a dozen medians per frame.

    Args:
        values: (N,) float32 or float64, no NaN.

    Returns:
        The median (the mean of the two middle values for even N, in the
        array's precision); NaN for N = 0.
    """
    n = values.size
    if n == 0:
        return float("nan")
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return float((part[half - 1] + part[half]) / 2.0)


def observe_log_ratios(
    log_ratio: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    min_points: int = 8,
    huber_k: float = 1.5,
    floor_std: float = 0.0,
    iterations: int = 10,
) -> ScaleObservation | None:
    """Robust ln s from per-point values of ln(z / d_rel); see :func:`observe_scale`.

    Args:
        log_ratio: (N,) float ln(metric / relative) per point (NaN ignored).
        weights, min_points, huber_k, floor_std, iterations: as in
            :func:`observe_scale`.
    """
    values = np.asarray(log_ratio, np.float64)
    w = np.ones_like(values) if weights is None else np.asarray(weights, np.float64)
    ok = np.isfinite(values) & np.isfinite(w) & (w > 0.0)
    if int(ok.sum()) < min_points:
        return None
    r = values[ok]
    w = w[ok] / w[ok].max()
    location = median(r)
    sigma = max(1.4826 * median(np.abs(r - location)), 1e-4)
    robust = np.ones_like(r)
    for iteration in range(iterations):
        u = np.abs(r - location) / sigma
        if iteration < iterations // 2:  # Huber: converges from any start
            robust = np.minimum(1.0, huber_k / np.maximum(u, 1e-12))
        else:  # then Tukey's biweight: far outliers get no weight at all
            robust = np.where(u < TUKEY_C, (1.0 - (u / TUKEY_C) ** 2) ** 2, 0.0)
        total = w * robust
        if total.sum() <= 0.0:
            break
        location = float(np.sum(total * r) / np.sum(total))
        inside = robust > 0.0
        # the spread of the points that carry weight, not of the outliers
        sigma = max(1.4826 * median(np.abs(r[inside] - location)), 1e-4)
    total = w * robust
    n_eff = float(total.sum() ** 2 / max(np.sum(total**2), 1e-300))
    stat = sigma / np.sqrt(max(n_eff, 1.0))
    inliers = int(np.sum(np.abs(r - location) <= huber_k * sigma))
    return ScaleObservation(
        log_scale=location,
        std=float(np.hypot(stat, floor_std)),
        spread=sigma,
        count=int(r.size),
        inliers=inliers,
    )


@dataclass(frozen=True)
class ScaleFilterOptions:
    """Settings of :class:`ScaleFilter` (ln units are relative errors of s).

    Attributes:
        process_noise: random-walk density of ln s, per √second.
        gate_sigma: innovations beyond this many standard deviations are
            rejected.
        step_allowance: the CUSUM's allowance k, standard deviations per
            observation (innovations below it never add up).
        step_threshold: the CUSUM level that signals a step.
        step_clip: an innovation adds at most this many standard deviations
            to the CUSUM, so that one wild observation (which is gated)
            cannot signal a step alone: at least
            step_threshold / (step_clip − step_allowance) of one sign must
            come in a row.
        converged_std: standard deviation of ln s below which the filter is
            converged (TRACKING, usable). With observations fused by their
            novelty (:class:`ViewNovelty`, the pipeline's ``novelty_floor``
            < 1) the variance counts independent views and is larger than
            one fusing every frame as independent claims; 0.05 is then the
            least (in steps of 0.01) with which the phantom converges within
            1 s of 2 mm of motion (docs/flow.md).
        hold_after_s: time without an accepted observation after which the
            state is HOLDING.
        initial_std: standard deviation of the first observation's estimate
            is the observation's own; this caps it from below.
    """

    process_noise: float = 0.003
    gate_sigma: float = 4.0
    step_allowance: float = 1.0
    step_threshold: float = 10.0
    step_clip: float = 2.5
    converged_std: float = 0.03
    hold_after_s: float = 0.3
    initial_std: float = 0.0

    def __post_init__(self) -> None:
        if self.process_noise < 0.0 or self.initial_std < 0.0:
            raise ValueError("process_noise and initial_std must be >= 0")
        if not (self.gate_sigma > 0.0 and self.step_allowance > 0.0
                and self.step_threshold > 0.0):
            raise ValueError("gate_sigma, step_allowance and step_threshold must be > 0")
        if not self.step_clip > self.step_allowance:
            raise ValueError("step_clip must exceed step_allowance")
        if not self.converged_std > 0.0 or self.hold_after_s < 0.0:
            raise ValueError("converged_std must be > 0 and hold_after_s >= 0")


@dataclass(frozen=True)
class ScaleUpdate:
    """What one observation did to the filter.

    Attributes:
        accepted: it entered the estimate.
        gated: it was rejected as an outlier.
        step: it completed a detected step (the filter jumped).
        innovation_sigma: innovation in standard deviations.
    """

    accepted: bool
    gated: bool
    step: bool
    innovation_sigma: float


class ScaleFilter:
    """Kalman filter on ln s with gating, step recovery and hold (see the module docstring).

    Args:
        options: the settings.
    """

    def __init__(self, options: ScaleFilterOptions | None = None) -> None:
        self.options = options or ScaleFilterOptions()
        self.reset()

    def reset(self) -> None:
        """Forget the estimate (a clock jump, a new sequence)."""
        self._log_scale = float("nan")
        self._variance = float("inf")
        self._stamp_ns: int | None = None
        self._last_accepted_ns: int | None = None
        self._converged = False
        self._recovering = False
        self._cusum = [0.0, 0.0]  # upper, lower
        self._since_zero: list[list[float]] = [[], []]
        self.gated = 0
        self.steps = 0
        self.accepted = 0

    @property
    def estimate(self) -> ScaleEstimate:
        """The current estimate."""
        std = float(np.sqrt(self._variance)) if np.isfinite(self._variance) else float("inf")
        if not np.isfinite(self._log_scale):
            state = ScaleState.INITIALIZING
        elif self._recovering:
            state = ScaleState.RECOVERING
        elif not self._converged:
            state = ScaleState.INITIALIZING
        elif self._holding():
            state = ScaleState.HOLDING
        else:
            state = ScaleState.TRACKING
        value = float(np.exp(self._log_scale)) if np.isfinite(self._log_scale) else float("nan")
        return ScaleEstimate(value, std, state, self._converged)

    def _holding(self) -> bool:
        if self._stamp_ns is None or self._last_accepted_ns is None:
            return True
        idle_s = (self._stamp_ns - self._last_accepted_ns) / NS_PER_S
        return idle_s > self.options.hold_after_s

    def predict(self, stamp_ns: int) -> None:
        """Advance to ``stamp_ns`` (integer ns, not before the last one)."""
        if self._stamp_ns is not None and np.isfinite(self._variance):
            dt = max(0.0, (stamp_ns - self._stamp_ns) / NS_PER_S)
            self._variance += self.options.process_noise**2 * dt
        self._stamp_ns = stamp_ns

    def update(self, observation: ScaleObservation, stamp_ns: int,
               novelty: float = 1.0) -> ScaleUpdate:
        """Predict to ``stamp_ns`` and fuse one observation.

        Args:
            observation: the frame's observation.
            stamp_ns: its stamp, integer ns.
            novelty: the share of the observation's evidence that no earlier
                observation used (:class:`ViewNovelty`), in (0, 1]. Its error
                is as large as ``observation.std`` says (the gate and the
                CUSUM use that), but only this share of it is independent of
                what the filter already holds, so it is fused with the
                variance std² / novelty: consecutive frames that see the
                same keyframes repeat their pose errors, and fusing them as
                independent would shrink the variance (and declare
                convergence) on one draw of those errors.
        """
        self.predict(stamp_ns)
        opts = self.options
        z, r = observation.log_scale, observation.std**2
        novelty = float(np.clip(novelty, 1e-6, 1.0))
        if not np.isfinite(self._log_scale):
            self._log_scale = z
            self._variance = max(r / novelty, opts.initial_std**2)
            self._accept(stamp_ns)
            return ScaleUpdate(True, False, False, 0.0)
        innovation = z - self._log_scale
        s = self._variance + r
        sigma = float(innovation / np.sqrt(s))
        values = self._step_values(sigma, z)
        if values is not None:
            self._log_scale = float(np.median(values))
            self._variance = float(np.var(values) + r)
            self._recovering = True
            self.steps += 1
            self._accept(stamp_ns)
            return ScaleUpdate(True, False, True, sigma)
        if abs(sigma) > opts.gate_sigma:
            self.gated += 1
            return ScaleUpdate(False, True, False, sigma)
        gain = self._variance / (self._variance + r / novelty)
        self._log_scale += gain * innovation
        self._variance *= 1.0 - gain
        self._accept(stamp_ns)
        return ScaleUpdate(True, False, False, sigma)

    def rescale(self, log_factor: float, std: float = 0.01) -> None:
        """Multiply the estimate by e^log_factor (a known exposure change).

        Args:
            log_factor: ln of the factor.
            std: its uncertainty (ln units), added to the variance.
        """
        if not np.isfinite(self._log_scale):
            return
        self._log_scale += float(log_factor)
        self._variance += std**2
        self._cusum = [0.0, 0.0]
        self._since_zero = [[], []]
        self.steps += 1

    def _accept(self, stamp_ns: int) -> None:
        self.accepted += 1
        self._last_accepted_ns = stamp_ns
        if self._variance < self.options.converged_std**2:
            self._converged = True
            self._recovering = False

    def _step_values(self, sigma: float, z: float) -> np.ndarray | None:
        """Update the CUSUM; the observations of the side that signals a step, or None."""
        k, h = self.options.step_allowance, self.options.step_threshold
        clipped = float(np.clip(sigma, -self.options.step_clip, self.options.step_clip))
        for side, signed in ((0, clipped), (1, -clipped)):
            level = max(0.0, self._cusum[side] + signed - k)
            if level == 0.0:
                self._since_zero[side] = []
            else:
                self._since_zero[side].append(z)
            self._cusum[side] = level
        for side in (0, 1):
            if self._cusum[side] > h:
                values = np.array(self._since_zero[side])
                self._cusum = [0.0, 0.0]
                self._since_zero = [[], []]
                return values
        return None


class ViewNovelty:
    """Which views earlier scale observations used, and how new an observation's evidence is.

    A frame's observation averages its tracks' ln(z / d_rel) over all their
    views (the keyframes and the current frame). The error a view brings
    (its camera pose's error, SFS's error at the tracks in that image) is
    fixed once the view exists, so the next frames, which see mostly the
    same keyframes, repeat it: consecutive observations are correlated
    (lag-one autocorrelation 0.5–0.9 on the evaluation bags), and fusing
    them as independent shrinks the filter's variance on one draw of those
    errors. The share of an observation's weight that lies on views no
    earlier observation used,

        novelty = Σ_new views w_v / Σ_views w_v,
        w_v = Σ_tracks seeing v (track weight / the track's view count),

    is taken as the share of its error that is independent of what the
    filter holds (a frame's own view is always new, a new keyframe once),
    and :meth:`ScaleFilter.update` fuses the observation with its variance
    divided by that share: the filter's variance then counts independent
    views, not frames.

    Args:
        floor: least novelty returned (a frame whose views were all used
            before still brings its share of independent noise).
    """

    def __init__(self, floor: float = 0.02) -> None:
        if not 0.0 < floor <= 1.0:
            raise ValueError(f"floor must be in (0, 1], got {floor}")
        self.floor = float(floor)
        self._used: set[int] = set()

    def reset(self) -> None:
        """Forget every view used."""
        self._used.clear()

    def novelty(self, view_stamps: np.ndarray, view_weights: np.ndarray) -> float:
        """The share of the weight on views not used before (at least ``floor``).

        Args:
            view_stamps: (V,) int64 stamps of the observation's views, ns.
            view_weights: (V,) float >= 0 weight of the observation on each.
        """
        w = np.asarray(view_weights, np.float64)
        total = float(w.sum())
        if not total > 0.0:
            return 1.0
        new = np.array([int(stamp) not in self._used for stamp in view_stamps], bool)
        return max(self.floor, float(w[new].sum()) / total)

    def use(self, view_stamps: np.ndarray, oldest_ns: int | None = None) -> None:
        """Mark views as used; forget those stamped before ``oldest_ns`` (out of the window)."""
        self._used.update(int(stamp) for stamp in view_stamps)
        if oldest_ns is not None:
            self._used = {stamp for stamp in self._used if stamp >= oldest_ns}


def view_weights(valid: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N, V) bool views of N tracks and their (N,) weights -> (V,) float64 weight per view.

    Each track spreads its weight evenly over the views it was seen in (its
    ln ratio is the mean over them).
    """
    seen = np.asarray(valid, np.float64)
    count = np.maximum(seen.sum(axis=1, keepdims=True), 1.0)
    return np.asarray((np.asarray(weights, np.float64)[:, None] * seen / count).sum(axis=0))
