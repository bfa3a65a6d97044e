"""Fusing correlated scale observations by their novelty (the views no earlier one used)."""

from __future__ import annotations

import numpy as np

from endo_flow.keyframes import Keyframe, KeyframeWindow
from endo_flow.scale import ScaleFilter, ScaleObservation, ViewNovelty, view_weights

FRAME_NS = 33_333_333


def test_novelty_is_the_weight_share_on_unused_views() -> None:
    novelty = ViewNovelty(floor=0.02)
    # three tracks over views 10, 20, 30 (the last one the current frame)
    valid = np.array([[True, True, True], [False, True, True], [True, False, True]])
    per_view = view_weights(valid, np.array([1.0, 2.0, 1.0]))
    np.testing.assert_allclose(per_view, [1 / 3 + 1 / 2, 1 / 3 + 1.0, 1 / 3 + 1.0 + 1 / 2])
    stamps = np.array([10, 20, 30])
    assert novelty.novelty(stamps, per_view) == 1.0
    novelty.use(stamps)
    # the next frame: the same keyframes and a new current view 40
    later = np.array([10, 20, 30, 40])
    weights = np.array([1.0, 1.0, 1.0, 1.0])
    assert novelty.novelty(later, weights) == 0.25
    # every view used before: the floor
    assert novelty.novelty(stamps, per_view) == 0.02
    # views that left the window are forgotten
    novelty.use(later, oldest_ns=30)
    assert novelty.novelty(np.array([10, 20]), np.ones(2)) == 1.0
    novelty.reset()
    assert novelty.novelty(later, weights) == 1.0


def test_repeated_observation_does_not_shrink_the_variance_below_its_own() -> None:
    """N copies of one draw of the error, each new by 1/N: the variance stays ~ r, not r / N."""
    obs = ScaleObservation(np.log(0.05), 0.05, 0.1, 50, 45)
    independent, discounted = ScaleFilter(), ScaleFilter()
    for k in range(1, 11):
        independent.update(obs, k * FRAME_NS)
        discounted.update(obs, k * FRAME_NS, novelty=1.0 if k == 1 else 0.1)
    assert independent.estimate.log_std < 0.017  # 0.05 / √10: converged on one draw
    assert 0.03 < discounted.estimate.log_std < 0.05  # 0.05 / √1.9
    assert not discounted.estimate.usable and independent.estimate.usable
    # the gate and the CUSUM still see the observation's own error
    assert discounted.update(ScaleObservation(np.log(0.05) + 0.3, 0.05, 0.1, 50, 45),
                             11 * FRAME_NS, novelty=0.1).gated


def test_window_view_stamps_follow_the_views_order() -> None:
    window = KeyframeWindow(capacity=5, min_step_m=0.0)
    rays = np.tile([0.0, 0.0, 1.0], (2, 1))
    for stamp in (1, 2, 3):
        window.add(Keyframe(stamp, np.eye(4), np.array([4, 5]), rays))
    np.testing.assert_array_equal(window.view_stamps(), [1, 2, 3])
    current = Keyframe(9, np.eye(4), np.array([4]), rays[:1])
    np.testing.assert_array_equal(window.view_stamps(current), [1, 2, 3, 9])
    # a current frame that is also the newest keyframe is not counted twice
    newest = Keyframe(3, np.eye(4), np.array([4]), rays[:1])
    np.testing.assert_array_equal(window.view_stamps(newest), [1, 2, 3])
