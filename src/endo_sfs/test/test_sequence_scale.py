"""The oracle scale of a sequence: exp(median ln(d*/d)) over every paired pixel."""

from __future__ import annotations

import numpy as np
import pytest

from endo_sfs.errors import NoCommonPixelsError, SfsInputError
from endo_sfs.evaluation import depth_error, sequence_scale


def test_the_oracle_recovers_a_known_scale_through_noise_and_invalid_pixels() -> None:
    rng = np.random.default_rng(3)
    truths = [rng.uniform(0.02, 0.09, (48, 64)) for _ in range(4)]
    # relative depth: the truth / 0.0193 with 12 % log-normal error, some pixels invalid
    estimates = []
    for truth in truths:
        d = truth / 0.0193 * np.exp(rng.normal(0.0, 0.12, truth.shape))
        d[rng.random(truth.shape) < 0.1] = np.nan
        d[0, :5] = -1.0  # not a depth
        estimates.append(d.astype(np.float32))
    truths[0][5, :] = np.nan
    s = sequence_scale(estimates, truths)
    assert s == pytest.approx(0.0193, rel=0.005)
    # a least-squares fit of d/d* to 1 sits lower by about the squared spread
    ratio = np.concatenate([(e / t).ravel() for e, t in zip(estimates, truths, strict=True)])
    ratio = np.where(ratio > 0, ratio, np.nan)
    least_squares = depth_error(ratio, np.ones_like(ratio), scaling="least_squares").scale
    assert least_squares < s
    assert least_squares == pytest.approx(0.0193 * np.exp(-1.5 * 0.12**2), rel=0.01)


def test_the_oracle_names_what_is_missing() -> None:
    with pytest.raises(NoCommonPixelsError, match="no pixel"):
        sequence_scale([np.full((4, 4), np.nan)], [np.ones((4, 4))])
    with pytest.raises(NoCommonPixelsError, match="no pixel"):
        sequence_scale([], [])
    with pytest.raises(SfsInputError, match="shape"):
        sequence_scale([np.ones((4, 4))], [np.ones((4, 5))])
    with pytest.raises(ValueError):
        sequence_scale([np.ones((4, 4))], [])  # unpaired
