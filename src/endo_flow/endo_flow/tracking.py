"""Sparse feature tracks by pyramidal Lucas–Kanade flow on the corrected image.

Each frame's linear irradiance (``endo_calib`` output, decoded to float32, NaN outside the
field of view and at saturated pixels) is averaged down by ``downsample``
(cv2.INTER_AREA, so a NaN poisons only its own block) and mapped to 8 bits by
:func:`endo_io.image.irradiance_to_mono8`. The white level of that mapping is
a slow running mean of a high percentile, so that the 8-bit values of one
surface point stay the same from frame to frame, which Lucas–Kanade assumes.

Features are Shi–Tomasi corners (``cv2.goodFeaturesToTrack``), spread over
the image by a grid of buckets (each bucket gets at most its share of
``max_tracks``), inside the valid region eroded by a margin and outside
specular highlights (:func:`endo_sfs.highlights.detect_highlights`: a
highlight moves over the surface with the viewpoint, so a corner on it is not
a surface point). Tracks are followed by ``cv2.calcOpticalFlowPyrLK`` and kept
only if the backward flow returns within ``fb_threshold_px`` of the start.
New corners are seeded when fewer than ``reseed_fraction`` of ``max_tracks``
are alive, or every ``reseed_every`` frames.

Coordinates are pixels of the full-resolution image (centres at integers):
a tracking-resolution pixel u' is ``(u' + 0.5)·downsample − 0.5`` there, the
cv2.resize mapping that :meth:`endo_io.camera.CameraModel.resized` uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from endo_flow.errors import FlowInputError
from endo_flow.scale import median
from endo_io.image import irradiance_to_mono8
from endo_sfs.highlights import detect_highlights


@dataclass(frozen=True)
class TrackingOptions:
    """Settings of :class:`FeatureTracker`.

    Attributes:
        max_tracks: tracks kept alive (about; re-seeding tops them up).
        grid: (columns, rows) of the buckets that spread the features.
        downsample: integer factor from the image to the tracking
            resolution (2: 640×480 is tracked at 320×240).
        quality_level: Shi–Tomasi quality relative to the best corner.
        min_distance_px: least distance between features, tracking pixels.
        block_size: Shi–Tomasi neighbourhood, tracking pixels.
        window_px: Lucas–Kanade window side, tracking pixels (odd).
        pyramid_levels: pyramid levels above the base (0: no pyramid).
        fb_threshold_px: largest forward–backward error, tracking pixels.
        border_px: features are kept this far inside the valid region,
            tracking pixels.
        reseed_fraction: seed new features when fewer than this fraction of
            ``max_tracks`` are alive.
        reseed_every: also seed every this many frames (0: never on a
            schedule).
        mask_highlights: keep seeds off specular highlights.
        gamma: tone curve exponent of the 8-bit mapping.
        white_percentile: percentile of the valid irradiance mapped to 255.
        white_smoothing: weight of the current frame in the running mean of
            the white level, (0, 1] (1: per frame, no memory).
        min_valid_fraction: a frame with less valid area than this fraction
            of its pixels has nothing to track.
    """

    max_tracks: int = 200
    grid: tuple[int, int] = (8, 6)
    downsample: int = 2
    quality_level: float = 0.01
    min_distance_px: float = 6.0
    block_size: int = 5
    window_px: int = 15
    pyramid_levels: int = 2
    fb_threshold_px: float = 0.3
    border_px: int = 6
    reseed_fraction: float = 0.8
    reseed_every: int = 10
    mask_highlights: bool = True
    gamma: float = 1.0
    white_percentile: float = 99.0
    white_smoothing: float = 0.1
    min_valid_fraction: float = 0.01
    flatten_sigma_px: float = 4.0

    def __post_init__(self) -> None:
        checks = [
            (self.max_tracks >= 1, "max_tracks must be >= 1"),
            (self.grid[0] >= 1 and self.grid[1] >= 1, "grid must be at least 1x1"),
            (self.downsample >= 1, "downsample must be >= 1"),
            (0.0 < self.quality_level < 1.0, "quality_level must be in (0, 1)"),
            (self.min_distance_px > 0.0, "min_distance_px must be > 0"),
            (self.block_size >= 3, "block_size must be >= 3"),
            (self.window_px >= 5 and self.window_px % 2 == 1, "window_px must be odd, >= 5"),
            (0 <= self.pyramid_levels <= 6, "pyramid_levels must be in [0, 6]"),
            (self.fb_threshold_px > 0.0, "fb_threshold_px must be > 0"),
            (self.border_px >= 0, "border_px must be >= 0"),
            (0.0 < self.reseed_fraction <= 1.0, "reseed_fraction must be in (0, 1]"),
            (self.reseed_every >= 0, "reseed_every must be >= 0"),
            (self.gamma > 0.0, "gamma must be > 0"),
            (50.0 <= self.white_percentile <= 100.0, "white_percentile must be in [50, 100]"),
            (0.0 < self.white_smoothing <= 1.0, "white_smoothing must be in (0, 1]"),
            (0.0 <= self.min_valid_fraction < 1.0, "min_valid_fraction must be in [0, 1)"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)


@dataclass(frozen=True)
class TrackedFeatures:
    """The features of one frame.

    Attributes:
        ids: (N,) int64 track ids, unique, increasing with age of creation.
        uv: (N, 2) float64 positions, full-resolution pixels (u right, v down).
        seeded: (N,) bool, True for features created on this frame.
        lost: tracks of the previous frame that were not continued.
        valid_fraction: fraction of the frame's pixels that were usable.
        brightness_ratio: median over the continued tracks of the irradiance
            at the track now over the irradiance there in the previous frame
            (NaN without continued tracks). Motion changes it by a few
            percent per frame at most; an exposure or gain change makes it
            jump by the gain factor.
    """

    ids: np.ndarray
    uv: np.ndarray
    seeded: np.ndarray
    lost: int
    valid_fraction: float
    brightness_ratio: float = float("nan")


def _brightness_ratio(before: np.ndarray, after: np.ndarray, old: np.ndarray,
                      new: np.ndarray) -> float:
    """Median of after(new) / before(old) over tracks, nearest pixels; NaN if none."""
    h, w = before.shape
    # both point sets' (col, row) at once; np.minimum / np.maximum, not np.clip
    # (the same integers, without np.clip's wrappers)
    pixel = np.rint(np.concatenate([old, new], axis=1)).astype(np.int64)
    pixel = np.maximum(np.minimum(pixel, np.array([w - 1, h - 1, w - 1, h - 1])), 0)
    a, b = before[pixel[:, 1], pixel[:, 0]], after[pixel[:, 3], pixel[:, 2]]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = b / a
    ratio = ratio[np.isfinite(ratio) & (ratio > 0.0)]
    return median(ratio) if ratio.size else float("nan")


@numba.njit(cache=True, nogil=True)
def _valid_data(image: np.ndarray, valid: np.ndarray, data: np.ndarray, weight: np.ndarray
                ) -> None:
    """data = image where valid else 0, weight = valid as 0 / 1 (float32, in one pass)."""
    h, w = image.shape
    for r in range(h):
        for c in range(w):
            if valid[r, c]:
                data[r, c] = image[r, c]
                weight[r, c] = 1.0
            else:
                data[r, c] = 0.0
                weight[r, c] = 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _local_ratio(data: np.ndarray, norm: np.ndarray, blurred: np.ndarray, valid: np.ndarray,
                 out: np.ndarray) -> None:
    """out = data · norm / blurred where valid, else 1, in float32 as numpy computes it."""
    h, w = data.shape
    for r in range(h):
        for c in range(w):
            out[r, c] = data[r, c] * norm[r, c] / blurred[r, c] if valid[r, c] else 1.0


def flatten_shading(image: np.ndarray, valid: np.ndarray, sigma_px: float) -> np.ndarray:
    """Divide out the slowly varying shading: image / (Gaussian of the valid pixels).

    Args:
        image: (h, w) float32 irradiance, NaN invalid.
        valid: (h, w) bool usable pixels.
        sigma_px: Gaussian σ, pixels.

    Returns:
        (h, w) float32 ratio to the local mean (about 1 on the tissue), 1
        where ``valid`` is False.
    """
    image = np.ascontiguousarray(image, np.float32)
    valid = np.ascontiguousarray(valid, np.bool_)
    data = np.empty(image.shape, np.float32)
    weight = np.empty(image.shape, np.float32)
    _valid_data(image, valid, data, weight)
    # ±2.5σ: OpenCV's own choice for float images is ±4σ, twice the work
    size = 2 * int(np.ceil(2.5 * sigma_px)) + 1
    blurred = cv2.GaussianBlur(data, (size, size), sigma_px, borderType=cv2.BORDER_CONSTANT)
    norm = cv2.GaussianBlur(weight, (size, size), sigma_px, borderType=cv2.BORDER_CONSTANT)
    # invalid pixels read as the local mean (1): no edge at the field of view's
    # rim or around a saturated blob for Lucas–Kanade's window to lock onto
    ratio = np.empty(image.shape, np.float32)
    _local_ratio(data, norm, blurred, valid, ratio)
    return ratio


class FeatureTracker:
    """Lucas–Kanade feature tracks over a stream of corrected images (see the module docstring).

    Args:
        options: the settings, validated.
    """

    def __init__(self, options: TrackingOptions | None = None) -> None:
        self.options = options or TrackingOptions()
        self._previous: np.ndarray | None = None
        self._previous_irradiance: np.ndarray | None = None
        self._points = np.empty((0, 2), np.float32)  # tracking-resolution pixels
        self._ids = np.empty(0, np.int64)
        self._next_id = 0
        self._white: float | None = None
        self._frames_since_seed = 0

    @property
    def white_level(self) -> float | None:
        """The irradiance currently mapped to 255, or None before the first frame."""
        return self._white

    def reset(self) -> None:
        """Forget every track and the white level (a clock jump, a new sequence)."""
        self._previous = None
        self._previous_irradiance = None
        self._points = np.empty((0, 2), np.float32)
        self._ids = np.empty(0, np.int64)
        self._white = None
        self._frames_since_seed = 0

    def to_full_resolution(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) tracking-resolution pixels -> (..., 2) float64 full-resolution pixels."""
        k = self.options.downsample
        return (np.asarray(uv, np.float64) + 0.5) * k - 0.5

    def tracking_image(self, irradiance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reduce one corrected image to the tracking resolution.

        Args:
            irradiance: (H, W) float linear irradiance, NaN invalid.

        Returns:
            ((h, w) float32 irradiance, NaN invalid; (h, w) bool valid), with
            h = H // downsample and w = W // downsample.
        """
        image = np.asarray(irradiance, np.float32)
        if image.ndim != 2:
            raise FlowInputError(f"corrected image must be (H, W), got shape {image.shape}")
        k = self.options.downsample
        h, w = image.shape[0] // k, image.shape[1] // k
        if h < 8 or w < 8:
            raise FlowInputError(f"image {image.shape[1]}x{image.shape[0]} too small to track")
        if k > 1:
            image = np.asarray(
                cv2.resize(image[: h * k, : w * k], (w, h), interpolation=cv2.INTER_AREA),
                np.float32,
            )
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(image) & (image > 0.0)
        return image, valid

    def _update_white(self, image: np.ndarray, valid: np.ndarray) -> float:
        sample = image[::2, ::2][valid[::2, ::2]]
        if sample.size == 0:
            return self._white if self._white is not None else 1.0
        rank = min(sample.size - 1, int(self.options.white_percentile / 100.0 * sample.size))
        level = float(np.partition(sample, rank)[rank])
        if not level > 0.0:
            return self._white if self._white is not None else 1.0
        if self._white is None:
            self._white = level
        else:
            a = self.options.white_smoothing
            # geometric mean: a gain step moves the level by the same factor
            # whichever way it goes
            self._white = float(np.exp((1.0 - a) * np.log(self._white) + a * np.log(level)))
        return self._white

    def track(self, irradiance: np.ndarray) -> TrackedFeatures:
        """Continue the tracks into this frame and top them up with new features.

        Args:
            irradiance: (H, W) float32 linear irradiance of the frame, NaN
                outside the field of view and where saturated.

        Returns:
            The frame's features (positions in full-resolution pixels).
        """
        opts = self.options
        image, valid = self.tracking_image(irradiance)
        valid_fraction = float(valid.mean())
        if valid_fraction < opts.min_valid_fraction:
            lost = len(self._ids)
            self.reset()
            return TrackedFeatures(
                np.empty(0, np.int64), np.empty((0, 2)), np.empty(0, bool), lost, valid_fraction
            )
        irradiance_small = image
        if opts.flatten_sigma_px > 0.0:
            image = flatten_shading(image, valid, opts.flatten_sigma_px)
        white = self._update_white(image, valid)
        mono = irradiance_to_mono8(image, white=white, gamma=opts.gamma)
        usable = valid
        if opts.border_px > 0:
            size = 2 * opts.border_px + 1
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
            # bool and uint8 share their bytes: views, not two conversions
            usable = cv2.erode(valid.view(np.uint8), kernel).view(bool)

        lost = 0
        ratio = float("nan")
        if self._previous is not None and len(self._ids) > 0:
            kept, points = self._flow(self._previous, mono, self._points, usable)
            lost = int((~kept).sum())
            if self._previous_irradiance is not None and kept.any():
                ratio = _brightness_ratio(self._previous_irradiance, irradiance_small,
                                          self._points[kept], points[kept])
            self._ids = self._ids[kept]
            self._points = points[kept]
        self._previous = mono
        self._previous_irradiance = irradiance_small

        seeded = np.zeros(len(self._ids), bool)
        self._frames_since_seed += 1
        due = opts.reseed_every > 0 and self._frames_since_seed >= opts.reseed_every
        if len(self._ids) < opts.reseed_fraction * opts.max_tracks or due:
            new_points = self._seed(mono, irradiance_small, usable)
            if len(new_points):
                new_ids = np.arange(self._next_id, self._next_id + len(new_points), dtype=np.int64)
                self._next_id += len(new_points)
                self._ids = np.concatenate([self._ids, new_ids])
                self._points = np.concatenate([self._points, new_points])
                seeded = np.concatenate([seeded, np.ones(len(new_points), bool)])
            self._frames_since_seed = 0
        return TrackedFeatures(
            self._ids.copy(), self.to_full_resolution(self._points), seeded, lost, valid_fraction,
            ratio,
        )

    def _flow(
        self, previous: np.ndarray, current: np.ndarray, points: np.ndarray, usable: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """LK forward and backward; returns (kept (N,) bool, new points (N, 2) float32)."""
        opts = self.options
        window = (opts.window_px, opts.window_px)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
        start = points.reshape(-1, 1, 2).astype(np.float32)
        forward, status_f, _ = cv2.calcOpticalFlowPyrLK(
            previous, current, start, start.copy(), winSize=window, maxLevel=opts.pyramid_levels,
            criteria=criteria,
        )
        backward, status_b, _ = cv2.calcOpticalFlowPyrLK(
            current, previous, forward, np.array(start), winSize=window,
            maxLevel=opts.pyramid_levels, criteria=criteria,
        )
        forward = forward.reshape(-1, 2)
        fb_error = np.linalg.norm(backward.reshape(-1, 2) - points, axis=1)
        kept = (status_f.ravel() == 1) & (status_b.ravel() == 1)
        kept &= fb_error < opts.fb_threshold_px
        col = np.rint(forward[:, 0]).astype(np.int64)
        row = np.rint(forward[:, 1]).astype(np.int64)
        inside = (col >= 0) & (col < usable.shape[1]) & (row >= 0) & (row < usable.shape[0])
        kept &= inside
        kept[kept] = usable[row[kept], col[kept]]
        return kept, forward

    def _seed(self, mono: np.ndarray, image: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """New Shi–Tomasi corners, bucketed, away from existing tracks: (M, 2) float32."""
        opts = self.options
        region = usable.copy()
        if opts.mask_highlights:
            region &= ~detect_highlights(image, usable)
        if len(self._points):
            taken = np.zeros(region.shape, np.uint8)
            col = np.clip(np.rint(self._points[:, 0]).astype(np.int64), 0, region.shape[1] - 1)
            row = np.clip(np.rint(self._points[:, 1]).astype(np.int64), 0, region.shape[0] - 1)
            taken[row, col] = 1
            size = 2 * int(np.ceil(opts.min_distance_px)) + 1
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
            region &= cv2.dilate(taken, kernel) == 0
        if not region.any():
            return np.empty((0, 2), np.float32)
        corners = cv2.goodFeaturesToTrack(
            mono, maxCorners=4 * opts.max_tracks, qualityLevel=opts.quality_level,
            minDistance=opts.min_distance_px, mask=region.astype(np.uint8),
            blockSize=opts.block_size,
        )
        if corners is None:
            return np.empty((0, 2), np.float32)
        corners = corners.reshape(-1, 2)  # strongest first
        cols, rows = opts.grid
        h, w = mono.shape
        bucket_of = lambda p: (  # noqa: E731
            np.minimum((p[:, 1] * rows / h).astype(np.int64), rows - 1) * cols
            + np.minimum((p[:, 0] * cols / w).astype(np.int64), cols - 1)
        )
        buckets = bucket_of(corners)
        # each bucket with any usable area gets an equal share of max_tracks
        area = np.bincount(bucket_of(np.argwhere(usable[::4, ::4])[:, ::-1] * 4.0),
                           minlength=cols * rows)
        share = int(np.ceil(opts.max_tracks / max(1, int((area > 0).sum()))))
        existing = np.bincount(bucket_of(self._points), minlength=cols * rows) if len(
            self._points) else np.zeros(cols * rows, np.int64)
        room = np.maximum(share - existing, 0)
        order = np.argsort(buckets, kind="stable")  # quality order kept inside each bucket
        sorted_buckets = buckets[order]
        first = np.searchsorted(sorted_buckets, sorted_buckets, side="left")
        rank = np.arange(len(order)) - first
        chosen = order[rank < room[sorted_buckets]]
        chosen.sort()  # back to quality order
        budget = max(0, opts.max_tracks - len(self._points))
        return corners[chosen[:budget]].astype(np.float32)
