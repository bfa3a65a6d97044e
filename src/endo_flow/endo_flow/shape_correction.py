"""A smooth correction field of the SFS depth over the image, from the sparse metric points.

A light map or response a few percent off bends the SFS surface, and no
single scale undoes that. Such an error is fixed in the image (it comes from
the calibration, not the scene), so the residual log ratios

    r_i = ln z_i − ln d_rel(u_i, v_i) − ln s

of the triangulated tracks, accumulated over frames, sample one field
c(u, v) with metric depth ≈ s · e^{c(u, v)} · d_rel. It is fitted as a
low-degree polynomial in normalised image coordinates (x, y) = ((u, v) −
(cx, cy)) / R, without the constant (that is the scale filter's), every
monomial made zero-mean over the field of view so that c does not shift s.

The fit is a MAP estimate with a Gaussian prior on the coefficients (every
coefficient N(0, ``prior_std²``)): ridge regression towards a constant field.
Each point is weighted by 1/σ² with σ the observations' robust spread and a
Huber weight on its residual from the current field. The normal equations
are accumulated with exponential forgetting (time constant ``memory_s``).
The field is applied only when the points seen in the memory cover enough of
the image (``min_cells`` of a ``cells × cells`` grid over the field of view
hold at least ``min_points_per_cell`` points); otherwise it is 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from endo_io.stamp import NS_PER_S

SHAPE_CORRECTION_MODES: tuple[str, ...] = ("none", "smooth")


@dataclass(frozen=True)
class ShapeCorrectionOptions:
    """Settings of :class:`ShapeCorrector`.

    Attributes:
        mode: "none" (no correction) or "smooth" (the polynomial field).
        degree: polynomial degree, 1 to 4.
        prior_std: prior standard deviation of every coefficient (ln units;
            smaller pulls harder towards a constant field).
        memory_s: time constant of the forgetting, seconds.
        cells: the coverage grid is cells × cells over the field of view.
        min_cells: cells that must hold points before the field is applied.
        min_points_per_cell: points (weighted by forgetting) that make a
            cell covered.
        max_correction: the field's |c| is clipped to this (ln units).
        huber_k: Huber threshold in robust standard deviations.
    """

    mode: str = "smooth"
    degree: int = 2
    prior_std: float = 0.05
    memory_s: float = 10.0
    cells: int = 4
    min_cells: int = 8
    min_points_per_cell: float = 5.0
    max_correction: float = 0.3
    huber_k: float = 1.5

    def __post_init__(self) -> None:
        if self.mode not in SHAPE_CORRECTION_MODES:
            raise ValueError(f"shape correction mode must be one of {SHAPE_CORRECTION_MODES}, "
                             f"got {self.mode!r}")
        if not 1 <= self.degree <= 4:
            raise ValueError(f"degree must be in [1, 4], got {self.degree}")
        if not (self.prior_std > 0.0 and self.memory_s > 0.0 and self.max_correction > 0.0):
            raise ValueError("prior_std, memory_s and max_correction must be > 0")
        if not (self.cells >= 1 and 0 <= self.min_cells <= self.cells**2):
            raise ValueError("need cells >= 1 and 0 <= min_cells <= cells²")
        if self.min_points_per_cell < 0.0 or self.huber_k <= 0.0:
            raise ValueError("min_points_per_cell must be >= 0 and huber_k > 0")


def _exponents(degree: int) -> list[tuple[int, int]]:
    return [(a, t - a) for t in range(1, degree + 1) for a in range(t, -1, -1)]


class ShapeCorrector:
    """Accumulates residual log ratios and evaluates the correction field.

    Args:
        width, height: image size, pixels.
        centre: (cx, cy) pixel of the normalisation (the principal point).
        radius_px: radius of the field of view, pixels (normalises x, y).
        options: the settings.
    """

    def __init__(
        self,
        width: int,
        height: int,
        centre: tuple[float, float],
        radius_px: float,
        options: ShapeCorrectionOptions | None = None,
    ) -> None:
        self.options = options or ShapeCorrectionOptions()
        self.width, self.height = int(width), int(height)
        self.centre = (float(centre[0]), float(centre[1]))
        self.radius_px = float(radius_px)
        self._exponents = _exponents(self.options.degree)
        # means of the monomials over the disc of the field of view
        gy, gx = np.mgrid[-1.0:1.0:201j, -1.0:1.0:201j]
        inside = gx**2 + gy**2 <= 1.0
        self._means = np.array(
            [float(np.mean(gx[inside] ** a * gy[inside] ** b)) for a, b in self._exponents]
        )
        self.reset()

    @property
    def active(self) -> bool:
        """Whether the field is applied (mode smooth and enough coverage)."""
        return self.options.mode == "smooth" and self._covered

    @property
    def coefficients(self) -> np.ndarray:
        """(K,) float64 current coefficients (zeros while inactive)."""
        return self._theta.copy() if self.active else np.zeros_like(self._theta)

    def reset(self) -> None:
        """Forget every accumulated point."""
        k = len(self._exponents)
        self._A = np.zeros((k, k))
        self._b = np.zeros(k)
        self._theta = np.zeros(k)
        self._cell_weight = np.zeros(self.options.cells**2)
        self._stamp_ns: int | None = None
        self._covered = False
        self._field: np.ndarray | None = None

    def basis(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, K) float64 zero-mean monomials of the normalised coordinates."""
        x = (np.asarray(uv, np.float64)[:, 0] - self.centre[0]) / self.radius_px
        y = (np.asarray(uv, np.float64)[:, 1] - self.centre[1]) / self.radius_px
        return np.stack([x**a * y**b for a, b in self._exponents], axis=1) - self._means

    def log_correction(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N,) float64 ln of the correction factor (0 while inactive)."""
        if not self.active:
            return np.zeros(len(uv))
        c = self.basis(uv) @ self._theta
        return np.clip(c, -self.options.max_correction, self.options.max_correction)

    def update(self, uv: np.ndarray, residual: np.ndarray, spread: float, stamp_ns: int) -> None:
        """Fuse one frame's residuals.

        Args:
            uv: (N, 2) pixels of the points.
            residual: (N,) ln z − ln d_rel − ln s at those pixels.
            spread: robust standard deviation of the residuals (ln units).
            stamp_ns: the frame's stamp, integer ns.
        """
        if self.options.mode == "none":
            return
        opts = self.options
        if self._stamp_ns is not None:
            dt = max(0.0, (stamp_ns - self._stamp_ns) / NS_PER_S)
            forget = float(np.exp(-dt / opts.memory_s))
            self._A *= forget
            self._b *= forget
            self._cell_weight *= forget
        self._stamp_ns = stamp_ns
        r = np.asarray(residual, np.float64)
        ok = np.isfinite(r)
        if not np.any(ok):
            return
        points, r = np.asarray(uv, np.float64)[ok], r[ok]
        phi = self.basis(points)
        sigma = max(float(spread), 1e-3)
        u = np.abs(r - phi @ self._theta) / sigma
        w = np.minimum(1.0, opts.huber_k / np.maximum(u, 1e-12)) / sigma**2
        self._A += (phi * w[:, None]).T @ phi
        self._b += phi.T @ (w * r)
        prior = np.eye(len(self._b)) / opts.prior_std**2
        self._theta = np.asarray(np.linalg.solve(self._A + prior, self._b), np.float64)
        cells = opts.cells
        x = (points[:, 0] - self.centre[0]) / self.radius_px
        y = (points[:, 1] - self.centre[1]) / self.radius_px
        cx = np.clip(((x + 1.0) * 0.5 * cells).astype(np.int64), 0, cells - 1)
        cy = np.clip(((y + 1.0) * 0.5 * cells).astype(np.int64), 0, cells - 1)
        self._cell_weight += np.bincount(cy * cells + cx, minlength=cells * cells)
        self._covered = int(np.sum(self._cell_weight >= opts.min_points_per_cell)) >= opts.min_cells
        self._field = None

    def field(self) -> np.ndarray | None:
        """(H, W) float32 multiplicative correction e^c, or None while inactive.

        Evaluated on a grid 4× coarser and resized (the field is smooth),
        and cached until the next update.
        """
        if not self.active:
            return None
        if self._field is None:
            step = 4
            w, h = max(2, self.width // step), max(2, self.height // step)
            # coarse pixel centres in full-resolution pixels (cv2.resize mapping)
            u = (np.arange(w) + 0.5) * (self.width / w) - 0.5
            v = (np.arange(h) + 0.5) * (self.height / h) - 0.5
            uu, vv = np.meshgrid(u, v)
            c = self.log_correction(np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(h, w)
            coarse = np.exp(c).astype(np.float32)
            self._field = cv2.resize(coarse, (self.width, self.height),
                                     interpolation=cv2.INTER_LINEAR)
        return self._field
