"""The seed paper's orthographic Eikonal model against analytic height fields."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from endo_sfs.evaluation import depth_error
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import reconstruct, solve
from endo_sfs.synthetic import (
    SCENE_NAMES,
    orthographic_scene,
    quantise_8bit,
    render_orthographic,
    scene_camera,
)

SIZE = 256


@functools.cache
def _scene(name: str, roughness: float, size: int = SIZE):
    camera = scene_camera(size)
    scene = orthographic_scene(name, camera)
    rendering = render_orthographic(scene.height, scene.gradient_x, scene.gradient_y, roughness)
    return camera, scene, rendering


def _solve(name, roughness, image=None, size=SIZE, **settings):
    camera, scene, rendering = _scene(name, roughness, size)
    settings.setdefault("singular_tolerance", 1e-4)
    options = SfsOptions(model="orthographic", roughness=roughness, concave=scene.concave,
                         **settings)
    return reconstruct(rendering.irradiance if image is None else image, camera, options,
                       boundary_depth=scene.boundary_depth)


def _height_error(depth, scene):
    """Mean and max |z − z*| relative to the scene's depth range (no fitting)."""
    truth = scene.height
    both = np.isfinite(truth) & np.isfinite(depth)
    depth_range = np.nanmax(truth) - np.nanmin(truth)
    error = np.abs(depth[both] - truth[both]) / depth_range
    return float(error.mean()), float(error.max()), both.sum() / np.isfinite(truth).sum()


@pytest.mark.parametrize("roughness", [0.0, 0.3])
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_noise_free_error_is_below_one_percent(name, roughness):
    _camera, scene, _ = _scene(name, roughness)
    depth = _solve(name, roughness)
    assert depth.dtype == np.float32 and depth.shape == (SIZE, SIZE)
    mean, _, coverage = _height_error(depth, scene)
    assert coverage == 1.0
    # Against the height range (the strict measure) and as the issue's
    # relative depth error after one least-squares scale.
    assert mean < 0.01
    assert depth_error(depth, scene.height).abs_rel < 0.01


@pytest.mark.parametrize("roughness", [0.0, 0.3])
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_8bit_noisy_relative_depth_error_is_below_three_percent(name, roughness):
    _, scene, rendering = _scene(name, roughness)
    noisy = quantise_8bit(rendering.irradiance, np.random.default_rng(3), noise_dn=1.0, peak=1.0)
    depth = _solve(name, roughness, noisy, singular_tolerance=1e-3)
    assert depth_error(depth, scene.height).abs_rel < 0.03


def test_smoothing_cuts_the_noise_bias_near_singular_points():
    _, scene, rendering = _scene("sphere", 0.3)
    noisy = quantise_8bit(rendering.irradiance, np.random.default_rng(4), noise_dn=1.0, peak=1.0)
    raw = _height_error(_solve("sphere", 0.3, noisy, singular_tolerance=1e-3), scene)[0]
    smoothed = _height_error(
        _solve("sphere", 0.3, noisy, singular_tolerance=1e-3, smoothing=1.0), scene
    )[0]
    assert smoothed < 0.01 < raw
    assert smoothed < 0.3 * raw


def test_first_order_converges_like_h_and_weno_beats_it_on_the_sphere():
    errors = {}
    for size in (64, 128, 256):
        _, scene, _ = _scene("sphere", 0.0, size)
        for order in (1, 3):
            depth = _solve("sphere", 0.0, size=size, order=order, singular_tolerance=1e-6,
                           tolerance=1e-10, max_iterations=200)
            errors[size, order] = _height_error(depth, scene)[0]
    for order in (1, 3):
        assert errors[64, order] > errors[128, order] > errors[256, order]
    assert 1.7 < errors[64, 1] / errors[128, 1] < 2.3  # first order
    assert 1.7 < errors[128, 1] / errors[256, 1] < 2.3
    for size in (64, 128, 256):
        assert errors[size, 3] < 0.2 * errors[size, 1]
    assert errors[256, 3] < 1e-4


def test_second_order_sweeping_is_second_order_on_the_sphere():
    errors = []
    for size in (64, 128, 256):
        _, scene, _ = _scene("sphere", 0.0, size)
        depth = _solve("sphere", 0.0, size=size, order=2, singular_tolerance=1e-6)
        errors.append(_height_error(depth, scene)[0])
    assert errors[0] / errors[1] > 3.0 and errors[1] / errors[2] > 3.0


def test_orientation_decides_bump_or_trough():
    # The same trough image read as convex comes out mirrored: wrong.
    _, scene, rendering = _scene("tube", 0.0)
    camera = scene_camera(SIZE)
    wrong = reconstruct(rendering.irradiance, camera,
                        SfsOptions(model="orthographic", singular_tolerance=1e-4, concave=False))
    assert _height_error(wrong, scene)[0] > 0.3


def test_solution_reports_sweep_statistics():
    camera, _, rendering = _scene("bumpy", 0.0)
    options = SfsOptions(model="orthographic", order=3, singular_tolerance=1e-4, tolerance=1e-9,
                         max_iterations=200)
    solution = solve(rendering.irradiance, camera, options)
    assert solution.info.converged and solution.info.updates > 0
    assert solution.grid.identity  # undistorted camera: nodes are the pixels
