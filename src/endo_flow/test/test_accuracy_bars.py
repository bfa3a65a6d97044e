"""Issue 11's accuracy bars on short renders with the real SFS upstream, against ground truth.

Each sequence is rendered by endo_sim at 320×240 with sensor noise, corrected
with the simulator's own response and light map (what ``endo-calibrate``
estimates to 0.6 %), solved by ``endo_sfs.solve`` (near-light, Oren–Nayar
0.3, highlights masked, warm-started), and run through ``FlowPipeline`` with
the tracker's noise (0.25 mm / 0.1°) and a hand–eye error of 1 mm / 0.3°.
Nothing here was tuned on these seeds: the flow settings were chosen on the
phantom (colon seed 1) and the matte abdomen variant on seed 3
(docs/flow.md); the tests use abdomen seed 4 and colon seed 5. The
full-size figures are bench/eval_flow.py's.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from endo_flow.pipeline import FlowFrame, FlowPipeline
from endo_io.pose import motion_onset, transform_points
from endo_sfs import SfsOptions, solve
from endo_sfs.evaluation import sequence_scale
from endo_sim.photometry import Photometry
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.texture import TextureOptions

FPS = 30.0
#: the matte peritoneum of bench/render_eval_bags.py: no specular lobe, albedo drift ±2 %
MATTE = {"photometry": Photometry(specular_strength=0.0),
         "texture": TextureOptions(drift=0.02)}


@dataclasses.dataclass
class Scored:
    """Per-frame results of one run."""

    moved_2mm_s: float
    usable_s: float
    ratios: np.ndarray  # (N,) s / s*, NaN before convergence
    mae_m: list[float]
    absrel: list[float]
    oracle_absrel: list[float]
    cloud_rms_m: list[float]
    map_rms_m: dict[int, float]  # map_decimation -> RMS distance of the map's voxels to the truth
    map_counts: dict[int, int]  # map_decimation -> points fused in all


def _map_rms(pipe: FlowPipeline, truth: cKDTree) -> float:
    """RMS distance (m) of the map's voxel means to the true surface (points of the frames)."""
    assert pipe.voxel_map is not None
    distance, _ = truth.query(pipe.voxel_map.points().points.astype(np.float64), k=1)
    return float(np.sqrt(np.mean(distance**2)))


def _run(scene: str, seed: int, seconds: float, kit, maps: tuple[int, ...] = (),
         **config: object) -> Scored:
    """One render through SFS and the pipeline; ``maps``: map decimations to score against truth."""
    cfg = SimulationConfig(scene=scene, width=320, height=240, fps=FPS, duration_s=seconds,
                           seed=seed, **config)  # type: ignore[arg-type]
    seq = build_sequence(cfg)
    camera, renderer = seq.camera, seq.renderer
    count = round(seconds * FPS)
    times = np.round(np.arange(count) * 1e9 / FPS).astype(np.int64)
    true_poses = seq.trajectory.poses_at(times)
    lut = cfg.photometry.response.inverse_lut(cfg.photometry.bit_depth)
    rng = np.random.default_rng(seed)
    options = SfsOptions(roughness=cfg.photometry.roughness, mask_highlights=True, threads=2)
    images, relative, depths = [], [], []
    previous = None
    for T in true_poses:
        frame = renderer.render(seq.scenes[0], T, rng)
        code = frame.image
        ok = renderer.mask & (code > 0) & (code < 255)
        image = np.where(ok, lut[code] / renderer.light_map, np.nan).astype(np.float32)
        previous = solve(image, camera, options, mask=renderer.mask, warm_start=previous)
        images.append(image)
        relative.append(previous.depth)
        depths.append(frame.depth)
    # the oracle: one scale for the whole sequence
    s_oracle = sequence_scale(relative, depths)
    poses = kit.tracked_poses(true_poses, seed=seed)
    stamps = cfg.start_ns + times
    pipe = FlowPipeline(kit.options())
    assert pipe.options.map_decimation == 1 and pipe.options.map_every == 1  # the defaults
    fused = 0
    ratios = np.full(count, np.nan)
    mae, absrel, oracle, cloud = [], [], [], []
    for k in range(count):
        out = pipe.process(FlowFrame(int(stamps[k]), images[k], relative[k], camera, poses[k]))
        fused += out.diagnostics.map_points
        if not out.scale.usable:
            continue
        ratios[k] = out.scale.value / s_oracle
        if times[k] < 1.5e9 or k % 3 or out.depth is None:  # every 3rd frame after 1.5 s
            continue
        truth = depths[k]
        sel = np.isfinite(truth) & np.isfinite(out.depth) & (truth >= 0.02) & (truth <= 0.08)
        err = np.abs(out.depth[sel] - truth[sel])
        mae.append(float(err.mean()))
        absrel.append(float((err / truth[sel]).mean()))
        oracle.append(float((np.abs(relative[k][sel] * s_oracle - truth[sel]) / truth[sel]).mean()))
        true_points = transform_points(true_poses[k], camera.depth_to_points(truth))
        true_points = true_points[np.isfinite(true_points).all(axis=-1)]
        distance, _ = cKDTree(true_points).query(out.points.astype(np.float64), k=1)
        cloud.append(float(np.sqrt(np.mean(distance**2))))
    moved = motion_onset(true_poses[:, :3, 3], 2e-3)
    assert moved is not None, "the test trajectory must move 2 mm"
    usable = int(np.argmax(np.isfinite(ratios))) if np.isfinite(ratios).any() else count
    map_rms: dict[int, float] = {}
    map_counts: dict[int, int] = {}
    if maps:
        # the true surface the map saw: every other frame's true points from the first usable
        seen = [transform_points(true_poses[k], camera.depth_to_points(depths[k])).reshape(-1, 3)
                for k in range(usable, count, 2)]
        truth = np.concatenate(seen)
        tree = cKDTree(truth[np.isfinite(truth).all(axis=1)])
        for decimation in maps:
            if decimation == 1:
                run, total = pipe, fused
            else:  # the same frames again, the map at that decimation
                run = FlowPipeline(kit.options(map_decimation=decimation))
                total = 0
                for k in range(count):
                    total += run.process(FlowFrame(int(stamps[k]), images[k], relative[k],
                                                   camera, poses[k])).diagnostics.map_points
            map_rms[decimation], map_counts[decimation] = _map_rms(run, tree), total
    return Scored(moved / FPS, usable / FPS, ratios, mae, absrel, oracle, cloud, map_rms,
                  map_counts)


