"""A frame with no warm start: the coarse start, and the warm-up on the stream's camera.

A near-light solve with no warm start at solve_scale >= 0.5 first solves the
frame at a quarter of the scale (``relative_depth.COARSE_START_FACTOR``) and
starts from that. It must reach the plain cold solve's answer (to the
solver's tolerance semantics: isolated pixels may differ by up to ~1e-3
relative, docs/sfs.md) and, on noisy 8-bit frames, for fewer node solves.
``warm_up_frame`` builds the camera's solve grids (the frame's scale and the
coarse start's) before the first real frame.
"""

from __future__ import annotations

import numpy as np
import pytest

from endo_sfs import grid as grid_module
from endo_sfs import relative_depth
from endo_sfs.grid import solve_grid
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import solve
from endo_sfs.synthetic import near_light_surface, quantise_8bit, render_near_light, scene_camera
from endo_sfs.warm_up import warm_up_frame


def _median_scaled_abs_rel(depth: np.ndarray, truth: np.ndarray) -> float:
    both = np.isfinite(depth) & np.isfinite(truth)
    scaled = depth[both] * np.median(truth[both]) / np.median(depth[both])
    return float(np.mean(np.abs(scaled - truth[both]) / truth[both]))


@pytest.mark.parametrize(("surface", "seed"), [("bumpy", 1), ("sphere", 2)])
def test_a_coarse_start_reaches_the_cold_solution_for_fewer_node_solves(
    monkeypatch: pytest.MonkeyPatch, surface: str, seed: int
) -> None:
    camera = scene_camera(256)
    rendering = render_near_light(camera, near_light_surface(surface), roughness=0.3)
    image = quantise_8bit(rendering.irradiance, np.random.default_rng(seed), noise_dn=3.0)
    options = SfsOptions(model="near_light", roughness=0.3, threads=1)
    started = solve(image, camera, options)
    monkeypatch.setattr(relative_depth, "COARSE_START_MIN_SCALE", 2.0)  # the plain cold solve
    cold = solve(image, camera, options)
    ratio = started.depth / cold.depth
    assert np.array_equal(np.isfinite(started.depth), np.isfinite(cold.depth))
    assert float(np.nanmedian(np.abs(ratio - 1.0))) < 1e-5
    assert float(np.nanmax(np.abs(ratio - 1.0))) < 1e-3  # measured 4.1e-4 / 1.1e-4
    # same accuracy against the rendered truth
    assert abs(_median_scaled_abs_rel(started.depth, rendering.depth)
               - _median_scaled_abs_rel(cold.depth, rendering.depth)) < 1e-4
    # fewer node solves (measured 2.34 against 3.76 per node on the bumpy surface,
    # 1.44 against 3.88 on the sphere)
    assert started.info.updates < 0.8 * cold.info.updates


def test_no_coarse_start_below_half_scale_or_with_a_warm_start(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    camera = scene_camera(64)
    image = render_near_light(camera, near_light_surface("sphere")).irradiance
    calls: list[float] = []
    real_solve = relative_depth.solve

    def counting(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(args[2].solve_scale)
        return real_solve(*args, **kwargs)

    monkeypatch.setattr(relative_depth, "solve", counting)
    previous = real_solve(image, camera, SfsOptions(solve_scale=1.0))
    assert calls == [0.25]  # the cold solve at 1.0 started from one at 0.25, not recursively
    calls.clear()
    real_solve(image, camera, SfsOptions(solve_scale=1.0), warm_start=previous)
    real_solve(image, camera, SfsOptions(solve_scale=0.4))
    real_solve(image, camera, SfsOptions(model="orthographic", solve_scale=1.0))
    assert calls == []


def test_the_warm_up_builds_the_cameras_solve_grids() -> None:
    camera = scene_camera(96)
    options = SfsOptions(solve_scale=1.0)
    grid_module._GRID_CACHE.clear()
    seconds = warm_up_frame(camera, options)
    assert seconds > 0.0
    cached = list(grid_module._GRID_CACHE.values())
    # the frame's grid and its coarse start's, both of this camera, served from the cache
    assert len(cached) == 2
    assert solve_grid(camera, "stereographic", 1.0) is cached[1]
    assert solve_grid(camera, "stereographic", 0.25) is cached[0]
