"""depth_from_log_distance: the one-pass depth resampling against sample_weighted in float64."""

from __future__ import annotations

import numpy as np

from endo_sfs.resampling import depth_from_log_distance, sample_weighted


def _case(seed: int, log_scale: float) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    h, w, H, W = 31, 41, 120, 160
    log_r = rng.normal(0.0, log_scale, (h, w))
    unusable = rng.random((h, w))
    log_r[unusable < 0.08] = np.nan
    log_r[(unusable >= 0.08) & (unusable < 0.10)] = np.inf
    log_r[(unusable >= 0.10) & (unusable < 0.12)] = -np.inf
    map_x = rng.uniform(-0.5, w - 0.5, (H, W))
    map_y = rng.uniform(-0.5, h - 0.5, (H, W))
    wanted = rng.random((H, W)) > 0.1
    ray_z = rng.uniform(0.5, 1.0, (H, W))
    return log_r, map_x, map_y, wanted, ray_z


def test_depth_matches_the_float64_path_and_counts_overflows():
    for seed, log_scale in ((1, 1.5), (2, 3.0), (3, 40.0)):  # 40: ln r up to ~±150, overflows
        log_r, map_x, map_y, wanted, ray_z = _case(seed, log_scale)
        depth, overflowed = depth_from_log_distance(log_r, map_x, map_y, wanted, ray_z)
        log_ref = sample_weighted(log_r, map_x, map_y, wanted)
        with np.errstate(over="ignore"):
            ref = (np.exp(log_ref) * ray_z).astype(np.float32)
        assert depth.dtype == np.float32 and depth.shape == map_x.shape
        # unknown (no finite node) or not wanted: NaN, the same pixels
        assert np.array_equal(np.isnan(depth), np.isnan(ref))
        assert not np.any(np.isfinite(depth) & ~wanted)
        # overflowed solves: counted, as the float64 path finds them
        assert overflowed == int(np.sum(np.isfinite(log_ref) & ~(np.isfinite(ref) & (ref > 0))))
        # (float32's subnormals, below e^-87, carry fewer digits: no depth is that small)
        ok = np.isfinite(ref) & (ref >= np.finfo(np.float32).tiny)
        relative = np.abs(depth[ok].astype(np.float64) / ref[ok] - 1.0)
        # float32's exponential: relative error ~6e-8 · |ln r| plus the output's rounding
        assert np.all(relative <= 7e-8 * np.abs(log_ref[ok]) + 2.5e-7), relative.max()
