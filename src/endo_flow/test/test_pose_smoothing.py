"""Pose smoothing: exact on uniform motion, and it averages the tracker's noise."""

from __future__ import annotations

import numpy as np

from endo_flow.pose_smoothing import PoseSmoother
from endo_io.pose import rigid_transform, rotation_angle

STEP = 33_333_333


def _motion(k: int) -> np.ndarray:
    # 10 mm/s and 10°/s about a fixed axis: constant velocity
    return rigid_transform(np.radians(10.0 / 30.0) * k * np.array([0.0, 0.6, 0.8]),
                           np.array([0.01 / 30.0 * k, 0.0, 0.0]))


def test_uniform_motion_is_reproduced_exactly():
    smoother = PoseSmoother(300_000_000)
    for k in range(40):
        smoother.add(k * STEP, _motion(k))
    # 1e-5: the small-angle logarithm over a 3° window (θ³/6), 1 % of the tracker's noise
    for k in (5, 20, 39):
        np.testing.assert_allclose(smoother.smoothed(k * STEP), _motion(k), atol=1e-5)


def test_noise_falls_about_threefold():
    rng = np.random.default_rng(0)
    smoother = PoseSmoother(300_000_000)
    truth = [_motion(k) for k in range(60)]
    for k, T in enumerate(truth):
        noisy = T @ rigid_transform(rng.normal(0.0, 1e-3, 3), rng.normal(0.0, 0.3e-3, 3))
        smoother.add(k * STEP, noisy)
    raw, smooth, turn = [], [], []
    for k in range(15, 45):
        T = smoother.smoothed(k * STEP)
        raw.append(np.linalg.norm(smoother.poses[k][:3, 3] - truth[k][:3, 3]))
        smooth.append(np.linalg.norm(T[:3, 3] - truth[k][:3, 3]))
        turn.append(float(rotation_angle(T[:3, :3].T @ truth[k][:3, :3])))
    assert np.sqrt(np.mean(np.square(smooth))) < 0.45 * np.sqrt(np.mean(np.square(raw)))
    assert np.sqrt(np.mean(np.square(turn))) < 0.8e-3  # raw: 1.7e-3 rad RMS
