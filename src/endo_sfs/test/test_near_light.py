"""Near-light perspective SFS against analytic ground truth.

Images are rendered with the model's own forward physics (light at the
optical centre, I = R(cos θ)/r², Oren–Nayar or Lambertian) by ray geometry
in endo_sfs.synthetic; the depth truth is analytic.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from endo_sfs.errors import InvalidOptionError
from endo_sfs.evaluation import depth_error
from endo_sfs.near_light import global_shift
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import reconstruct, solve
from endo_sfs.synthetic import (
    SCENE_NAMES,
    near_light_surface,
    quantise_8bit,
    render_near_light,
    scene_camera,
)

SIZE = 256


@functools.cache
def _camera(size: int = SIZE, distortion: float = 0.0):
    return scene_camera(size, distortion=distortion)


@functools.cache
def _scene(name: str, roughness: float, size: int = SIZE, distortion: float = 0.0):
    camera = _camera(size, distortion)
    mask = camera.fov_mask(0.48 * size)
    return camera, mask, render_near_light(camera, near_light_surface(name), roughness)


@pytest.mark.parametrize("roughness", [0.0, 0.3])
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_noise_free_relative_depth_error_is_below_one_percent(name, roughness):
    camera, mask, rendering = _scene(name, roughness)
    depth = reconstruct(rendering.irradiance, camera, SfsOptions(roughness=roughness), mask=mask)
    assert depth.shape == (SIZE, SIZE) and depth.dtype == np.float32
    error = depth_error(depth, rendering.depth, mask)
    assert error.coverage > 0.999
    assert error.abs_rel < 0.01
    assert error.p95_rel < 0.01
    # albedo × light = 1 is the convention of the renderer too: no scale left.
    assert error.scale == pytest.approx(1.0, abs=2e-3)


@pytest.mark.parametrize("roughness", [0.0, 0.3])
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_8bit_noisy_relative_depth_error_is_below_three_percent(name, roughness):
    camera, mask, rendering = _scene(name, roughness)
    noisy = quantise_8bit(rendering.irradiance, np.random.default_rng(7), noise_dn=1.0)
    depth = reconstruct(noisy, camera, SfsOptions(roughness=roughness), mask=mask)
    error = depth_error(depth, rendering.depth, mask)
    assert error.coverage > 0.99
    assert error.abs_rel < 0.03


@pytest.mark.parametrize("name", ["sphere", "bumpy"])
def test_masked_highlights_restore_the_diffuse_solution(name):
    # Wet tissue: a white lobe 5·cos^120 θ on top of Oren–Nayar (the
    # simulator's colon gloss over its albedo), clipped at twice the diffuse
    # peak and marked NaN there, as endo_calib marks saturated pixels. Read as
    # diffuse shading the highlight pulls the surface towards the camera;
    # masked, the rest is recovered from the diffuse data alone.
    camera = _camera()
    diffuse = render_near_light(camera, near_light_surface(name), 0.3).irradiance
    mask = camera.fov_mask(0.48 * SIZE) & np.isfinite(diffuse)
    rendering = render_near_light(camera, near_light_surface(name), 0.3, 5.0, 120.0)
    image = np.where(rendering.irradiance >= 2.0 * np.nanmax(diffuse[mask]), np.nan,
                     rendering.irradiance)
    assert np.isnan(image[mask]).any()  # the highlight saturates
    ignored = depth_error(reconstruct(image, camera, SfsOptions(roughness=0.3), mask=mask),
                          rendering.depth, mask)
    masked = depth_error(
        reconstruct(image, camera, SfsOptions(roughness=0.3, mask_highlights=True), mask=mask),
        rendering.depth, mask,
    )
    assert ignored.abs_rel > 0.04
    assert masked.abs_rel < 0.03 and masked.abs_rel < ignored.abs_rel / 2.5
    assert masked.coverage > 0.85


def test_wrong_roughness_gives_a_larger_error():
    # The roughness matters: solving a σ = 0.3 image as Lambertian is worse.
    camera, mask, rendering = _scene("bumpy", 0.3)
    right = depth_error(
        reconstruct(rendering.irradiance, camera, SfsOptions(roughness=0.3), mask=mask),
        rendering.depth, mask,
    )
    wrong = depth_error(
        reconstruct(rendering.irradiance, camera, SfsOptions(roughness=0.0), mask=mask),
        rendering.depth, mask,
    )
    assert wrong.abs_rel > 5 * right.abs_rel


@pytest.mark.parametrize("name", ["sphere", "tube"])
def test_lens_distortion_is_handled_through_the_ray_table(name):
    camera, mask, rendering = _scene(name, 0.3, distortion=-0.25)
    assert np.any(camera.D)
    handled = depth_error(
        reconstruct(rendering.irradiance, camera, SfsOptions(roughness=0.3), mask=mask),
        rendering.depth, mask,
    )
    assert handled.abs_rel < 0.001 and handled.coverage > 0.999
    # Ignoring the distortion (same K, no D) is several times worse.
    pinhole = _camera(SIZE, 0.0)
    ignored = reconstruct(rendering.irradiance, pinhole, SfsOptions(roughness=0.3), mask=mask)
    assert depth_error(ignored, rendering.depth, mask).abs_rel > 4 * handled.abs_rel


def test_error_falls_with_grid_refinement_and_order():
    # Away from the grazing silhouette (cos θ > 0.3), where the solution is
    # smooth: first order converges like h, the second-order and WENO
    # schemes faster and below it.
    errors = {}
    for size in (64, 128, 256):
        camera, mask, rendering = _scene("sphere", 0.0, size)
        distance = rendering.depth / camera.unit_rays()[..., 2]
        with np.errstate(invalid="ignore"):
            interior = mask & (rendering.irradiance * distance**2 > 0.3)
        for order in (1, 2, 3):
            options = SfsOptions(order=order, tolerance=1e-9, max_iterations=300)
            depth = reconstruct(rendering.irradiance, camera, options, mask=mask)
            errors[size, order] = depth_error(depth, rendering.depth, interior).abs_rel
    for order in (1, 2, 3):
        assert errors[64, order] > errors[128, order] > errors[256, order]
    assert errors[64, 1] / errors[256, 1] > 3.5  # about h
    assert errors[64, 2] / errors[256, 2] > 10.0  # about h²
    for size in (128, 256):
        assert errors[size, 3] < errors[size, 2] < errors[size, 1]


def test_albedo_scales_depth_by_inverse_square_root_only():
    camera, mask, rendering = _scene("tilted_plane", 0.0)
    unit = reconstruct(rendering.irradiance, camera, mask=mask)
    dimmer = reconstruct(0.25 * rendering.irradiance, camera, mask=mask)
    # I' = ρ·I  ⇒  r' = r/√ρ exactly: a constant factor 2, no renormalisation.
    ratio = dimmer / unit
    assert np.nanmax(np.abs(ratio - 2.0)) < 1e-4


def test_warm_start_reaches_the_same_depth_with_less_work():
    camera, mask, rendering = _scene("bumpy", 0.3)
    options = SfsOptions(roughness=0.3, tolerance=1e-7)
    cold = solve(rendering.irradiance, camera, options, mask=mask)
    # The next frame: the camera moved 1 % closer (irradiance × 1.0201).
    moved = rendering.irradiance * 1.01**2
    warm = solve(moved, camera, options, mask=mask, warm_start=cold)
    fresh = solve(moved, camera, options, mask=mask)
    assert warm.info.converged and fresh.info.converged
    np.testing.assert_allclose(warm.depth, fresh.depth, rtol=1e-5)
    np.testing.assert_allclose(warm.depth, cold.depth / 1.01, rtol=1e-5)
    assert warm.info.updates <= 1.05 * fresh.info.updates
    # A warm start given as the previous (H, W) depth works the same way.
    from_depth = solve(moved, camera, options, mask=mask, warm_start=cold.depth)
    np.testing.assert_allclose(from_depth.depth, fresh.depth, rtol=1e-5)


def test_solve_scale_solves_a_coarser_grid_and_upsamples():
    camera, mask, rendering = _scene("bumpy", 0.0)
    full = solve(rendering.irradiance, camera, mask=mask)
    half = solve(rendering.irradiance, camera, SfsOptions(solve_scale=0.5), mask=mask)
    assert half.node_solution.size < 0.3 * full.node_solution.size
    assert half.depth.shape == (SIZE, SIZE)
    assert depth_error(half.depth, rendering.depth, mask).abs_rel < 0.01


def test_masked_pixels_are_nan_and_get_no_data():
    camera, mask, rendering = _scene("sphere", 0.0)
    image = rendering.irradiance.copy()
    hole = np.zeros_like(mask)
    hole[100:120, 100:120] = True
    image[hole] = 50.0  # garbage under the mask must not matter
    depth = reconstruct(image, camera, mask=mask & ~hole)
    assert np.all(np.isnan(depth[~mask])) and np.all(np.isnan(depth[hole]))
    rest = mask & ~hole
    rest[96:124, 96:124] = False  # allow the state-constraint edge of the hole
    assert depth_error(depth, rendering.depth, rest).abs_rel < 0.01


def test_two_threads_reach_the_same_depth_as_one():
    # 256² with the circular mask is ~51 000 nodes: the first pass is split.
    camera, mask, rendering = _scene("bumpy", 0.3)
    one = solve(rendering.irradiance, camera, SfsOptions(roughness=0.3, tolerance=1e-7), mask=mask)
    two_threads = SfsOptions(roughness=0.3, tolerance=1e-7, threads=2)
    two = solve(rendering.irradiance, camera, two_threads, mask=mask)
    assert np.isfinite(two.node_solution).sum() >= 20000
    assert one.info.converged and two.info.converged
    np.testing.assert_allclose(two.depth, one.depth, rtol=1e-5)
    moved = rendering.irradiance * 1.01**2
    warm = solve(moved, camera, two_threads, mask=mask, warm_start=two)
    np.testing.assert_allclose(warm.depth, one.depth / 1.01, rtol=1e-5)
    assert depth_error(warm.depth, rendering.depth, mask).abs_rel < 0.01


def test_threads_must_be_positive_or_zero_for_auto():
    with pytest.raises(InvalidOptionError, match="threads must be >= 1, or 0"):
        SfsOptions(threads=-1)


def test_a_poorly_predicted_order_switches_the_chain_to_sweeps_and_back():
    from endo_sfs.relative_depth import (
        FIRST_PASS_WORK_LIMIT,
        RETRY_FIRST_PASS,
        RETRY_FIRST_PASS_MAX,
        retry_interval,
    )

    camera, mask, rendering = _scene("bumpy", 0.3)
    rng = np.random.default_rng(5)
    previous = clean = solve(rendering.irradiance, camera, SfsOptions(roughness=0.3), mask=mask)
    assert previous.ordered_work is not None and previous.ordered_work < FIRST_PASS_WORK_LIMIT
    # A previous frame whose order says nothing about this one: new noise
    # on every frame scrambles the order of neighbouring nodes.
    modes, retries = [], []
    second_retry = 3 * RETRY_FIRST_PASS
    for k in range(second_retry + 2):
        image = rendering.irradiance * np.exp(rng.normal(0.0, 0.05, rendering.irradiance.shape))
        solution = solve(image, camera, SfsOptions(roughness=0.3, threads=2, tolerance=1e-8),
                         mask=mask, warm_start=previous)
        modes.append(solution.frames_since_ordered == 0)
        retries.append(solution.ordered_retries)
        assert solution.info.converged
        if k <= RETRY_FIRST_PASS + 1 or k == second_retry:
            fresh = solve(image, camera, SfsOptions(roughness=0.3, tolerance=1e-8), mask=mask)
            np.testing.assert_allclose(solution.depth, fresh.depth, rtol=1e-5)
        previous = solution
    assert previous.ordered_work > FIRST_PASS_WORK_LIMIT
    # Ordered, then sweeps until the retry, then ordered again; that retry
    # cost too much as well, so the next waits twice as long.
    assert modes[0] and not modes[1] and modes[RETRY_FIRST_PASS]
    assert not any(modes[1:RETRY_FIRST_PASS])
    assert retries[0] == 0 and retries[RETRY_FIRST_PASS] == 1
    assert not any(modes[RETRY_FIRST_PASS + 1:second_retry]) and modes[second_retry]
    assert retries[second_retry] == 2 and retries[-1] == 2
    assert [retry_interval(n) for n in range(5)] == [
        RETRY_FIRST_PASS, 2 * RETRY_FIRST_PASS, 4 * RETRY_FIRST_PASS,
        min(8 * RETRY_FIRST_PASS, RETRY_FIRST_PASS_MAX), RETRY_FIRST_PASS_MAX,
    ]
    # A chain whose ordered pass pays again is back to the first interval.
    chain = dataclasses.replace(
        clean, ordered_work=previous.ordered_work, ordered_retries=previous.ordered_retries,
        frames_since_ordered=10**6,
    )
    ordered = solve(rendering.irradiance, camera, SfsOptions(roughness=0.3), mask=mask,
                    warm_start=chain)
    assert ordered.frames_since_ordered == 0
    assert ordered.ordered_work < FIRST_PASS_WORK_LIMIT and ordered.ordered_retries == 0


@pytest.mark.parametrize("count", [0, 1, 2, 7, 1000, 1001])
def test_global_shift_is_minus_half_the_median_log_ratio(count):
    # The shift logs only the middle ratio(s): the same value, bit for bit,
    # as the median of every logged ratio over the same nodes.
    rng = np.random.default_rng(count)
    shape = (40, 50)
    valid = np.zeros(shape, dtype=bool)
    valid.ravel()[rng.choice(valid.size, size=count, replace=False)] = True
    previous = rng.normal(-1.0, 0.1, shape)
    intensity = rng.uniform(0.2, 2.0, shape)
    before = intensity * rng.uniform(0.9, 1.1, shape)
    # nodes that must not count: unknown before, or not positive and finite
    previous[0, ::3] = np.nan
    intensity[1, ::4] = 0.0
    before[2, ::5] = np.inf
    every = np.ones(shape, dtype=bool)
    shift = global_shift(previous, every & valid, intensity, before)
    sampled = (valid & np.isfinite(previous) & (intensity > 0) & (before > 0)
               & np.isfinite(intensity) & np.isfinite(before))[::2, ::2]
    # math.log is the C library's logarithm, as the kernels' np.log
    ratios = [math.log(r) for r in intensity[::2, ::2][sampled] / before[::2, ::2][sampled]]
    expected = -0.5 * float(np.median(ratios)) if ratios else 0.0
    assert shift == expected
    assert global_shift(previous, valid, intensity, None) == 0.0
