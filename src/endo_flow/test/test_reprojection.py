"""The scale-only reprojection fit against known points, poses and a perfect or spoiled SFS."""

from __future__ import annotations

import numpy as np
import pytest

from endo_flow.keyframes import TrackViews
from endo_flow.pipeline import FlowOptions
from endo_flow.reprojection import fit_log_scale, track_leverage
from endo_flow.triangulation import TriangulationGates, triangulate

from .conftest import synthetic_track_views

#: metres of depth per unit of depth_relative (the scale to recover)
SCALE = 0.04
AXIS = np.array([0.0, 0.0, 1.0])


def _views(points: np.ndarray, centres: np.ndarray, angle_noise: float = 0.0,
           seed: int = 0) -> TrackViews:
    """Every point seen from every centre (cameras looking along +z), relative depth exact."""
    return synthetic_track_views(points, centres, angle_noise=angle_noise, seed=seed,
                                 scale=SCALE)


def test_exact_views_give_the_scale_from_any_start():
    rng = np.random.default_rng(1)
    points = rng.uniform([-0.02, -0.02, 0.03], [0.02, 0.02, 0.06], (60, 3))
    centres = np.array([[0.0, 0.0, 0.0], [0.002, 0.001, 0.0], [0.004, -0.001, 0.002],
                        [0.006, 0.0, 0.003]])
    views = _views(points, centres)
    for reference in ("all", "newest"):
        for start in (np.log(SCALE) - 0.3, np.log(SCALE) + 0.3):
            fit = fit_log_scale(views, np.ones(60, bool), np.ones(60), start,
                                reference=reference)
            assert fit is not None
            assert abs(fit.log_scale - np.log(SCALE)) < 1e-6, (reference, start)
            assert fit.tracks == 60
            assert fit.pairs == 60 * (3 if reference == "newest" else 12)
            np.testing.assert_allclose(fit.leverage.sum(), 1.0)


def test_no_gate_no_selection_bias_at_short_baselines():
    """2.8 mm baseline, 3 mrad ray noise, points 30–50 mm away (parallax 3–5°).

    A 4° gate on the rays' own parallax keeps the tracks whose noise widened
    it, which triangulate 3–4 % too near (test_triangulation.py); the fit,
    over every track with no gate, is within 1 % (measured −0.12 to +0.14 %
    over seeds 3–6, the gate's median −2.9 to −3.6 %), and tracks with
    little parallax have little leverage.
    """
    rng = np.random.default_rng(3)
    n = 2000
    points = rng.uniform([-0.02, -0.02, 0.03], [0.02, 0.02, 0.05], (n, 3))
    centres = np.array([[0.0, 0.0, 0.0], [1.4e-3, 0.0, 0.0], [2.8e-3, 0.0, 0.0]])
    views = _views(points, centres, angle_noise=3e-3, seed=3)
    gated = triangulate(views, TriangulationGates(min_parallax_rad=np.radians(4.0)),
                        optical_axis=AXIS)
    bias_gate = np.median(np.log(gated.depth_m[gated.accepted] / points[gated.accepted, 2]))
    assert bias_gate < -0.02
    fit = fit_log_scale(views, np.ones(n, bool), np.ones(n), float(np.log(SCALE)))
    assert fit is not None
    assert abs(fit.log_scale - np.log(SCALE)) < 0.01, fit.log_scale - np.log(SCALE)
    # its standard error is honest: the error is within 3 of them
    assert abs(fit.log_scale - np.log(SCALE)) < 3.0 * fit.std
    # leverage grows with the squared parallax: the third with the most holds most of it
    angle = np.arccos(np.sum((points - centres[0]) * (points - centres[-1]), axis=1)
                      / np.linalg.norm(points - centres[0], axis=1)
                      / np.linalg.norm(points - centres[-1], axis=1))
    widest = angle >= np.quantile(angle, 2 / 3)
    assert fit.leverage[widest].sum() > 0.45
    leverage = track_leverage(views, np.ones(n, bool), float(np.log(SCALE)))
    assert np.corrcoef(leverage, angle**2)[0, 1] > 0.9


def test_wild_tracks_get_no_weight():
    """A fifth of the tracks with depth_relative 30 % off (SFS wrong there): the fit stays."""
    rng = np.random.default_rng(2)
    n = 200
    points = rng.uniform([-0.02, -0.02, 0.03], [0.02, 0.02, 0.05], (n, 3))
    centres = np.array([[0.0, 0.0, 0.0], [2e-3, 0.0, 0.0], [4e-3, 0.0, 0.0], [6e-3, 0.0, 0.0]])
    views = _views(points, centres, angle_noise=1e-3, seed=2)
    assert views.relative is not None
    wild = rng.random(n) < 0.2
    views.relative[wild] *= 1.3
    fit = fit_log_scale(views, np.ones(n, bool), np.ones(n), float(np.log(SCALE)) + 0.1)
    assert fit is not None
    assert abs(fit.log_scale - np.log(SCALE)) < 0.015, fit.log_scale - np.log(SCALE)


def test_options_name_the_observation():
    assert FlowOptions(scale_observation="reprojection", parallax_gate="none")
    with pytest.raises(ValueError, match="scale_observation"):
        FlowOptions(scale_observation="bundle")
    with pytest.raises(ValueError, match="reprojection_reference"):
        FlowOptions(reprojection_reference="oldest")
