"""Gray-card frames, level by level: what the photometric fit is given.

A gray level is every frame of the card at one reflectance (and pose and
exposure). :class:`GrayCardAccumulator` streams frames into per-pixel running
sums (:class:`LevelStatistics`), so a calibration from a long bag never holds
its frames in memory; :func:`endo_calib.fit.fit_gray_card` fits from those sums.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from endo_calib.errors import FitError, ImageSizeMismatchError, InsufficientLevelsError
from endo_calib.geometry import CardPose
from endo_calib.response import SUPPORTED_BIT_DEPTHS


@dataclass(frozen=True)
class GrayLevel:
    """All frames of one gray level.

    reflectance: the card's reflectance ρ in (0, 1].
    frames: N ≥ 1 raw frames, each (H, W) or (H, W, 3) RGB, uint8 or uint16.
    pose: the card pose (fronto-parallel at 5 cm when None).
    exposure: relative exposure (exposure time × gain) of these frames; 1 when
        every level was taken with the same settings, as the protocol asks.
    """

    reflectance: float
    frames: Sequence[NDArray[np.integer]]
    pose: CardPose | None = None
    exposure: float = 1.0


@dataclass
class LevelStatistics:
    """Running per-pixel statistics of one gray level (frames added one by one).

    Samples at or above the saturation value, or at or below the black value,
    are censored: they only say that the true value lies beyond the limit, so
    they are counted, not summed.

    count: frames added. total, total_sq: (H, W, C) float64 sums of the
    uncensored raw values and of their squares. n_ok, n_high, n_low: (H, W, C)
    uint16 counts of uncensored, saturated and black-clipped samples.
    """

    reflectance: float
    exposure: float
    pose: CardPose
    count: int = 0
    total: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    total_sq: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    n_ok: NDArray[np.uint16] = field(default_factory=lambda: np.zeros(0, np.uint16))
    n_high: NDArray[np.uint16] = field(default_factory=lambda: np.zeros(0, np.uint16))
    n_low: NDArray[np.uint16] = field(default_factory=lambda: np.zeros(0, np.uint16))

    def add(self, image: NDArray[np.integer], saturation_value: int, black_value: int) -> None:
        """Add one (H, W, C) frame, censoring values ≥ saturation_value or ≤ black_value."""
        if self.count == 0:
            self.total = np.zeros(image.shape, np.float64)
            self.total_sq = np.zeros(image.shape, np.float64)
            self.n_ok = np.zeros(image.shape, np.uint16)
            self.n_high = np.zeros(image.shape, np.uint16)
            self.n_low = np.zeros(image.shape, np.uint16)
        if self.count >= np.iinfo(np.uint16).max:
            raise FitError("more than 65535 frames in one gray level")
        high = image >= saturation_value
        low = image <= black_value
        ok = ~(high | low)
        values = np.where(ok, image, 0).astype(np.float64)
        self.total += values
        self.total_sq += values * values
        self.n_ok += ok
        self.n_high += high
        self.n_low += low
        self.count += 1


class GrayCardAccumulator:
    """Collects gray-card frames level by level without keeping them in memory.

    bit_depth: significant bits of the raw values; 8 for uint8 frames, and it
        must be given for uint16 frames (10, 12, 14 or 16).
    saturation_value: raw values ≥ this are saturated (2^bits − 1 when None).
    black_value: raw values ≤ this are clipped at black (0 by default).
    """

    def __init__(
        self,
        bit_depth: int | None = None,
        saturation_value: int | None = None,
        black_value: int = 0,
    ) -> None:
        if bit_depth is not None and bit_depth not in SUPPORTED_BIT_DEPTHS:
            raise FitError(f"bit depth {bit_depth} not one of {SUPPORTED_BIT_DEPTHS}")
        self._bit_depth = bit_depth
        self._saturation_value = saturation_value
        self.black_value = int(black_value)
        self.levels: dict[tuple[float, float, CardPose], LevelStatistics] = {}
        self.shape: tuple[int, int, int] | None = None
        self.dtype: np.dtype | None = None

    @property
    def bit_depth(self) -> int:
        """The raw bit depth (known once the first frame was added)."""
        if self._bit_depth is None:
            raise InsufficientLevelsError("no gray-card frames were added")
        return self._bit_depth

    @property
    def saturation_value(self) -> int:
        """Raw values at or above this count as saturated."""
        top = (1 << self.bit_depth) - 1
        return top if self._saturation_value is None else int(self._saturation_value)

    def add(
        self,
        frame: NDArray[np.integer],
        reflectance: float,
        pose: CardPose | None = None,
        exposure: float = 1.0,
    ) -> None:
        """Add one raw frame of the card with ``reflectance`` in (0, 1].

        frame: (H, W) or (H, W, 3) RGB, uint8 or uint16, every frame the same
        shape and dtype. pose: the card pose (fronto-parallel when None).
        exposure: relative exposure of this frame's level (> 0).
        """
        image = np.asarray(frame)
        if image.ndim == 2:
            image = image[:, :, None]
        if image.ndim != 3 or image.shape[2] not in (1, 3):
            raise ImageSizeMismatchError(
                f"gray-card frame must be (H, W) or (H, W, 3), got shape {np.shape(frame)}"
            )
        if image.dtype not in (np.uint8, np.uint16):
            raise ImageSizeMismatchError(
                f"gray-card frame must be uint8 or uint16, got {image.dtype}"
            )
        if self.shape is None:
            if image.dtype == np.uint8:
                if self._bit_depth not in (None, 8):
                    raise ImageSizeMismatchError(
                        f"8-bit frames given for a {self._bit_depth}-bit calibration"
                    )
                self._bit_depth = 8
            elif self._bit_depth is None:
                raise FitError(
                    "16-bit frames need an explicit bit depth (10, 12, 14 or 16 significant bits)"
                )
            self.shape = (image.shape[0], image.shape[1], image.shape[2])
            self.dtype = image.dtype
        elif image.shape != self.shape or image.dtype != self.dtype:
            raise ImageSizeMismatchError(
                f"gray-card frame {image.shape[1]}x{image.shape[0]}x{image.shape[2]} {image.dtype} "
                f"differs from the first frame {self.shape[1]}x{self.shape[0]}x{self.shape[2]} "
                f"{self.dtype}"
            )
        if not (np.isfinite(reflectance) and 0.0 < reflectance <= 1.0):
            raise InsufficientLevelsError(f"reflectance must be in (0, 1], got {reflectance!r}")
        if not (np.isfinite(exposure) and exposure > 0.0):
            raise InsufficientLevelsError(f"exposure must be > 0, got {exposure!r}")
        peak = int(image.max())
        if peak >= 1 << self.bit_depth:
            raise ImageSizeMismatchError(f"raw value {peak} does not fit in {self.bit_depth} bits")
        card = pose or CardPose()
        key = (float(reflectance), float(exposure), card)
        level = self.levels.get(key)
        if level is None:
            level = LevelStatistics(float(reflectance), float(exposure), card)
            self.levels[key] = level
        level.add(image, self.saturation_value, self.black_value)

    def add_level(self, level: GrayLevel) -> None:
        """Add every frame of a :class:`GrayLevel`."""
        if len(level.frames) == 0:
            raise InsufficientLevelsError(f"gray level {level.reflectance:g} has no frames")
        for frame in level.frames:
            self.add(frame, level.reflectance, level.pose, level.exposure)
