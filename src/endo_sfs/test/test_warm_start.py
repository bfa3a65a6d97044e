"""Warm starts across frames and workers: frame ownership, pose prediction, the chain."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from endo_io.camera import CameraModel
from endo_sfs.errors import SfsInputError
from endo_sfs.options import SfsOptions
from endo_sfs.pose_prediction import (
    estimate_metres_per_unit,
    predict_warm_start,
    relative_motion,
)
from endo_sfs.relative_depth import solve
from endo_sfs.synthetic import posed_tube_sequence
from endo_sfs.warm_start import (
    FrameDealer,
    WarmStartChain,
    frame_owner,
    solution_from_depth,
)

PERIOD_NS = 33_333_333
#: Metres per unit of the renderings' depth (a tube of radius 1 unit = 20 mm).
METRES_PER_UNIT = 0.02


def _posed_tube(frames: int, width: int = 128, height: int = 96):
    """Renderings of a camera moving in a world-fixed tube, with T_world_camera in metres."""
    focal = width / 2.0
    camera = CameraModel.pinhole(width, height, focal, focal, (width - 1) / 2, (height - 1) / 2)
    out = []
    for rendering, pose in posed_tube_sequence(camera, frames, 0.3):
        metric = pose.copy()
        metric[:3, 3] *= METRES_PER_UNIT
        out.append((rendering, metric))
    return camera, camera.fov_mask(0.5 * height), out


def test_frame_owner_deals_consecutive_frames_round_robin_whatever_the_jitter() -> None:
    rng = np.random.default_rng(0)
    start = 1_764_547_200 * 10**9 + 12_345_678  # an arbitrary epoch stamp, off the slots
    stamps = start + np.arange(300) * PERIOD_NS + rng.integers(-8_000_000, 8_000_000, 300)
    for count in (1, 2, 3):
        dealers = [FrameDealer(count, PERIOD_NS) for _ in range(count)]
        owners = [dealers[0].owner(int(s)) for s in stamps]
        # each worker gets every count-th frame, in turn, after the first few
        # frames have set the phase
        steps = [(b - a) % count for a, b in itertools.pairwise(owners[4:])]
        assert steps == [1 % count] * len(steps)
        assert np.bincount(owners[4:], minlength=count).min() >= (296 // count)
        # a worker that joins late agrees once it has seen the same frames
        late = dealers[-1]
        late_owners = [late.owner(int(s)) for s in stamps[150:]]
        assert late_owners[16:] == owners[166:]
    # without the phase, frames near a slot boundary would be dealt by jitter
    fixed = [frame_owner(int(s), 2, PERIOD_NS) for s in stamps]
    assert any((b - a) % 2 != 1 for a, b in itertools.pairwise(fixed))
    with pytest.raises(SfsInputError):
        frame_owner(0, 0, PERIOD_NS)


def test_pose_prediction_moves_the_previous_solution_onto_the_next() -> None:
    camera, mask, frames = _posed_tube(2)
    options = SfsOptions(roughness=0.3, tolerance=1e-8)
    first = solve(frames[0][0].irradiance, camera, options, mask=mask)
    second = solve(frames[1][0].irradiance, camera, options, mask=mask)
    motion = relative_motion(frames[0][1], frames[1][1])
    predicted = predict_warm_start(first, motion, metres_per_unit=METRES_PER_UNIT)
    truth = second.node_solution
    as_is = np.nanmedian(np.abs(first.node_solution - truth))
    moved = np.nanmedian(np.abs(predicted.node_solution - truth))
    # the camera moved 3 % of the radius: the moved surface is far closer
    assert as_is > 0.05
    assert moved < 0.002 * as_is
    # the part of the wall the previous frame saw (the camera approached it)
    assert np.isfinite(predicted.node_solution[np.isfinite(truth)]).mean() > 0.8
    # here the translation dominates: without the scale there is no gain
    rotated = predict_warm_start(first, motion, metres_per_unit=None)
    assert np.nanmedian(np.abs(rotated.node_solution - truth)) > 0.5 * as_is
    # and the fitted scale is the true one
    fitted = estimate_metres_per_unit(first, second, motion)
    assert fitted == pytest.approx(METRES_PER_UNIT, rel=0.05)
    # the solve from the prediction is the same fixed point
    warm = solve(frames[1][0].irradiance, camera, options, mask=mask, warm_start=predicted)
    both = np.isfinite(second.depth)
    assert np.max(np.abs(warm.depth[both] / second.depth[both] - 1.0)) < 1e-5


def test_a_rebuilt_depth_is_the_solution_it_came_from() -> None:
    camera, mask, frames = _posed_tube(1)
    options = SfsOptions(roughness=0.3)
    solution = solve(frames[0][0].irradiance, camera, options, mask=mask)
    rebuilt = solution_from_depth(solution.depth, camera, options,
                                  irradiance=frames[0][0].irradiance)
    inside = np.isfinite(rebuilt.node_solution)
    assert inside.sum() > 0.8 * np.isfinite(solution.node_solution).sum()
    error = np.abs(rebuilt.node_solution[inside] - solution.node_solution[inside])
    assert np.median(error) < 1e-3 and error.max() < 0.01  # two bilinear resamplings
    with pytest.raises(SfsInputError):
        solution_from_depth(solution.depth, camera, SfsOptions(model="orthographic"))


def test_two_workers_sharing_their_depths_give_one_chain_s_output() -> None:
    """Two chains, each solving every other frame and warm-started from the other's output."""
    camera, mask, frames = _posed_tube(8)
    options = SfsOptions(roughness=0.3, tolerance=1e-8)
    stamps = [k * PERIOD_NS for k in range(len(frames))]
    single = WarmStartChain(predict=False, keep=1)
    workers = [WarmStartChain(predict=False, keep=2) for _ in range(2)]
    for stamp, (rendering, _) in zip(stamps, frames, strict=True):
        one = solve(rendering.irradiance, camera, options, mask=mask,
                    warm_start=single.warm_start(stamp))
        single.add(stamp, one)
        owner = frame_owner(stamp, 2, PERIOD_NS)  # stamps on the slots: no phase needed
        chain = workers[owner]
        shared = solve(rendering.irradiance, camera, options, mask=mask,
                       warm_start=chain.warm_start(stamp))
        chain.add(stamp, shared)
        workers[1 - owner].add_depth(stamp, shared.depth, camera, options,
                                     irradiance=rendering.irradiance)
        both = np.isfinite(one.depth)
        assert np.array_equal(both, np.isfinite(shared.depth))
        assert np.max(np.abs(shared.depth[both] / one.depth[both] - 1.0)) < 1e-5
    # each worker started from the other's newest frame, not only its own
    assert all(len(chain) == 2 for chain in workers)
