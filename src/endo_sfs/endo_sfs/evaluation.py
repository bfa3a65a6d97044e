"""Depth error measures for relative (up-to-scale) depth maps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DepthError:
    """Errors of a depth map against ground truth after one global scale.

    scale: the factor applied to the estimate. abs_rel: mean |s·d − d*|/d*.
    p95_rel, max_rel: 95th percentile and maximum of the same ratio.
    mae: mean |s·d − d*|, in the unit of the truth (metres for metric depth).
    coverage: fraction of the pixels with finite truth (inside the evaluated
    region) that have a finite estimate.
    """

    scale: float
    abs_rel: float
    p95_rel: float
    max_rel: float
    coverage: float
    mae: float


def depth_error(
    estimate: np.ndarray,
    truth: np.ndarray,
    region: np.ndarray | None = None,
    scaling: str = "least_squares",
) -> DepthError:
    """Compare a relative depth map with the truth after one global scale.

    estimate, truth: (H, W) float depths (NaN invalid); region: optional
    (H, W) bool where to evaluate. scaling: "least_squares" (s minimising
    Σ(s·d − d*)²), "median" (s = median(d*)/median(d)) or "none".
    Raises ValueError when no pixel has both values.
    """
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    wanted = np.isfinite(truth) & (truth > 0.0)
    if region is not None:
        wanted &= region
    both = wanted & np.isfinite(estimate)
    if not both.any():
        raise ValueError("no pixel has both an estimate and a ground-truth depth")
    d, t = estimate[both], truth[both]
    if scaling == "least_squares":
        scale = float(np.dot(d, t) / np.dot(d, d))
    elif scaling == "median":
        scale = float(np.median(t) / np.median(d))
    elif scaling == "none":
        scale = 1.0
    else:
        raise ValueError(f"unknown scaling {scaling!r}")
    difference = np.abs(scale * d - t)
    ratio = difference / t
    return DepthError(
        scale=scale,
        abs_rel=float(np.mean(ratio)),
        p95_rel=float(np.percentile(ratio, 95)),
        max_rel=float(np.max(ratio)),
        coverage=float(both.sum() / wanted.sum()),
        mae=float(np.mean(difference)),
    )
