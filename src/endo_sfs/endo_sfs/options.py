"""The solver settings of one shape-from-shading problem, in one frozen object.

:class:`SfsOptions` holds every setting of :func:`endo_sfs.solve` that is
not a per-frame array (those are ``mask``, ``warm_start`` and
``boundary_depth``). It is validated once, when built: a solve never starts
with a setting out of range, and the ``sfs`` node builds a new one only when
a parameter changes, not per frame. Change a setting with
``dataclasses.replace(options, roughness=0.3)`` (validated again).
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass

from endo_sfs.errors import InvalidOptionError, UnknownModelError
from endo_sfs.near_light import MAX_ROUGHNESS

#: The reflectance geometries :func:`endo_sfs.solve` implements.
MODELS: tuple[str, ...] = ("near_light", "orthographic")
#: Upwind schemes: 1 first-order Godunov, 2 second-order, 3 WENO3 Godunov.
ORDERS: tuple[int, ...] = (1, 2, 3)
#: Default stopping tolerance of the near-light sweeps: largest change of
#: ln r in a full iteration (a relative depth change of 1e-4). 1e-5 until
#: session 14: 1e-4 does 0.83 of the node solves on the phantom, with the
#: same AbsRel to 1e-5 on the phantom and on held-out renders, and two
#: solves of a frame still agree within :func:`agreement_bound` (docs/sfs.md,
#: "Speed").
DEFAULT_TOLERANCE = 1e-4
#: :func:`agreement_bound`'s factors: median ≤ AGREEMENT_MEDIAN·τ, 99.9th
#: percentile ≤ AGREEMENT_P999·τ, every pixel ≤ AGREEMENT_LARGEST·√τ.
AGREEMENT_MEDIAN = 0.5
AGREEMENT_P999 = 30.0
AGREEMENT_LARGEST = 10.0
#: The tolerances :func:`agreement_bound` holds for: measured from 1e-9 (where
#: the float32 depth's rounding, :data:`FLOAT32_SPACING`, dominates) to 1e-3;
#: at 1e-2 the median reached 0.7·τ (review, session 14).
AGREEMENT_TOLERANCES = (1e-9, 1e-3)
#: Relative spacing of float32 numbers near 1 (2⁻²³): two depths rounded to
#: float32 may differ by that much whatever the solver did.
FLOAT32_SPACING = 2.0**-23
DEFAULT_MAX_ITERATIONS = 60
#: Largest irradiance a frame may hold (image units). endo_calib's correction
#: gives g(v)/L(x) with g ≤ 1 and the light map L normalised to ≤ 1, so its
#: values stay within 1/L_min (~1e2 at a vignetted rim); 1e6 leaves room for
#: other linear sources (float counts of a 16-bit sensor) while refusing a
#: frame whose values cannot be irradiance (1e30: an overflowed upstream
#: computation, garbage bytes read as float).
DEFAULT_MAX_IRRADIANCE = 1e6
#: Largest reduction of the image for highlight detection.
MAX_HIGHLIGHT_DOWNSAMPLE = 8
#: solve_scale at and below which highlights are detected on the halved image
#: when ``highlight_downsample`` is 0 (the default).
HALVED_DETECTION_SCALE = 0.5
#: Images of at least this many rows are detected on the halved image at every
#: solve_scale when ``highlight_downsample`` is 0: at 640×480 and solve_scale 1
#: that costs about half, and the AbsRel moved by at most 0.0002 (docs/sfs.md,
#: "Cost per frame", session 8).
HALVED_DETECTION_ROWS = 480
#: With ``threads`` 0 (auto), images of at least this many pixels at
#: ``solve_scale`` get two threads, smaller ones one (the solve grid inside the
#: field of view is smaller still: 67 032 nodes at 640×480 and 0.5, 267 672 at
#: 1). 640×480 at solve_scale 0.5 is 76 800 pixels: one
#: thread solves it in ~17 ms, within a 30 fps frame interval, for ~10 % less
#: CPU, and kept every frame of the 60 s colon at 30 fps where two threads
#: skipped (their parallel regions wait for a descheduled thread on a busy
#: machine); full resolution (307 200 pixels) needs both to pass 15 Hz
#: (docs/benchmarks.md, "Session 14: one SFS thread at solve_scale 0.5").
TWO_THREAD_PIXELS = 150_000


@dataclass(frozen=True)
class SfsOptions:
    """Settings of :func:`endo_sfs.solve` and :func:`endo_sfs.reconstruct`.

    Attributes:
        model: "near_light" (Prados–Faugeras perspective, light at the
            optical centre, 1/r² fall-off) or "orthographic" (the seed
            paper's Eikonal model).
        roughness: Oren–Nayar σ in radians, 0 (Lambertian) to 0.6.
        solve_scale: solve-grid density relative to the pixels, (0, 1]; the
            result is resampled back to (H, W).
        tolerance: stop when a full iteration changes no node by more than
            this (near-light: ln r, i.e. relative depth; orthographic:
            depth), > 0.
        max_iterations: cap on full iterations (four sweeps each), ≥ 1.
        order: 1 first-order Godunov, 2 second-order upwind, 3 WENO3 Godunov.
        dark_level: irradiance at or below this is not data, ≥ 0.
        saturation: irradiance at or above this is not data; None: no upper
            limit. Must exceed ``dark_level``.
        max_irradiance: a frame with a finite pixel above this is physically
            implausible and refused (:class:`endo_sfs.errors.IrradianceRangeError`),
            > ``dark_level``; see :data:`DEFAULT_MAX_IRRADIANCE`.
        singular_tolerance: orthographic only: nodes with
            c ≥ max(c) − this are singular points (sources of the Eikonal)
            when no ``boundary_depth`` is given, in [0, 1).
        concave: orthographic only: the singular points are depth maxima.
        smoothing: Gaussian σ in pixels applied to the valid irradiance
            before solving (:func:`endo_sfs.relative_depth.smooth_irradiance`);
            0 for none.
        mask_highlights: detect specular highlights and their shoulders
            (:func:`endo_sfs.highlights.detect_highlights`) and give them no
            data term; they come out NaN, like every other masked pixel.
        highlight_downsample: the detection runs on the image reduced by
            this factor (``detect_highlights(downsample=...)``), 1 to
            :data:`MAX_HIGHLIGHT_DOWNSAMPLE`, or 0 (the default): as the
            solve grid and the image size allow, :meth:`detection_downsample`
            (2 at ``solve_scale`` ≤ 0.5 or with 480 rows or more, else 1).
            At 640×480 the halved image costs about half (docs/sfs.md,
            "Cost per frame"), with the phantom's AbsRel unchanged at
            solve_scale 0.5 (0.0797) and 0.0787 against 0.0788 at 1.
        threads: CPU threads for the resampling, the highlight detection
            (two independent halves of its baseline at once,
            :func:`endo_sfs.highlights.detect_highlights`) and, with the
            near-light model on large grids, for the first pass of the
            solver (two halves at once), ≥ 1; or 0: as the solve grid needs,
            :meth:`solve_threads`. 1 gives bit-identical results run to
            run; 2 gives results equal to those to the tolerance.
        first_sweeps: near-light, warm-started frames solved by sweeps
            alone (no first pass): each node is first solved in the sweep
            that meets its upwind neighbours (by the previous frame's
            solution) before it, not in the first sweep that reaches it
            (see docs/sfs.md, "Cost per frame").

    Raises:
        UnknownModelError: ``model`` is not one of :data:`MODELS`.
        InvalidOptionError: another setting is out of its range; the
            message names it, its range and the value given.
    """

    model: str = "near_light"
    roughness: float = 0.0
    solve_scale: float = 1.0
    tolerance: float = DEFAULT_TOLERANCE
    max_iterations: int = DEFAULT_MAX_ITERATIONS
    order: int = 2
    dark_level: float = 0.0
    saturation: float | None = None
    max_irradiance: float = DEFAULT_MAX_IRRADIANCE
    singular_tolerance: float = 1e-3
    concave: bool = False
    smoothing: float = 0.0
    mask_highlights: bool = False
    highlight_downsample: int = 0
    threads: int = 1
    first_sweeps: bool = True

    def __post_init__(self) -> None:
        # Plain Python numbers from here on (an int for a float, numpy
        # scalars): numba specialises its kernels on the argument types.
        for name in _FLOATS:
            _coerce(self, name, float)
        for name in _INTEGERS:
            _coerce(self, name, int)
        if self.saturation is not None:
            _coerce(self, "saturation", float)
        object.__setattr__(self, "concave", bool(self.concave))
        object.__setattr__(self, "mask_highlights", bool(self.mask_highlights))
        object.__setattr__(self, "first_sweeps", bool(self.first_sweeps))
        if self.model not in MODELS:
            raise UnknownModelError(
                f"unknown model {self.model!r}; expected one of {', '.join(MODELS)}"
            )
        _check_range("roughness", self.roughness, 0.0, MAX_ROUGHNESS, "rad")
        if not (math.isfinite(self.solve_scale) and 0.0 < self.solve_scale <= 1.0):
            raise InvalidOptionError(f"solve_scale must be in (0, 1], got {self.solve_scale}")
        if not (math.isfinite(self.tolerance) and self.tolerance > 0.0):
            raise InvalidOptionError(f"tolerance must be > 0, got {self.tolerance}")
        if self.max_iterations < 1:
            raise InvalidOptionError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if self.order not in ORDERS:
            raise InvalidOptionError(f"order must be 1, 2 or 3, got {self.order}")
        _check_range("dark_level", self.dark_level, 0.0, math.inf, "irradiance units")
        if self.saturation is not None and not self.saturation > self.dark_level:
            raise InvalidOptionError(
                f"saturation must exceed dark_level ({self.dark_level}), got {self.saturation}"
            )
        if not self.max_irradiance > self.dark_level:  # also False for NaN
            raise InvalidOptionError(
                f"max_irradiance must exceed dark_level ({self.dark_level}), "
                f"got {self.max_irradiance}"
            )
        if not 0.0 <= self.singular_tolerance < 1.0:  # also False for NaN
            raise InvalidOptionError(
                f"singular_tolerance must be in [0, 1), got {self.singular_tolerance}"
            )
        _check_range("smoothing", self.smoothing, 0.0, math.inf, "pixels")
        if self.threads < 0:
            raise InvalidOptionError(
                f"threads must be >= 1, or 0 (as the solve grid needs), got {self.threads}"
            )
        if not 0 <= self.highlight_downsample <= MAX_HIGHLIGHT_DOWNSAMPLE:
            raise InvalidOptionError(
                f"highlight_downsample must be in [0, {MAX_HIGHLIGHT_DOWNSAMPLE}] "
                f"(0: as the solve grid needs), got {self.highlight_downsample}"
            )

    def solve_threads(self, height: int, width: int) -> int:
        """The threads a solve of an image of ``height`` × ``width`` pixels runs on.

        ``threads`` when set, else 2 when the image at ``solve_scale`` has
        at least :data:`TWO_THREAD_PIXELS` pixels and 1 below.
        """
        if self.threads:
            return self.threads
        nodes = round(height * self.solve_scale) * round(width * self.solve_scale)
        return 2 if nodes >= TWO_THREAD_PIXELS else 1

    def detection_downsample(self, height: int) -> int:
        """The factor by which highlight detection reduces an image of ``height`` rows.

        ``highlight_downsample`` when set, else 2 at ``solve_scale`` ≤
        :data:`HALVED_DETECTION_SCALE` (a node there spans 2 × 2 pixels, so
        finer detection changes no more than the mask's edge: the phantom's
        and the seed-7 colon's AbsRel stay within 0.0003) or when the image
        has at least :data:`HALVED_DETECTION_ROWS` rows (the detection's
        filters are fractions of the height and its baseline grid has 120
        rows either way: at 640×480 and solve_scale 1 the phantom's AbsRel
        0.0788 → 0.0787, the colon seed 2's 0.0919 → 0.0919 with the
        field-of-view mask and 0.0912 → 0.0914 without), else 1.
        """
        if self.highlight_downsample:
            return self.highlight_downsample
        halved = self.solve_scale <= HALVED_DETECTION_SCALE or height >= HALVED_DETECTION_ROWS
        return 2 if halved else 1


@dataclass(frozen=True)
class AgreementBound:
    """How far apart two solves of one frame, stopped at one tolerance, may be.

    Relative depth differences |d₁/d₂ − 1| over the pixels both solved.

    Attributes:
        median: bound on the median over the pixels.
        p999: bound on the 99.9th percentile.
        largest: bound on the largest, at any single pixel.
    """

    median: float
    p999: float
    largest: float


def agreement_bound(tolerance: float = DEFAULT_TOLERANCE) -> AgreementBound:
    """The documented spread of near-light solves stopped at ``tolerance``.

    Two solves of one frame from different starts (warm or cold, one or two
    threads, another worker's chain) reach the same fixed point only to the
    stopping tolerance τ: the sweeps stop when no node changed ln r by more
    than τ in an iteration, and a node is solved again only when an upwind
    neighbour changed by more than τ, so each node may lag the last sub-τ
    changes of its stencil, and the upwind scheme carries such lags down
    the characteristics (monotone: carried, not amplified). Beside singular
    points (surface facing the light, slope ~0) the node equation is
    quadratic in the slope, so a residual τ there moves the slope by ~√τ:
    rare single pixels differ by several √τ, more the more pixels are
    compared. Measured (docs/sfs.md, "Speed", session 14) on the phantom, a
    held-out render and noisy synthetic frames at τ = 1e-5 … 3e-4: median
    ≤ 0.24·τ, 99.9th percentile ≤ 11·τ (20·τ in an earlier measurement at
    1e-5), largest ≤ 5.8·√τ over the phantom's 90 frames (13.9 M pixels;
    7.5·√τ at 3e-4, full resolution). The bound is that worst case with
    room: :data:`AGREEMENT_MEDIAN`·τ, :data:`AGREEMENT_P999`·τ and
    :data:`AGREEMENT_LARGEST`·√τ, each plus two float32 spacings (the
    depth's rounding: at τ = 1e-9 the 99.9th percentile was 1.2e-7). It is
    an envelope of measurements, not a derivation, so it is given only
    within :data:`AGREEMENT_TOLERANCES`: beyond 1e-3 the spread grows faster
    than these terms (median 0.7·τ at 1e-2).

    Args:
        tolerance: the sweeps' stopping tolerance τ in ln r, within
            :data:`AGREEMENT_TOLERANCES`.

    Returns:
        The bounds on the median, 99.9th percentile and largest relative
        depth difference (dimensionless).

    Raises:
        InvalidOptionError: ``tolerance`` outside :data:`AGREEMENT_TOLERANCES`.
    """
    low, high = AGREEMENT_TOLERANCES
    if not low <= tolerance <= high:  # also False for NaN
        raise InvalidOptionError(
            f"agreement_bound is measured for tolerances in [{low:g}, {high:g}], got {tolerance}"
        )
    rounding = 2.0 * FLOAT32_SPACING
    return AgreementBound(AGREEMENT_MEDIAN * tolerance + rounding,
                          AGREEMENT_P999 * tolerance + rounding,
                          AGREEMENT_LARGEST * math.sqrt(tolerance) + rounding)


_FLOATS = ("roughness", "solve_scale", "tolerance", "dark_level", "max_irradiance",
           "singular_tolerance", "smoothing")
_INTEGERS = ("max_iterations", "order", "threads", "highlight_downsample")


def _coerce(options: SfsOptions, name: str, kind: type[float] | type[int]) -> None:
    """Set ``options.name`` to its plain float or int; a bool or a float for an int is refused."""
    value = getattr(options, name)
    converted: float | int
    try:
        if isinstance(value, bool):
            raise TypeError(name)
        converted = operator.index(value) if kind is int else float(value)
    except (TypeError, ValueError):
        what = "an integer" if kind is int else "a number"
        raise InvalidOptionError(f"{name} must be {what}, got {value!r}") from None
    object.__setattr__(options, name, converted)


def _check_range(name: str, value: float, low: float, high: float, unit: str) -> None:
    if not low <= value <= high:  # also False for NaN
        bound = f">= {low:g}" if math.isinf(high) else f"in [{low:g}, {high:g}]"
        raise InvalidOptionError(f"{name} must be {bound} {unit}, got {value}")
