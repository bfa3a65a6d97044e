#!/usr/bin/env python3
"""SFS accuracy against the highlight mask on noise-free, perfectly corrected renders.

The frames are rendered by endo_sim's own renderer without sensor noise and
corrected exactly (irradiance / (exposure · light map), NaN where the sensor
saturates), so that the only departures from SFS's model are the texture and
the specular lobe. The lobe's share of each pixel is known (the same hits
rendered with the lobe off), which gives oracle masks to compare the
detector with. Each mask is scored by the oracle-scaled AbsRel of
``endo_sfs.solve`` (near-light, σ = 0.3, cold, one scale fitted over all the
frames of a set: the median of the pooled log ratios) in 20–80 mm, on the
pixels with an estimate, and on the pixels that every compared mask leaves
(``common``), so that a mask cannot score by dropping hard pixels only.

With ``--bag`` it scores recorded endo_sim bags instead (the phantom, a
colon render): every frame corrected by the ``endo-calibrate`` calibration,
solved in order warm-started as the node does, per-frame median-scaled
AbsRel on the ground-truth frames (the figure of ``bench_sfs.py --phantom``),
once per ``--growth``.

Usage::

    .venv/bin/python bench/eval_highlights.py [--scene abdomen] [--seeds 3 4]
        [--times 1 3 5 7] [--growth 1 2] [--oracle 0.2 0.05] [--specular 2.0]
        [--drift 0.08]
    .venv/bin/python bench/eval_highlights.py --bag bags/phantom_colon.mcap
        --calibration photometric.yaml [--growth 1 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable
from functools import partial

import numpy as np
from recorded_frames import read_recorded_frames

from endo_calib.calibration import PhotometricCalibration
from endo_calib.raw_image import to_raw_frame
from endo_io.camera import CameraModel
from endo_io.image import image_to_array
from endo_sfs import SfsOptions, solve
from endo_sfs.errors import SfsError
from endo_sfs.evaluation import depth_error, sequence_scale
from endo_sfs.highlights import DEFAULT_SHOULDER_GROWTH, detect_highlights
from endo_sim.photometry import Photometry
from endo_sim.render import Renderer
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.texture import TextureOptions

#: Irradiance (1 = full well) at or above which the sensor reads full scale.
FULL_SCALE = 0.995
DEPTH_RANGE = (0.02, 0.08)


@dataclasses.dataclass
class Frame:
    """One noise-free frame: corrected irradiance, lobe fraction, true depth, mask."""

    irradiance: np.ndarray
    lobe_fraction: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


def render_frames(scene: str, seed: int, times: list[float], specular: float | None,
                  drift: float | None) -> tuple[list[Frame], CameraModel]:
    """The frames at ``times`` (s) of the ``scene``/``seed`` recording, noise-free."""
    photometry = Photometry(noise=False)
    if specular is not None:
        photometry = dataclasses.replace(photometry, specular_strength=specular)
    texture = TextureOptions() if drift is None else TextureOptions(drift=drift)
    config = SimulationConfig(scene=scene, seed=seed, duration_s=max(times) + 0.5,
                              photometry=photometry, texture=texture)
    sequence = build_sequence(config)
    renderer = sequence.renderer
    matte = Renderer(sequence.camera, dataclasses.replace(photometry, specular_strength=0.0),
                     config.fov_radius)
    norm = photometry.exposure * renderer.light_map
    frames = []
    for t in times:
        k = round(t * config.fps)
        pose = sequence.trajectory.pose_at(int(sequence.frame_times_ns[k]))
        hits = sequence.scene_of_frame(k).trace(pose, renderer.rays, renderer.mask)
        total = renderer.irradiance(hits)[..., 0]
        diffuse = matte.irradiance(hits)[..., 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            image = np.where(renderer.mask & (total < FULL_SCALE) & (total > 0),
                             total / norm, np.nan).astype(np.float32)
            fraction = np.where(diffuse > 0, (total - diffuse) / diffuse, 0.0)
        depth = (hits.distance * renderer.rays[..., 2]).astype(np.float32)
        frames.append(Frame(image, fraction, depth, renderer.mask))
    return frames, sequence.camera


def score(frames: list[Frame], depths: list[np.ndarray], common: list[np.ndarray]) -> dict:
    """Oracle-scaled AbsRel / MAE over 20–80 mm (all pixels with an estimate, and ``common``)."""
    scale = sequence_scale(depths, [frame.depth for frame in frames])
    out: dict[str, list[float]] = {"absrel": [], "mae_mm": [], "coverage": [], "common": []}
    for frame, depth, shared in zip(frames, depths, common, strict=True):
        est = depth * scale
        in_range = (frame.depth >= DEPTH_RANGE[0]) & (frame.depth <= DEPTH_RANGE[1])
        ok = in_range & np.isfinite(est)
        err = np.abs(est[ok] - frame.depth[ok])
        out["absrel"].append(float(np.mean(err / frame.depth[ok])))
        out["mae_mm"].append(1e3 * float(np.mean(err)))
        out["coverage"].append(float(ok.sum() / max(1, in_range.sum())))
        both = shared & ok
        out["common"].append(float(np.mean(np.abs(est[both] - frame.depth[both])
                                           / frame.depth[both])))
    return {key: float(np.mean(values)) for key, values in out.items()} | {
        "per_frame": out["absrel"]}


Detector = Callable[[Frame], np.ndarray]


def evaluate(frames: list[Frame], camera: CameraModel, detectors: dict[str, Detector]) -> None:
    """Solve every frame with each detector's mask and print the scores."""
    options = SfsOptions(roughness=0.3, threads=2)
    depths: dict[str, list[np.ndarray]] = {}
    seconds: dict[str, float] = {}
    for name, detector in detectors.items():
        depths[name] = []
        seconds[name] = 0.0
        for frame in frames:
            start = time.perf_counter()
            masked = detector(frame)
            seconds[name] += time.perf_counter() - start
            try:
                depth = solve(frame.irradiance, camera, options,
                              mask=frame.mask & ~masked).depth
            except SfsError as error:
                print(f"  {name}: {error}")
                depth = np.full(frame.depth.shape, np.nan, np.float32)
            depths[name].append(depth)
    common = [np.logical_and.reduce([np.isfinite(depths[name][i]) for name in depths])
              for i in range(len(frames))]
    print("| mask | AbsRel | common AbsRel | MAE mm | coverage | per frame | ms/frame |")
    print("|---|---|---|---|---|---|---|")
    for name in detectors:
        s = score(frames, depths[name], common)
        per = " ".join(f"{v:.4f}" for v in s["per_frame"])
        print(f"| {name} | {s['absrel']:.4f} | {s['common']:.4f} | {s['mae_mm']:.2f} | "
              f"{s['coverage']:.3f} | {per} | {1e3 * seconds[name] / len(frames):.1f} |")


