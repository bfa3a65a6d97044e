"""Robust scale observations and the Kalman filter on ln s."""

from __future__ import annotations

import numpy as np

from endo_flow.scale import ScaleFilter, ScaleObservation, ScaleState, observe_scale

FRAME_NS = 33_333_333


def test_observation_ignores_30_percent_outliers():
    rng = np.random.default_rng(0)
    relative = rng.uniform(0.5, 2.0, 200)
    metric = 0.04 * relative * np.exp(rng.normal(0.0, 0.02, 200))
    metric[:60] *= rng.uniform(1.5, 3.0, 60)  # 30 % wild tracks
    obs = observe_scale(metric, relative)
    assert obs is not None
    assert abs(np.exp(obs.log_scale) / 0.04 - 1.0) < 0.01
    assert 0.015 < obs.spread < 0.04
    assert observe_scale(metric[:5], relative[:5]) is None


def _obs(value: float, std: float = 0.02) -> ScaleObservation:
    return ScaleObservation(np.log(value), std, std * 5, 50, 45)


def test_filter_converges_gates_and_holds():
    rng = np.random.default_rng(1)
    f = ScaleFilter()
    t = 0
    for _ in range(30):
        t += FRAME_NS
        f.update(_obs(0.04 * np.exp(rng.normal(0.0, 0.02))), t)
    est = f.estimate
    assert est.usable and est.state == ScaleState.TRACKING
    assert abs(est.value / 0.04 - 1.0) < 0.01
    # a single wild observation is gated and counted
    t += FRAME_NS
    update = f.update(_obs(0.08), t)
    assert update.gated and f.gated == 1
    assert abs(f.estimate.value / 0.04 - 1.0) < 0.01
    # no observations for 1 s: the value holds, the state says so
    held = f.estimate.value
    for _ in range(30):
        t += FRAME_NS
        f.predict(t)
    assert f.estimate.value == held
    assert f.estimate.state == ScaleState.HOLDING


def test_filter_recovers_from_a_gain_step_within_one_second():
    """A 20 % gain step scales depth_relative by 1/√1.2: s rises by 9.5 %."""
    rng = np.random.default_rng(2)
    f = ScaleFilter()
    t = 0
    for _ in range(60):
        t += FRAME_NS
        f.update(_obs(0.04 * np.exp(rng.normal(0.0, 0.02))), t)
    stepped = 0.04 * np.sqrt(1.2)
    for _ in range(30):  # one second at 30 fps
        t += FRAME_NS
        f.update(_obs(stepped * np.exp(rng.normal(0.0, 0.02))), t)
    assert f.steps == 1
    assert abs(f.estimate.value / stepped - 1.0) < 0.02