@pytest.fixture(scope="module")
def matte_abdomen(kit) -> Scored:
    """2.5 s of the matte abdomen, seed 4 (the held-out seed of the variant)."""
    return _run("abdomen", 4, 2.5, kit, maps=(1, 4), **MATTE)


@pytest.fixture(scope="module")
def colon(kit) -> Scored:
    """2.5 s of the colon, seed 5."""
    return _run("colon", 5, 2.5, kit)


def _converged_after_2mm(r: Scored) -> float:
    return r.usable_s - r.moved_2mm_s


def test_matte_abdomen_depth_and_cloud_bars(matte_abdomen):
    """Where SFS's model holds: MAE <= 1 mm, AbsRel <= 0.03 (20-80 mm), cloud <= 1.5 mm RMS.

    Measured at 320x240: MAE 0.56 mm, AbsRel 0.016 (oracle-scaled 0.015),
    cloud 0.86 mm; the scale converged 0.53 s after 2 mm of motion.
    """
    r = matte_abdomen
    assert _converged_after_2mm(r) <= 1.0, (r.moved_2mm_s, r.usable_s)
    assert len(r.mae_m) >= 5
    assert np.mean(r.mae_m) <= 1e-3, r.mae_m
    assert np.mean(r.absrel) <= 0.03, r.absrel
    assert np.sqrt(np.mean(np.square(r.cloud_rms_m))) <= 1.5e-3, r.cloud_rms_m


def test_colon_metric_absrel_within_0_01_of_the_oracle(colon):
    """The colon's metric AbsRel is within 0.01 of the oracle-scaled one (measured 0.067, 0.066)."""
    r = colon
    assert _converged_after_2mm(r) <= 1.0, (r.moved_2mm_s, r.usable_s)
    assert len(r.absrel) >= 5
    gap = np.mean(r.absrel) - np.mean(r.oracle_absrel)
    assert abs(gap) <= 0.01, (np.mean(r.absrel), np.mean(r.oracle_absrel))


def test_full_resolution_map_against_the_truth(matte_abdomen):
    """The map fused from every pixel: its voxels lie on the true surface, 1.5 mm RMS at most.

    The bar is issue 11's for the frame's cloud (seed 4, not tuned on: the
    map's settings were not tuned at all). Measured at 320x240: the map at
    full resolution (the default) fused 2.31 M points, 16.0x the 144 k of the
    live topic's decimation 4 over the same frames, and its voxels are
    1.10 mm RMS from the truth against 1.04 mm at decimation 4: full
    resolution does not make the map more accurate here (the error is the
    depth's bias and the poses', not noise that more points average out).
    The frames' own clouds after 1.5 s: 0.86 mm.
    """
    r = matte_abdomen
    assert r.map_counts[1] > 14 * r.map_counts[4], r.map_counts
    assert r.map_rms_m[1] <= 1.5e-3, r.map_rms_m