def grown_mask(frame: Frame, growth: float) -> np.ndarray:
    """``detect_highlights`` with ``shoulder_growth`` = growth."""
    return detect_highlights(frame.irradiance, frame.mask, shoulder_growth=growth)


def score_bag(bag: str, calibration: str, growth: float, fov_radius: float = 240.0) -> None:
    """Per-frame median-scaled AbsRel of the warm-started chain over a bag's ground-truth frames."""
    frames = read_recorded_frames(bag)
    images, infos, depths, stamps = frames.images, frames.infos, frames.depths, frames.stamps
    correction = PhotometricCalibration.load(calibration)
    camera = CameraModel.from_camera_info(infos[stamps[0]])
    fov = camera.fov_mask(fov_radius)
    options = SfsOptions(roughness=0.3, threads=2)
    previous = None
    errors, coverage = [], []
    for stamp in stamps:
        raw = to_raw_frame(image_to_array(images[stamp]), images[stamp].encoding)
        irradiance = correction.luminance(correction.correct(raw))
        masked = detect_highlights(irradiance, fov, shoulder_growth=growth)
        previous = solve(irradiance, camera, options, mask=fov & ~masked, warm_start=previous)
        if stamp in depths:
            error = depth_error(previous.depth, image_to_array(depths[stamp]), scaling="median")
            errors.append(error.abs_rel)
            coverage.append(error.coverage)
    print(f"{bag}, shoulder_growth {growth:g}: median-scaled AbsRel mean {np.mean(errors):.4f} "
          f"(per frame {' '.join(f'{e:.4f}' for e in errors)}), coverage "
          f"{np.mean(coverage):.3f}", flush=True)


def oracle_mask(frame: Frame, level: float) -> np.ndarray:
    """The pixels where the true lobe exceeds ``level`` × the diffuse light, and the saturated."""
    return (frame.lobe_fraction > level) | (frame.mask & ~np.isfinite(frame.irradiance))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="abdomen")
    parser.add_argument("--seeds", type=int, nargs="+", default=[3])
    parser.add_argument("--times", type=float, nargs="+", default=[1.0, 3.0, 5.0, 7.0])
    parser.add_argument("--oracle", type=float, nargs="*", default=[0.2, 0.05, 0.01],
                        help="oracle masks: lobe / diffuse above these")
    parser.add_argument("--growth", type=float, nargs="+",
                        default=[1.0, DEFAULT_SHOULDER_GROWTH], help="shoulder_growth values")
    parser.add_argument("--bag", help="score this endo_sim bag instead of rendering")
    parser.add_argument("--calibration", default="photometric.yaml",
                        help="endo-calibrate output for --bag")
    parser.add_argument("--specular", type=float, default=None)
    parser.add_argument("--drift", type=float, default=None)
    args = parser.parse_args()
    if args.bag:
        for growth in args.growth:
            score_bag(args.bag, args.calibration, growth)
        return
    detectors: dict[str, Detector] = {"none": lambda f: np.zeros(f.mask.shape, bool)}
    for growth in args.growth:
        detectors[f"detect_highlights, shoulder_growth {growth:g}"] = partial(
            grown_mask, growth=growth)
    for level in args.oracle:
        detectors[f"oracle lobe > {level:g}·diffuse"] = partial(oracle_mask, level=level)
    for seed in args.seeds:
        frames, camera = render_frames(args.scene, seed, args.times, args.specular, args.drift)
        print(f"\n{args.scene} seed {seed}, t = {args.times} s, specular {args.specular}, "
              f"drift {args.drift}")
        evaluate(frames, camera, detectors)


if __name__ == "__main__":
    main()
