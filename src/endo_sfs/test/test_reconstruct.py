"""The public API's conventions and its behaviour on bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import endo_sfs
from endo_sfs.errors import (
    CameraMismatchError,
    InvalidOptionError,
    NoValidPixelsError,
    SfsInputError,
    UnknownModelError,
)
from endo_sfs.evaluation import depth_error
from endo_sfs.relative_depth import surface_normals
from endo_sfs.synthetic import near_light_surface, render_near_light, scene_camera

SIZE = 96


@pytest.fixture(scope="module")
def scene():
    camera = scene_camera(SIZE)
    mask = camera.fov_mask(0.48 * SIZE)
    return camera, mask, render_near_light(camera, near_light_surface("tilted_plane"))


def test_reconstruct_is_exported_and_returns_float32_depth(scene):
    camera, mask, rendering = scene
    depth = endo_sfs.reconstruct(rendering.irradiance.astype(np.float32), camera, mask=mask)
    assert depth.shape == (SIZE, SIZE) and depth.dtype == np.float32
    assert np.all(np.isnan(depth[~mask]))
    assert depth_error(depth, rendering.depth, mask).abs_rel < 0.01


def test_all_dark_all_saturated_and_all_nan_frames_raise_a_named_error(scene):
    camera, _mask, _rendering = scene
    for frame in (np.zeros((SIZE, SIZE)), np.full((SIZE, SIZE), np.nan)):
        with pytest.raises(NoValidPixelsError, match="all dark, saturated, NaN"):
            endo_sfs.reconstruct(frame, camera)
    with pytest.raises(NoValidPixelsError):
        endo_sfs.reconstruct(np.full((SIZE, SIZE), 1.0), camera,
                             endo_sfs.SfsOptions(saturation=1.0))


def test_nan_and_saturated_pixels_are_excluded_not_fatal(scene):
    camera, mask, rendering = scene
    image = rendering.irradiance.copy()
    image[40:44, 40:44] = np.nan
    image[60:62, 30:34] = 9.0
    depth = endo_sfs.reconstruct(image, camera, endo_sfs.SfsOptions(saturation=5.0), mask=mask)
    assert np.all(np.isnan(depth[40:44, 40:44])) and np.all(np.isnan(depth[60:62, 30:34]))
    assert np.isfinite(depth[mask]).mean() > 0.98


def test_camera_of_a_different_size_is_rejected(scene):
    camera, _, rendering = scene
    with pytest.raises(CameraMismatchError, match="camera_info is 96x96"):
        endo_sfs.reconstruct(rendering.irradiance[:, :80], camera)


@pytest.mark.parametrize(
    ("settings", "mask", "error"),
    [
        ({"model": "photometric_stereo"}, None, UnknownModelError),
        ({"roughness": 0.9}, None, SfsInputError),
        ({"solve_scale": 0.0}, None, SfsInputError),
        ({"order": 4}, None, SfsInputError),
        ({}, np.ones((3, 3), bool), SfsInputError),
    ],
)
def test_bad_arguments_raise_named_errors(scene, settings, mask, error):
    camera, _, rendering = scene
    with pytest.raises(error):
        endo_sfs.reconstruct(rendering.irradiance, camera, endo_sfs.SfsOptions(**settings),
                             mask=mask)


def test_options_are_frozen_validated_when_built_and_take_integers_for_floats():
    options = endo_sfs.SfsOptions(solve_scale=1, roughness=0)
    assert isinstance(options.solve_scale, float) and isinstance(options.roughness, float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.roughness = 0.3  # type: ignore[misc]
    assert dataclasses.replace(options, roughness=0.3).roughness == 0.3
    with pytest.raises(InvalidOptionError, match=r"solve_scale must be in \(0, 1\], got 5.0"):
        dataclasses.replace(options, solve_scale=5.0)
    with pytest.raises(InvalidOptionError, match="order must be an integer"):
        endo_sfs.SfsOptions(order=2.5)  # type: ignore[arg-type]
    with pytest.raises(InvalidOptionError, match="saturation must exceed dark_level"):
        endo_sfs.SfsOptions(dark_level=2.0, saturation=1.0)
    with pytest.raises(SfsInputError, match="options must be an SfsOptions"):
        endo_sfs.solve(np.ones((SIZE, SIZE)), scene_camera(SIZE), {"roughness": 0.3})


def test_threads_zero_takes_two_threads_only_on_large_solve_grids(scene, monkeypatch):
    from endo_sfs import relative_depth
    from endo_sfs.options import TWO_THREAD_PIXELS

    auto = endo_sfs.SfsOptions(threads=0)
    assert TWO_THREAD_PIXELS == 150_000
    assert auto.solve_threads(480, 640) == 2  # 307 200 nodes
    assert dataclasses.replace(auto, solve_scale=0.5).solve_threads(480, 640) == 1  # 76 800
    assert auto.solve_threads(300, 500) == 2 and auto.solve_threads(300, 499) == 1
    assert endo_sfs.SfsOptions(threads=3).solve_threads(480, 640) == 3  # set: as given
    for bad in (np.ones(SIZE), np.ones((SIZE, SIZE, 3))):  # named, as with threads 1 (review)
        with pytest.raises(SfsInputError, match=r"single-channel|2-D|shape"):
            endo_sfs.solve(bad, scene_camera(SIZE), auto)
    with pytest.raises(InvalidOptionError, match=r"threads must be >= 1, or 0 .*got -1"):
        endo_sfs.SfsOptions(threads=-1)
    # solve() runs a small grid given threads 0 on one thread: the one-thread
    # solve, bit for bit.
    counts: list[int] = []
    numba_threads = relative_depth._numba_threads

    def recording(threads: int):  # type: ignore[no-untyped-def]
        counts.append(threads)
        return numba_threads(threads)

    monkeypatch.setattr(relative_depth, "_numba_threads", recording)
    camera, mask, rendering = scene
    image = rendering.irradiance.astype(np.float32)
    solved = endo_sfs.solve(image, camera, dataclasses.replace(auto, mask_highlights=True),
                            mask=mask)
    assert counts and set(counts) == {1}, counts
    one = endo_sfs.solve(image, camera, endo_sfs.SfsOptions(threads=1, mask_highlights=True),
                         mask=mask)
    np.testing.assert_array_equal(solved.depth, one.depth)


def test_non_float_and_colour_images_are_rejected(scene):
    camera, _, _ = scene
    with pytest.raises(SfsInputError, match="linear float"):
        endo_sfs.reconstruct(np.ones((SIZE, SIZE), np.uint8), camera)
    with pytest.raises(SfsInputError, match="single-channel"):
        endo_sfs.reconstruct(np.ones((SIZE, SIZE, 3)), camera)


def test_errors_derive_from_the_project_base_class():
    from endo_io.errors import Endo3dError

    for error in (CameraMismatchError, NoValidPixelsError, SfsInputError, UnknownModelError):
        assert issubclass(error, Endo3dError)


def test_surface_normals_of_the_tilted_plane_match_its_normal(scene):
    camera, mask, rendering = scene
    normals = surface_normals(rendering.depth, camera)
    plane = near_light_surface("tilted_plane")
    expected = np.asarray(plane.normal) / np.linalg.norm(plane.normal)
    inner = mask & np.all(np.isfinite(normals), axis=-1)
    assert inner.sum() > 0.9 * mask.sum()
    np.testing.assert_allclose(normals[inner], np.broadcast_to(expected, normals[inner].shape),
                               atol=1e-4)


def test_a_near_light_solve_times_its_stages_and_reuses_its_buffers_exactly(scene):
    from endo_sfs import near_light
    from endo_sfs.relative_depth import STAGES, solve

    camera, mask, rendering = scene
    image = rendering.irradiance.astype(np.float32)
    options = endo_sfs.SfsOptions(mask_highlights=True, solve_scale=0.5)
    first = solve(image, camera, options, mask=mask)
    assert set(first.timings) == set(STAGES)
    assert all(seconds >= 0.0 for seconds in first.timings.values())
    assert options.threads > 1 or first.timings["finish"] == 0.0  # no two-thread phase
    # A frame of another grid in between, then the same frame again on the
    # reused buffers, then on fresh ones: the same depth bit for bit (one thread).
    solve(image, camera, dataclasses.replace(options, solve_scale=1.0), mask=mask)
    again = solve(image, camera, options, mask=mask, warm_start=first)
    near_light._WORKSPACES.clear()
    fresh = solve(image, camera, options, mask=mask, warm_start=first)
    np.testing.assert_array_equal(again.depth, fresh.depth)
    np.testing.assert_array_equal(again.node_solution, fresh.node_solution)
    assert depth_error(again.depth, rendering.depth, mask).abs_rel < 0.01
