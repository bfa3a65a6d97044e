"""Specular highlights: find them so that shape from shading can ignore them.

Wet mucosa under a light at the optical centre reflects a white specular lobe
where the surface faces the camera. The lobe comes from the air/mucus
interface, so it is not scaled by the (textured) albedo and is no part of the
diffuse reflectance the SFS models invert: read as diffuse shading, a
highlight is a surface patch far too close, and the near-light solution
carries that error into its surroundings. Endoscopic SFS pipelines therefore
detect highlights and give those pixels no data term; the PDE continues the
surface around them from the surrounding diffuse data (the hole's edge is a
state constraint, see :mod:`endo_sfs.near_light`).

Detection, on the linear irradiance (the output of ``endo_calib``):

1. **Saturated pixels**: NaN inside ``mask`` (``endo_calib`` marks saturated
   pixels NaN), values at or above ``saturation``, and, without a mask, NaN
   holes enclosed by finite pixels. They are grown by a small margin
   (the last codes below saturation are compressed by the response).
2. **A diffuse baseline** of ln I, on a grid about 120 rows high:
   a grey-scale *closing* (radius ``closing_radius``, a fraction of the image
   height) bridges the dark gaps between fold ridges and vessels, then an
   *opening* (``opening_radius``) removes bright blobs narrower than its
   disc. Highlights are such blobs; diffuse shading, after the closing, is
   broader. Saturated cells count as very bright; cells outside the data take
   no part (neither erode nor dilate), so a highlight at the edge of the
   field of view is measured against the data beside it.
3. **Excess** e = ln I (Gaussian σ = 1.5 px) − baseline. Pixels with
   e > ``core_excess`` or saturated are highlight cores; an excess core
   needs a baseline with support, i.e. at least ``min_support`` of the
   opening's disc on data. Without that rule the bright band of a wall close
   to the camera along the edge of the field of view reads as a highlight
   (the opening, cut by the edge, removes it), and masking it makes the
   remaining wall's nearest points unseen, which costs more than the band.
   The lobe's shoulders (where it is still a large fraction of the diffuse
   light but no longer stands out from the texture) are taken by
   hysteresis: every connected region of e > ``shoulder_excess`` that
   contains a core. A lobe as wide as the opening's disc lifts the
   baseline under its own peak, which may then stand less than
   ``core_excess`` above it: a second baseline, opened by a disc twice as
   wide on a grid half as fine, finds those cores (:func:`_broad_excess`).
4. **Shoulder growth** of the lobes as wide as the opening's disc. The lobe
   k·c^m (c = cos θ, θ the angle between the normal and the ray) falls as
   e^(−mθ²/2): its ratio to the diffuse light, q(θ) = q₀·e^(−mθ²/2), is a
   Gaussian in θ, and so, where θ grows about linearly with the distance
   from the lobe's centre in the image, in that distance too. A region
   whose edge is at q = q_e covers the lobe down to q = τ once its radius
   is multiplied by √(ln(q₀/τ) / ln(q₀/q_e)). A lobe about as wide as the
   opening's disc is not removed by the opening, the baseline rises under
   it, and the excess test ends its region at q_e ≈ 1.5, where the lobe
   still outshines the texture and SFS reads it as surface facing the
   camera and near (on the textured abdomen that was most of the error;
   docs/sfs.md, "Specular shoulders and broad lobes"). The peak ratio of
   wet tissue (k = 2 on albedo 0.4: q₀ ≈ 5) gives 1.64 for τ = 0.2 and 1.84 for τ = 0.1: the
   factor depends on the ratios only, not on the surface's distance or
   curvature, which set the lobe's size in the image. So such a region is
   grown by (``shoulder_growth`` − 1) times its inradius (its largest
   distance from a pixel to its edge: across an elongated region, not
   along it). The growth ramps in over inradii of :data:`WIDE_LOBE` opening
   radii (narrower lobes go with their shoulders in the opening, and the
   excess test finds those), and a region that touches the edge of the
   view does not grow (in the colon that is the near wall, saturated by
   diffuse light alone, whose nearest seen points the solution needs).

The defaults of steps 1–3 were chosen on endo_sim's colon phantom (specular
2·c^120 on albedo 0.4, σ = 0.3) against the true specular fraction, the
growth on the textured abdomen (seed 3); see docs/sfs.md for the figures
and the limits.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numba import njit, prange

from endo_sfs.errors import SfsInputError
from endo_sfs.second_thread import beside, numba_single_threaded

#: Rows of the grid on which the morphological baseline is computed.
BASELINE_ROWS = 120
#: Default radii of the baseline filters, as fractions of the image height.
DEFAULT_OPENING_RADIUS = 0.15
DEFAULT_CLOSING_RADIUS = 0.025
#: Default thresholds on the excess of ln I over the diffuse baseline.
DEFAULT_CORE_EXCESS = 0.9
DEFAULT_SHOULDER_EXCESS = 0.3
#: Smallest fraction of the opening's disc that must hold data for the
#: excess to be measured (about 0.4 radii from a straight edge of the data).
DEFAULT_MIN_SUPPORT = 0.85
#: Default radius of the second, broader opening (fraction of the image height).
DEFAULT_BROAD_OPENING_RADIUS = 0.3
#: Default factor by which a wide highlight region's inradius is grown (step 4).
DEFAULT_SHOULDER_GROWTH = 2.0
#: Inradii (fractions of the opening's radius) over which the growth ramps
#: from none to full: narrower regions' shoulders were found by the excess test.
WIDE_LOBE = (0.55, 0.75)
#: Gaussian σ (pixels) of ln I before it is compared with the baseline.
FINE_SIGMA = 1.5
#: Stand-in for ±∞ in the float32 morphology (cells that take no part).
_NO_PART = np.float32(1e30)


def filled(inside: np.ndarray) -> np.ndarray:
    """``inside`` with its holes filled: ``scipy.ndimage.binary_fill_holes``, by OpenCV.

    A hole is a connected region (4-connected, as scipy's default structure)
    of pixels outside ``inside`` that does not touch the image border.
    inside: (H, W) bool. Returns (H, W) bool. The outside reached from the
    border is flood-filled (``cv2.floodFill``, 4-connected) once, from a
    corner of a one-pixel frame of outside pixels around the image: the
    frame joins every run of outside pixels along the edges. ~0.14 ms at
    640×480 (one fill from a seed per run along the edges: ~0.21; labelling
    every component: ~0.7).
    """
    inside = np.asarray(inside, dtype=bool)
    if inside.size == 0:
        return np.ones(inside.shape, dtype=bool)
    height, width = inside.shape
    outside = np.ones((height + 2, width + 2), dtype=np.uint8)  # 1 outside, 0 inside
    np.logical_not(inside, out=outside[1:-1, 1:-1].view(bool))
    cv2.floodFill(outside, None, (0, 0), 2, flags=4)
    return np.asarray(outside[1:-1, 1:-1] != 2)


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


#: From this radius on the baseline's erosions and dilations run in numba
#: (:func:`_disc_minimum`); OpenCV is faster below.
_NUMBA_DISC_RADIUS = 8


@functools.lru_cache(maxsize=32)
def _disc_half_widths(radius: int) -> np.ndarray:
    """(2·radius + 1,) int64: row k of :func:`_disc` spans columns radius ± half_widths[k].

    OpenCV's ellipse is symmetric and each of its rows one run, which is what
    lets the disc filters work row by row.
    """
    widths = []
    for row in _disc(radius):
        columns = np.flatnonzero(row)
        left, right = int(columns[0]), int(columns[-1])
        if right - left + 1 != columns.size or left + right != 2 * radius:
            raise AssertionError(f"the disc of radius {radius} is not symmetric runs")
        widths.append(radius - left)
    return np.array(widths, dtype=np.int64)


@njit(cache=True, nogil=True, error_model="numpy")
def _disc_minimum(values: np.ndarray, half_widths: np.ndarray) -> np.ndarray:
    """``cv2.erode(values, _disc(radius))`` on float32, the same values, ~2× faster for r ≥ 8.

    values: (H, W) float32; half_widths: :func:`_disc_half_widths`. Cells
    beyond the grid take no part (OpenCV's default border for erosion). The
    minimum over a row's run of width 2w + 1 is the smaller of two
    overlapping power-of-two windows of a sparse table (the row padded with
    +∞), one per distinct w; the disc's minimum is the smallest of those
    over its 2·radius + 1 rows. Only comparisons: no rounding.
    """
    rows, columns = values.shape
    radius = (half_widths.shape[0] - 1) // 2
    widest = 0
    for w in half_widths:
        widest = max(widest, w)
    padded = columns + 2 * widest
    levels = 1
    while (1 << levels) <= 2 * widest + 1:
        levels += 1
    infinity = np.float32(np.inf)
    table = np.full((levels, rows, padded), infinity, dtype=np.float32)
    for y in range(rows):
        for x in range(columns):
            table[0, y, x + widest] = values[y, x]
    for k in range(1, levels):
        step = 1 << (k - 1)
        for y in range(rows):
            for i in range(padded - step):
                a = table[k - 1, y, i]
                b = table[k - 1, y, i + step]
                table[k, y, i] = a if a < b else b
    runs = np.empty((widest + 1, rows, columns), dtype=np.float32)
    done = np.zeros(widest + 1, dtype=np.bool_)
    for w in half_widths:
        if done[w]:
            continue
        done[w] = True
        level = 0
        while (1 << (level + 1)) <= 2 * w + 1:
            level += 1
        second = w - (1 << level) + 1  # the right window's start, relative to x
        for y in range(rows):
            for x in range(columns):
                a = table[level, y, x + widest - w]
                b = table[level, y, x + widest + second]
                runs[w, y, x] = a if a < b else b
    out = np.full((rows, columns), infinity, dtype=np.float32)
    for y in range(rows):
        for d in range(max(-radius, -y), min(radius, rows - 1 - y) + 1):
            w = half_widths[d + radius]
            for x in range(columns):
                a = out[y, x]
                b = runs[w, y + d, x]
                out[y, x] = a if a < b else b
    return out


def _disc_fraction(part: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) float32 share of each cell's disc of ``radius`` inside ``part`` ((H, W) bool)."""
    disc = _disc(radius).astype(np.float32)
    return cv2.filter2D(part.astype(np.float32), -1, disc / disc.sum(),
                        borderType=cv2.BORDER_CONSTANT)  # fmt: skip


@njit(cache=True, nogil=True, error_model="numpy")
def _masked_disc_minimum(
    values: np.ndarray, part: np.ndarray, half_widths: np.ndarray, sign: np.float32
) -> np.ndarray:
    """:func:`_erode` (sign 1) or :func:`_dilate` (sign −1) of float32 ``values`` for r ≥ 8.

    values: (H, W) float32; part: (H, W) bool. The minimum of sign·value over
    the disc's cells in ``part`` (:func:`_disc_minimum`), times sign, where
    ``part``; ``values`` elsewhere: the same float32 values as the numpy
    selections around :func:`_disc_minimum`, in two passes instead of four.
    """
    rows, columns = values.shape
    taking_part = np.empty((rows, columns), dtype=np.float32)
    for y in range(rows):
        for x in range(columns):
            taking_part[y, x] = sign * values[y, x] if part[y, x] else _NO_PART
    out = _disc_minimum(taking_part, half_widths)
    for y in range(rows):
        for x in range(columns):
            out[y, x] = sign * out[y, x] if part[y, x] else values[y, x]
    return out


def _erode(values: np.ndarray, part: np.ndarray, radius: int) -> np.ndarray:
    """Minimum over a disc of the cells in ``part`` (others neither count nor change)."""
    if radius >= _NUMBA_DISC_RADIUS and values.dtype == np.float32:
        return _masked_disc_minimum(np.ascontiguousarray(values), np.ascontiguousarray(part),
                                    _disc_half_widths(radius), np.float32(1.0))  # fmt: skip
    outside = np.where(part, values, _NO_PART).astype(np.float32)
    if radius >= _NUMBA_DISC_RADIUS:
        out = _disc_minimum(outside, _disc_half_widths(radius))
    else:
        out = cv2.erode(outside, _disc(radius))
    return np.where(part, out, values).astype(np.float32)


def _dilate(values: np.ndarray, part: np.ndarray, radius: int) -> np.ndarray:
    """Maximum over a disc of the cells in ``part`` (others neither count nor change)."""
    if radius >= _NUMBA_DISC_RADIUS and values.dtype == np.float32:
        return _masked_disc_minimum(np.ascontiguousarray(values), np.ascontiguousarray(part),
                                    _disc_half_widths(radius), np.float32(-1.0))  # fmt: skip
    if radius >= _NUMBA_DISC_RADIUS:  # the maximum is minus the minimum of the negated values
        negated = np.where(part, -values, _NO_PART).astype(np.float32)
        out = -_disc_minimum(negated, _disc_half_widths(radius))
    else:
        out = cv2.dilate(np.where(part, values, -_NO_PART).astype(np.float32), _disc(radius))
    return np.where(part, out, values).astype(np.float32)


def _normalised_blur(values: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
    num = cv2.GaussianBlur(values * weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    return num / np.maximum(den, np.float32(1e-6))


def diffuse_excess(
    irradiance: np.ndarray,
    data: np.ndarray,
    saturated: np.ndarray,
    opening_radius: float = DEFAULT_OPENING_RADIUS,
    closing_radius: float = DEFAULT_CLOSING_RADIUS,
    min_support: float = DEFAULT_MIN_SUPPORT,
    fine_sigma: float = FINE_SIGMA,
    broad_opening_radius: float = DEFAULT_BROAD_OPENING_RADIUS,
    *,
    threads: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """ln I minus its morphological diffuse baseline (step 2–3 of the module docstring).

    irradiance: (H, W) float linear irradiance; data: (H, W) bool pixels with
    a finite, positive value; saturated: (H, W) bool. opening_radius,
    closing_radius, broad_opening_radius: fractions of H. min_support: see
    :data:`DEFAULT_MIN_SUPPORT`. threads: 2 or more computes the baseline's
    support, the fine blur and the broad excess on a second thread while
    this one closes and opens the baseline (two independent halves of about
    equal cost; the same values). Returns ((H, W) float32 excess in ln units,
    0 where not ``data``; (H, W) bool pixels whose baseline has that support;
    (h, w) float32 broad excess of :func:`_broad_excess`, one value per block
    of b × b pixels; b).
    """
    height, width = irradiance.shape
    weighted_log, weight = _log_and_weight(np.ascontiguousarray(irradiance), data)
    factor = max(1, round(height / BASELINE_ROWS))
    size = (max(1, width // factor), max(1, height // factor))
    cell_weight = cv2.resize(weight, size, interpolation=cv2.INTER_AREA)
    cell_log = cv2.resize(weighted_log, size, interpolation=cv2.INTER_AREA)
    has_data = cell_weight > 0.5
    cell_log = np.where(has_data, cell_log / np.maximum(cell_weight, 1e-6), 0.0)
    cell_saturated = (
        cv2.resize(saturated.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5
    ) & ~has_data
    if not has_data.any():
        nothing = np.zeros((height, width), dtype=np.float32)
        return nothing, np.zeros((height, width), bool), np.zeros((1, 1), np.float32), 1
    cell_log[cell_saturated] = cell_log[has_data].max()
    part = has_data | cell_saturated
    rows = height / factor
    closing = max(1, round(closing_radius * rows))
    opening = max(1, round(opening_radius * rows))

    def the_rest() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        # Where the opening's disc leaves the data, the baseline has too little
        # support to tell a highlight from a bright band along the edge.
        support = _disc_fraction(part, opening)
        support = cv2.resize(support, (width, height), interpolation=cv2.INTER_LINEAR)
        # The fine image is the normalised blur of ln I over the data.
        blurred_log = cv2.GaussianBlur(weighted_log, (0, 0), fine_sigma,
                                       borderType=cv2.BORDER_CONSTANT)  # fmt: skip
        blurred_weight = cv2.GaussianBlur(weight, (0, 0), fine_sigma,
                                          borderType=cv2.BORDER_CONSTANT)  # fmt: skip
        broad = _broad_excess(cell_log, has_data, part, closing_radius, broad_opening_radius,
                              min_support)  # fmt: skip
        return support, blurred_log, blurred_weight, broad

    started = beside(the_rest) if threads > 1 else None
    closed = _erode(_dilate(cell_log, part, closing), part, closing)
    baseline = _dilate(_erode(closed, part, opening), part, opening)
    baseline = _normalised_blur(baseline, part.astype(np.float32), 1.0)
    baseline = cv2.resize(baseline, (width, height), interpolation=cv2.INTER_LINEAR)
    support, blurred_log, blurred_weight, broad = (
        the_rest() if started is None else started.result()
    )
    excess, supported = _excess(blurred_log, blurred_weight, baseline, support, data,
                                np.float32(min_support))  # fmt: skip
    return excess, supported, broad, 2 * factor


def _broad_excess(
    cell_log: np.ndarray, has_data: np.ndarray, part: np.ndarray, closing_radius: float,
    opening_radius: float, min_support: float,
) -> np.ndarray:
    """The excess of block means of ln I over a baseline opened by a disc twice as wide.

    A lobe about as wide as the opening's disc is not removed by the
    opening: the baseline rises under its peak too, which then stands less
    than ``core_excess`` above it and no core is found (the textured
    abdomen's wall facing the scope). Against an opening of
    ``opening_radius`` (0.3 H), on a grid half as fine as the baseline's
    (the same cost), its peak stands out again. cell_log, has_data, part:
    the baseline grid's mean ln I, cells with data, cells taking part. Returns
    the (h // 2, w // 2) float32 excess of the blocks of 2 × 2 cells with
    data and support ≥ ``min_support``, 0 elsewhere.
    """
    rows, columns = cell_log.shape[0] // 2, cell_log.shape[1] // 2
    if rows < 1 or columns < 1:
        return np.zeros((max(rows, 1), max(columns, 1)), dtype=np.float32)
    size = (columns, rows)
    weight = cv2.resize(part.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    logs = cv2.resize(np.where(part, cell_log, 0.0).astype(np.float32), size,
                      interpolation=cv2.INTER_AREA)  # fmt: skip
    takes_part = weight > 0.5
    logs = np.where(takes_part, logs / np.maximum(weight, 1e-6), 0.0).astype(np.float32)
    closing = max(1, round(closing_radius * rows))
    opening = max(1, round(opening_radius * rows))
    closed = _erode(_dilate(logs, takes_part, closing), takes_part, closing)
    baseline = _dilate(_erode(closed, takes_part, opening), takes_part, opening)
    support = _disc_fraction(takes_part, opening)
    with_data = cv2.resize(has_data.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5
    return np.where(with_data & (support >= min_support), logs - baseline, 0.0).astype(
        np.float32)


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _log_and_weight(irradiance: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ln I where ``data`` else 0, ``data`` as 0/1), both (H, W) float32, in one pass."""
    height, width = irradiance.shape
    weighted_log = np.zeros((height, width), dtype=np.float32)
    weight = np.zeros((height, width), dtype=np.float32)
    for r in prange(height):
        for c in range(width):
            if data[r, c]:
                weighted_log[r, c] = np.log(np.float32(irradiance[r, c]))
                weight[r, c] = 1.0
    return weighted_log, weight


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _excess(
    blurred_log: np.ndarray,
    blurred_weight: np.ndarray,
    baseline: np.ndarray,
    support: np.ndarray,
    data: np.ndarray,
    min_support: np.float32,
) -> tuple[np.ndarray, np.ndarray]:
    """The excess of the fine ln I over the baseline, and where the baseline has support.

    fine = blurred_log / max(blurred_weight, 1e-6) (the normalised blur);
    all (H, W) float32 but ``data`` (bool). Returns ((H, W) float32 excess,
    0 outside ``data``; (H, W) bool data pixels with support ≥ min_support).
    """
    height, width = data.shape
    excess = np.zeros((height, width), dtype=np.float32)
    supported = np.zeros((height, width), dtype=np.bool_)
    floor = np.float32(1e-6)
    for r in prange(height):
        for c in range(width):
            if data[r, c]:
                fine = blurred_log[r, c] / max(blurred_weight[r, c], floor)
                excess[r, c] = fine - baseline[r, c]
                supported[r, c] = support[r, c] >= min_support
    return excess, supported


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def block_means(
    image: np.ndarray, region: np.ndarray, saturation: float, factor: int
) -> tuple[np.ndarray, np.ndarray]:
    """``image`` reduced by ``factor`` in both directions, for detection on fewer pixels.

    image: (H, W) float; region: (H, W) bool; saturation: values at or
    above it are saturated (inf: none). A block of factor × factor pixels
    (the last row and column of blocks may be partial) is in the small
    region when at least half of its pixels are in ``region``. Its value is
    NaN (saturated) when any of its region pixels is NaN or saturated,
    else the geometric mean of its region pixels that are > 0 (0 when there
    are none: dark, not saturated): the detection works on ln I, and the
    mean of ln I is what the full image's baseline grid averages too (the
    arithmetic mean moved the phantom's AbsRel at solve_scale 0.5 from
    0.0797 to 0.0802, the geometric one leaves it there). Returns ((h, w) float32, (h, w) bool) with
    h = ceil(H / factor), w = ceil(W / factor).
    """
    height, width = image.shape
    rows = (height + factor - 1) // factor
    columns = (width + factor - 1) // factor
    small = np.zeros((rows, columns), dtype=np.float32)
    inside = np.zeros((rows, columns), dtype=np.bool_)
    for r in prange(rows):
        for c in range(columns):
            # ln of the product, one logarithm per block (not per pixel); the
            # product is folded into the sum before it could leave float64's range
            product = 1.0
            total = 0.0
            count = 0
            in_region = 0
            pixels = 0
            saturated = False
            for y in range(r * factor, min((r + 1) * factor, height)):
                for x in range(c * factor, min((c + 1) * factor, width)):
                    pixels += 1
                    if not region[y, x]:
                        continue
                    in_region += 1
                    value = image[y, x]
                    if not (value < saturation):  # NaN or saturated
                        saturated = True
                    elif value > 0.0:
                        product *= value
                        count += 1
                        if not 1e-100 < product < 1e100:
                            total += np.log(product)
                            product = 1.0
            inside[r, c] = 2 * in_region >= pixels
            if saturated:
                small[r, c] = np.nan
            elif count > 0:
                small[r, c] = np.exp((total + np.log(product)) / count)
    return small, inside


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _halved(
    image: np.ndarray, region: np.ndarray, saturation: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`block_means` for factor 2 on a float32 image of even size, without branches.

    A product of four float32 values cannot leave float64's range, so no
    range check; the mean of four (two, one) values is the fourth (square)
    root of their product in float64, rounded to float32: the same float32
    values as exp(ln(product)/count) on every block of the 90 phantom frames
    (a float64 difference of ~1e-16 changes the float32 rounding only at a
    tie), at ~0.4 of the time of a logarithm and an exponential per block.
    """
    rows, columns = image.shape[0] // 2, image.shape[1] // 2
    small = np.zeros((rows, columns), dtype=np.float32)
    inside = np.zeros((rows, columns), dtype=np.bool_)
    for r in prange(rows):
        for c in range(columns):
            product = 1.0
            count = 0
            in_region = 0
            saturated = 0
            for y in range(2 * r, 2 * r + 2):
                for x in range(2 * c, 2 * c + 2):
                    value = np.float64(image[y, x])
                    taken = bool(region[y, x])
                    below = value < saturation
                    good = taken and below and value > 0.0
                    in_region += 1 if taken else 0
                    saturated += 1 if taken and not below else 0  # NaN or saturated
                    count += 1 if good else 0
                    product *= value if good else 1.0
            inside[r, c] = in_region >= 2
            if saturated:
                small[r, c] = np.nan
            elif count == 4:  # the usual block: two square roots, no log and exp
                small[r, c] = np.sqrt(np.sqrt(product))
            elif count == 2:
                small[r, c] = np.sqrt(product)
            elif count == 1:
                small[r, c] = product
            elif count > 0:
                small[r, c] = np.exp(np.log(product) / count)
    return small, inside


def _any_in_blocks(flags: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(size[1], size[0]) uint8: 1 where any pixel of the block (cv2 INTER_AREA's) is set."""
    return (cv2.resize(flags.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.0
            ).astype(np.uint8)  # fmt: skip


def _growth_cells(
    found: np.ndarray, height: int, width: int, downsample: int
) -> np.ndarray | None:
    """:func:`grown_regions`' cells of an (H, W) answer from the reduced image's answer.

    found: (h, w) bool, the answer on the image reduced by ``downsample``,
    inside the reduced region. Each of its blocks holds at least one pixel
    of the full region (half of its pixels, :func:`block_means`), so a cell
    of the grid holds a pixel of the full answer (``found`` upsampled, within
    the region) exactly when it holds a block of ``found``: the same cells
    from ``downsample``² times fewer pixels. None when the grid's cells are
    not whole blocks (then :func:`grown_regions` takes them from the pixels).
    """
    factor = max(1, round(height / BASELINE_ROWS))
    if factor % downsample or height % factor or width % factor or found.shape != (
        height // downsample, width // downsample
    ):
        return None
    return _any_in_blocks(found, (width // factor, height // factor))


def grown_regions(
    found: np.ndarray, region: np.ndarray, growth: float,
    opening_radius: float = DEFAULT_OPENING_RADIUS, *, cells: np.ndarray | None = None,
) -> np.ndarray:
    """The wide regions of ``found`` grown by (growth − 1) × their inradius (step 4 above).

    found, region: (H, W) bool; growth ≥ 1 (1: ``found`` unchanged);
    opening_radius: the baseline's, a fraction of H. The regions, their
    inradii and the distances are taken on a grid about
    :data:`BASELINE_ROWS` rows high (a cell is in a region when any of its
    pixels is); a region grows fully when its inradius is at least
    ``WIDE_LOBE[1]`` opening radii, not at all below ``WIDE_LOBE[0]`` or
    when it touches a cell with a pixel outside ``region``. Each cell gets
    the margin of its nearest region, and the margin minus the distance is
    interpolated back to the pixels, so the grown edge is smooth. cells:
    the grid's cells that hold a pixel of ``found`` ((h, w) uint8, 0 or 1),
    if the caller has them (:func:`detect_highlights` takes them from the
    reduced image's answer); computed from ``found`` otherwise. Returns
    (H, W) bool: ``found`` and the grown margins, inside ``region``.
    """
    if growth <= 1.0 or not found.any():
        return found
    height, width = found.shape
    factor = max(1, round(height / BASELINE_ROWS))
    size = (max(1, -(-width // factor)), max(1, -(-height // factor)))
    if cells is None:
        cells = _any_in_blocks(found, size)
    elif cells.shape != (size[1], size[0]):
        raise SfsInputError(f"cells have shape {cells.shape}, expected {(size[1], size[0])}")
    # the inradius: the largest distance from a region cell to the outside
    depth = cv2.distanceTransform(cells, cv2.DIST_L2, 5)
    # Only lobes about as wide as the opening's disc lift the baseline.
    opening = max(1.0, opening_radius * cells.shape[0])
    low, high = WIDE_LOBE
    if float(depth.max()) <= low * opening:
        return found  # no region is wide enough (the usual case in the colon)
    count, labels = cv2.connectedComponents(cells, connectivity=8)
    inside = cells.astype(bool)
    radius = np.zeros(count, dtype=np.float64)
    np.maximum.at(radius, labels[inside], depth[inside])
    share = np.clip((radius / opening - low) / (high - low), 0.0, 1.0)
    share[0] = 0.0
    if not np.any(share > 0.0):
        return found
    # A region cut by the edge of the view (or of the data) does not grow.
    unseen = _any_in_blocks(~np.asarray(region, dtype=bool), size)
    edge = cv2.dilate(unseen, np.ones((3, 3), np.uint8)).astype(bool) & inside
    share[labels[edge]] = 0.0
    margin = (growth - 1.0) * radius * share
    if not np.any(margin > 0.0):
        return found
    # distance (in cells) to the nearest region cell, and which zero-component that is
    distance, nearest = cv2.distanceTransformWithLabels(
        1 - cells, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_CCOMP
    )
    component = np.zeros(int(nearest.max()) + 1, dtype=np.int64)
    component[nearest[inside]] = labels[inside]
    grows = margin[component[nearest]]
    if not np.any(grows > 0.0):
        return found
    # cells near a region that does not grow stay out (-1), as do those beyond the margin
    reach = np.where(grows > 0.0, grows - distance, -1.0).astype(np.float32)
    # cell centres to pixel centres: the grid covers the padded image
    pixels = cv2.resize(reach, (size[0] * factor, size[1] * factor),
                        interpolation=cv2.INTER_LINEAR)[:height, :width]  # fmt: skip
    return np.asarray((found | (pixels >= 0.0)) & region, dtype=bool)


def detect_highlights(
    irradiance: np.ndarray,
    mask: np.ndarray | None = None,
    saturation: float | None = None,
    core_excess: float = DEFAULT_CORE_EXCESS,
    shoulder_excess: float = DEFAULT_SHOULDER_EXCESS,
    opening_radius: float = DEFAULT_OPENING_RADIUS,
    closing_radius: float = DEFAULT_CLOSING_RADIUS,
    min_support: float = DEFAULT_MIN_SUPPORT,
    *,
    downsample: int = 1,
    shoulder_growth: float = DEFAULT_SHOULDER_GROWTH,
    threads: int = 1,
) -> np.ndarray:
    """Pixels of specular highlights (saturated or not) and their shoulders.

    Args:
        irradiance: (H, W) float linear irradiance (any scale; NaN marks
            saturated or unseen pixels, as ``endo_calib`` writes them).
        mask: optional (H, W) bool region of interest (the circular field of
            view). NaN inside it counts as saturated; without it only NaN
            holes enclosed by finite pixels do.
        saturation: irradiance at or above which a pixel is saturated, or None.
        core_excess: ln-excess over the diffuse baseline that makes a
            highlight core (0.9: the pixel is 2.5× brighter than the
            baseline).
        shoulder_excess: ln-excess down to which a core's connected region
            is included (0.3: 1.35×), 0 < shoulder_excess ≤ core_excess.
        opening_radius, closing_radius: baseline filter radii, fractions of
            the image height (> 0).
        min_support: fraction of the opening's disc that must hold data
            for an excess core (see the module docstring).
        downsample: detect on the image reduced by this factor
            (:func:`block_means`: a block with a saturated pixel is
            saturated) and give each pixel its block's answer. The filters'
            radii are fractions of the height, so the result is the same
            detection on a coarser grid; a solve on a coarser grid
            (``solve_scale`` 0.5) cannot use finer detail anyway.
        shoulder_growth: a highlight region as wide as the opening's disc
            has its inradius multiplied by this, ≥ 1 (1: no growth), to take
            the lobe's broad shoulders (step 4 of the module docstring,
            :func:`grown_regions`).
        threads: 1 runs on the calling thread (numba's kernels on as many
            threads as the caller set); 2 or more runs half of the baseline's
            work on a second thread (:func:`diffuse_excess`,
            :mod:`endo_sfs.second_thread`) and every numba kernel on one
            thread: 0.71–0.80 of the time of numba's two-thread kernels on
            the phantom at 320×240. The same answer either way.

    Returns:
        (H, W) bool, True on highlight pixels (inside ``mask`` if given).

    Raises:
        SfsInputError: bad shapes or thresholds.
    """
    image = np.asarray(irradiance)
    if image.ndim != 2:
        raise SfsInputError(f"irradiance must be (H, W), got shape {image.shape}")
    if mask is not None and np.shape(mask) != image.shape:
        raise SfsInputError(f"mask has shape {np.shape(mask)}, expected {image.shape}")
    if not 0.0 < shoulder_excess <= core_excess:
        raise SfsInputError(
            f"need 0 < shoulder_excess <= core_excess, got {shoulder_excess}, {core_excess}"
        )
    if not (opening_radius > 0.0 and closing_radius > 0.0):
        raise SfsInputError("opening_radius and closing_radius must be > 0")
    if downsample < 1:
        raise SfsInputError(f"downsample must be >= 1, got {downsample}")
    if not shoulder_growth >= 1.0:  # also refuses NaN
        raise SfsInputError(f"shoulder_growth must be >= 1, got {shoulder_growth}")
    if threads < 1:
        raise SfsInputError(f"threads must be >= 1, got {threads}")
    if threads > 1:
        with numba_single_threaded():
            return _detect_highlights(image, mask, saturation, core_excess, shoulder_excess,
                                      opening_radius, closing_radius, min_support, downsample,
                                      shoulder_growth, threads)  # fmt: skip
    return _detect_highlights(image, mask, saturation, core_excess, shoulder_excess,
                              opening_radius, closing_radius, min_support, downsample,
                              shoulder_growth, threads)  # fmt: skip


def _detect_highlights(
    image: np.ndarray, mask: np.ndarray | None, saturation: float | None, core_excess: float,
    shoulder_excess: float, opening_radius: float, closing_radius: float, min_support: float,
    downsample: int, shoulder_growth: float, threads: int,
) -> np.ndarray:
    """:func:`detect_highlights` on checked arguments."""
    region = np.ones(image.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if downsample > 1:
        if mask is None:
            # NaN holes enclosed by data are saturated: the same as a mask around them.
            region = filled(np.isfinite(image))
        pixels = image if image.dtype in (np.float32, np.float64) else image.astype(np.float64)
        pixels, region = np.ascontiguousarray(pixels), np.ascontiguousarray(region)
        level = np.inf if saturation is None else float(saturation)
        if downsample == 2 and pixels.dtype == np.float32 and not (
            pixels.shape[0] % 2 or pixels.shape[1] % 2
        ):
            small, small_region = _halved(pixels, region, level)
        else:
            small, small_region = block_means(pixels, region, level, downsample)
        found = _detect(
            small, small_region, None, core_excess, shoulder_excess, opening_radius,
            closing_radius, min_support, FINE_SIGMA / downsample, threads=threads,
        )
        height, width = image.shape
        # each pixel its block's answer (nearest neighbour at an integer factor)
        full = cv2.resize(found.view(np.uint8), (found.shape[1] * downsample,
                          found.shape[0] * downsample), interpolation=cv2.INTER_NEAREST)
        return grown_regions(full[:height, :width].view(bool) & region, region, shoulder_growth,
                             opening_radius, cells=_growth_cells(found, height, width, downsample))
    enclosed = None
    if mask is None:
        region = enclosed = filled(np.isfinite(image))  # the data and the NaN holes it encloses
    found = _detect(
        image, mask, saturation, core_excess, shoulder_excess, opening_radius, closing_radius,
        min_support, FINE_SIGMA, enclosed, threads=threads,
    )
    return grown_regions(found, region, shoulder_growth, opening_radius)


def _detect(
    image: np.ndarray,
    mask: np.ndarray | None,
    saturation: float | None,
    core_excess: float,
    shoulder_excess: float,
    opening_radius: float,
    closing_radius: float,
    min_support: float,
    fine_sigma: float,
    enclosed: np.ndarray | None = None,
    *,
    threads: int = 1,
) -> np.ndarray:
    """:func:`detect_highlights` on checked arguments, at the image's own resolution.

    enclosed: without a mask, ``filled(np.isfinite(image))`` if the caller
    has it already (computed here otherwise). threads: :func:`diffuse_excess`'s.
    """
    region = np.ones(image.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    region = np.ascontiguousarray(region)
    saturated, data = _classify(
        np.ascontiguousarray(image), region, np.inf if saturation is None else float(saturation)
    )
    if mask is None:
        saturated &= filled(np.isfinite(image)) if enclosed is None else enclosed
    if saturated.any():
        margin = max(1, round(image.shape[0] / 240))
        saturated = cv2.dilate(saturated.astype(np.uint8), _disc(margin)).astype(bool) & region
        data &= ~saturated
    excess, supported, broad, block = diffuse_excess(
        image, data, saturated, opening_radius, closing_radius, min_support, fine_sigma,
        threads=threads,
    )
    core, candidate, cores = _cores(
        excess, supported, broad, block, saturated, np.float32(core_excess),
        np.float32(shoulder_excess),
    )
    if cores == 0:
        return np.zeros(image.shape, dtype=bool)
    count, labels = cv2.connectedComponents(candidate, connectivity=8)
    return _regions_with_a_core(labels, core, region, count)


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _classify(
    image: np.ndarray, region: np.ndarray, saturation: float
) -> tuple[np.ndarray, np.ndarray]:
    """Saturated pixels of ``region`` (not finite, or ≥ ``saturation``) and data pixels (> 0).

    Returns two (H, W) bool arrays, in one pass.
    """
    height, width = image.shape
    saturated = np.zeros((height, width), dtype=np.bool_)
    data = np.zeros((height, width), dtype=np.bool_)
    for r in prange(height):
        for c in range(width):
            if not region[r, c]:
                continue
            value = image[r, c]
            if not np.isfinite(value) or value >= saturation:
                saturated[r, c] = True
            elif value > 0.0:
                data[r, c] = True
    return saturated, data


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _cores(
    excess: np.ndarray,
    supported: np.ndarray,
    broad: np.ndarray,
    block: int,
    saturated: np.ndarray,
    core_excess: np.float32,
    shoulder_excess: np.float32,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Highlight cores (saturated, or excess or broad excess above ``core_excess``) and candidates.

    ``excess`` counts where ``supported``; ``broad`` (:func:`_broad_excess`,
    one value per ``block`` × ``block`` pixels, pixels beyond its blocks
    read 0) is 0 where it has no support, and it makes a core only where the pixel
    also stands (core_excess + shoulder_excess) / 2 above the ordinary
    baseline: a lobe's peak is sharp, so it still does (0.75–0.86 on the
    abdomen's broad lobes); the near side of a sphere, diffuse, is as
    bright against the broad baseline but only 0.2 above the ordinary one.

    Returns ((H, W) bool cores; (H, W) uint8 candidates: cores and every
    pixel of excess above ``shoulder_excess``; the number of cores).
    """
    height, width = excess.shape
    midway = np.float32(0.5) * (core_excess + shoulder_excess)
    core = np.zeros((height, width), dtype=np.bool_)
    candidate = np.zeros((height, width), dtype=np.uint8)
    counts = np.zeros(height, dtype=np.int64)
    for r in prange(height):
        count = 0
        broad_row = r // block
        for c in range(width):
            is_core = saturated[r, c] or (excess[r, c] > core_excess and supported[r, c])
            if not is_core and excess[r, c] > midway:  # rare: look the broad excess up
                broad_column = c // block
                is_core = (broad_row < broad.shape[0] and broad_column < broad.shape[1]
                           and broad[broad_row, broad_column] > core_excess)
            if is_core:
                core[r, c] = True
                count += 1
            if is_core or excess[r, c] > shoulder_excess:
                candidate[r, c] = 1
        counts[r] = count
    return core, candidate, int(counts.sum())


@njit(cache=True, nogil=True, error_model="numpy")
def _regions_with_a_core(
    labels: np.ndarray, core: np.ndarray, region: np.ndarray, count: int
) -> np.ndarray:
    """The pixels of ``region`` whose connected candidate region (label > 0) holds a core."""
    height, width = labels.shape
    keep = np.zeros(count, dtype=np.bool_)
    for r in range(height):
        for c in range(width):
            if core[r, c]:
                keep[labels[r, c]] = True
    keep[0] = False
    out = np.zeros((height, width), dtype=np.bool_)
    for r in range(height):
        for c in range(width):
            out[r, c] = keep[labels[r, c]] and region[r, c]
    return out
