#!/usr/bin/env python3
"""What the scale's smooth excursion on a bag is: pose path, tracker draw, or vision.

``make demo`` judges the phantom's scale from 1 s after the camera's first
2 mm of motion; the published scale there rises smoothly to a few percent
over the oracle and falls back. This diagnosis runs ``FlowPipeline`` on one
bag (upstream exactly as ``bench/eval_flow.py``: the calibration's
correction, SFS cached, the tracker bridge's composition) with the camera
poses from several sources, the vision side (images, SFS) fixed:

* ``bag``: the bag's noisy ``/tracker/pose`` composed with the hand–eye file
  (``--handeye``, as the demo composes them) or the truth's;
* ``clean``: the same tracker samples without noise (the true marker pose at
  each sample time), composed with the same hand–eye and clock offset and
  interpolated at the image stamps by ``PoseBuffer``: the pose path alone
  (hand–eye error, clock offset, interpolation), no noise;
* ``true``: the simulator's exact camera poses at the image stamps;
* ``draw:K``: the tracker's noise model (``endo_sim.tracker.TrackerModel``,
  the bag's own noise figures) drawn again with seed K on the same samples,
  composed like ``bag``: what other draws of the same tracker give;
* ``bagwin`` (with ``--noise-window A B``): the bag's own noise only on the
  samples taken between A and B seconds (the draws likewise), the others
  clean: whose noise makes the excursion.

Per frame: the filter's s / s*, the observation / s*, its claimed standard
deviation, and (with the scene's truth traced at every frame, as
``eval_flow --split``) the triangulated depth against the true one and SFS's
depth at the tracks against the oracle, at the accepted tracks; also SFS's own
per-frame scale at every frame (every 8th pixel traced), against s*.

Usage: ``bench/scale_excursion.py BAG --calibration photometric.yaml --cache DIR
[--handeye handeye.yaml] [--sources bag clean true] [--draws N] [--noise-window A B]
[--set OPTION=VALUE] [--relative-from OUT.mcap] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from eval_flow import (  # bench/ is on sys.path when run as bench/scale_excursion.py
    Sequence,
    oracle_scale,
    read_bag,
    scene_depth,
)

from endo_bringup.acceptance import AccuracyBars, converged_scale_error
from endo_calib.calibration import PhotometricCalibration
from endo_flow.errors import FlowError
from endo_flow.pipeline import FlowFrame, FlowOptions, FlowPipeline, sample_bilinear
from endo_io.bag import BagReader, deserialize
from endo_io.errors import Endo3dError
from endo_io.image import image_to_array
from endo_io.pose import invert_transform, motion_onset, pose_to_matrix, transform_points
from endo_io.pose_buffer import PoseBuffer
from endo_io.stamp import stamp_to_ns
from endo_io.topics import DEPTH_RELATIVE, TRACKER_POSE
from endo_process.accuracy import Accuracy, ScaleTrack
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.tracker import TrackerModel
from endo_tracker_bridge.composition import compose_camera_pose, corrected_stamp_ns
from endo_tracker_bridge.handeye_file import HandEyeCalibration


def tracker_samples(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The bag's ``/tracker/pose`` messages: (N,) int64 stamps, ns, and (N, 4, 4) poses, m."""
    samples = []
    with BagReader(path) as reader:
        for message in reader.messages([TRACKER_POSE]):
            msg = deserialize(message)
            samples.append((stamp_to_ns(msg.header.stamp), pose_to_matrix(msg)[0]))
    samples.sort(key=lambda item: item[0])
    return (np.array([s for s, _ in samples], np.int64),
            np.array([p for _, p in samples], np.float64))


def pose_sources(path: Path, seq: Sequence, handeye: Path | None, draws: int,
                 seed0: int, noise_window_s: tuple[float, float] | None = None,
                 ) -> dict[str, dict[int, np.ndarray | None]]:
    """Camera poses at the image stamps from every source (module docstring).

    ``noise_window_s`` (start, end), seconds since the recording's start:
    the redrawn noise only on the tracker samples taken then (the others
    exact), to find whose noise makes an excursion.
    """
    truth = yaml.safe_load(path.with_suffix(".ground_truth.yaml").read_text())
    tracker = truth["tracker"]
    T_tracker_world = np.array(tracker["T_tracker_world"])
    X_true = np.array(tracker["T_marker_camera"])
    latency_true = round(tracker["latency_s"] * 1e9)
    if handeye is not None:
        calibration = HandEyeCalibration.load(handeye)
        X, offset = calibration.T_marker_camera, calibration.time_offset_ns
    else:
        X, offset = X_true, latency_true
    recording = truth["recording"]
    planned = build_sequence(SimulationConfig(
        scene=truth["scene"]["scene"], seed=truth["scene"]["seed"],
        duration_s=recording["duration_s"], fps=recording["fps"],
        start_ns=recording["start_ns"]))
    stamps, bag_markers = tracker_samples(path)
    sample_rel = stamps - recording["start_ns"] - latency_true
    model = TrackerModel(position_noise_rms_m=tracker["position_noise_rms_m"],
                         rotation_noise_rms_rad=np.radians(tracker["rotation_noise_rms_deg"]),
                         T_marker_camera=X_true, T_tracker_world=T_tracker_world)
    clean_markers = model.true_marker_poses(planned.trajectory.poses_at(sample_rel))
    world_tracker = invert_transform(T_tracker_world)

    def at_frames(markers: np.ndarray) -> dict[int, np.ndarray | None]:
        buffer = PoseBuffer(capacity=100_000, max_gap_ns=100_000_000)
        for stamp, marker in zip(stamps, markers, strict=True):
            buffer.insert(corrected_stamp_ns(int(stamp), offset),
                          compose_camera_pose(world_tracker, marker, X))
        poses: dict[int, np.ndarray | None] = {}
        for stamp in seq.stamps:
            try:
                poses[stamp] = buffer.query(stamp)
            except Endo3dError:
                poses[stamp] = None
        return poses

    sources: dict[str, dict[int, np.ndarray | None]] = {
        "bag": dict(seq.poses),
        "clean": at_frames(clean_markers),
        "true": {s: seq.true_pose.get(s) for s in seq.stamps},
    }
    if noise_window_s is not None:  # the bag's own noise, only in the window
        outside = ((sample_rel < noise_window_s[0] * 1e9)
                   | (sample_rel >= noise_window_s[1] * 1e9))
        sources["bagwin"] = at_frames(np.where(outside[:, None, None], clean_markers,
                                               bag_markers))
    for k in range(draws):
        rng = np.random.default_rng(seed0 + k)
        noisy = model.add_noise(clean_markers, rng)
        if noise_window_s is not None:
            noisy[outside] = clean_markers[outside]
        sources[f"draw:{seed0 + k}"] = at_frames(noisy)
    return sources


def relative_from(path: Path, seq: Sequence) -> None:
    """Replace ``seq``'s depth_relative by an endo-process output's, frame by frame.

    ``make demo``'s SFS differs from ``eval_flow.read_bag``'s in a few frames
    (its validity mask); with the demo's own depth the trace is the demo's.
    """
    wanted = set(seq.stamps)
    with BagReader(path) as reader:
        for message in reader.messages([DEPTH_RELATIVE]):
            msg = deserialize(message)
            stamp = stamp_to_ns(msg.header.stamp)
            if stamp in wanted:
                seq.relative[stamp] = image_to_array(msg).astype(np.float32)


def sfs_frame_scales(seq: Sequence, truth_at: Any, s_oracle: float,
                     step: int = 8) -> np.ndarray:
    """(N,) SFS's own scale at every frame over s*: exp(median ln(z_true / d_rel)) / s*."""
    v, u = np.mgrid[step // 2:seq.camera.height:step, step // 2:seq.camera.width:step]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    out = []
    for stamp in seq.stamps:
        z = truth_at(stamp, uv)
        rel = seq.relative[stamp][v.ravel(), u.ravel()].astype(np.float64)
        ok = np.isfinite(z) & np.isfinite(rel) & (rel > 0) & (z > 0)
        out.append(float(np.exp(np.median(np.log(z[ok] / rel[ok]))) / s_oracle))
    return np.array(out)


def run(seq: Sequence, poses: dict[int, np.ndarray | None], options: FlowOptions,
        s_oracle: float, truth_at: Any | None) -> dict[str, Any]:
    """One pipeline pass; per-frame traces and the demo's figure."""
    pipe = FlowPipeline(options)
    t0 = seq.stamps[0]
    rows: dict[str, list[float]] = {k: [] for k in (
        "t", "s", "usable", "std", "obs", "obs_std", "tri", "z_tri", "sfs_tracks")}
    published: list[tuple[int, float]] = []
    for stamp in seq.stamps:
        pose = poses[stamp]
        try:
            out = pipe.process(FlowFrame(stamp, seq.images[stamp], seq.relative[stamp],
                                         seq.camera, pose))
        except FlowError:
            continue
        d = out.diagnostics
        published.append((stamp, out.scale.value))
        z_tri = sfs_t = np.nan
        if truth_at is not None and len(out.triangulated) and pose is not None:
            local = transform_points(invert_transform(pose), out.triangulated)
            uv = seq.camera.project(local)
            z_true = truth_at(stamp, uv)
            with np.errstate(invalid="ignore", divide="ignore"):
                z_tri = float(np.nanmedian(local[:, 2] / z_true))
                sfs_t = float(np.nanmedian(sample_bilinear(seq.relative[stamp], uv)
                                           * s_oracle / z_true))
        for key, value in (("t", (stamp - t0) / 1e9), ("s", out.scale.value / s_oracle),
                           ("usable", float(out.scale.usable)),
                           ("std", out.scale.log_std), ("obs", d.observation / s_oracle),
                           ("obs_std", d.observation_std), ("tri", d.triangulated),
                           ("z_tri", z_tri), ("sfs_tracks", sfs_t)):
            rows[key].append(float(value))
    posed = [s for s in seq.stamps if s in seq.true_pose]
    centres = np.array([seq.true_pose[s][:3, 3] for s in posed])
    track = ScaleTrack(np.array([p[0] for p in published], np.int64),
                       np.array([p[1] for p in published], np.float64), s_oracle)
    errors = converged_scale_error(
        Accuracy(truth_frames=len(seq.true_depth), scale=track,
                 true_positions=(np.array(posed, np.int64), centres)), AccuracyBars())
    onset = motion_onset(centres, AccuracyBars().motion_m)
    return {"demo_max_pct": 100 * float(np.max(np.abs(errors))) if len(errors) else np.nan,
            "demo_signed_extreme_pct": 100 * float(errors[np.argmax(np.abs(errors))])
            if len(errors) else np.nan,
            "moved_2mm_s": (posed[onset] - t0) / 1e9 if onset is not None else np.nan,
            **rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--calibration", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--handeye", type=Path, default=None)
    parser.add_argument("--sources", nargs="*", default=["bag", "clean", "true"])
    parser.add_argument("--draws", type=int, default=0)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--noise-window", nargs=2, type=float, default=None,
                        metavar=("START_S", "END_S"),
                        help="redrawn noise only on the samples taken in this span")
    parser.add_argument("--no-split", action="store_true", help="skip the traced truth")
    parser.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE")
    parser.add_argument("--relative-from", type=Path, default=None, metavar="OUT.mcap",
                        help="depth_relative from an endo-process output (make demo's "
                        "out/offline.mcap) instead of eval_flow's SFS")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    calibration = PhotometricCalibration.load(args.calibration)
    seq = read_bag(args.bag, calibration, 0.0, args.cache, 1.0, handeye_error=False,
                   handeye=args.handeye)
    if args.relative_from is not None:
        relative_from(args.relative_from, seq)
    s_oracle = oracle_scale(seq)
    truth_at = None if args.no_split else scene_depth(args.bag, seq)
    overrides: dict[str, Any] = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if "." in key:
            group, name = key.split(".", 1)
            nested = overrides.get(group, getattr(FlowOptions(), group))
            overrides[group] = dataclasses.replace(
                nested, **{name: type(getattr(nested, name))(yaml.safe_load(value))})
        else:
            overrides[key] = type(getattr(FlowOptions(), key))(yaml.safe_load(value))
    options = dataclasses.replace(FlowOptions(), **overrides)
    sources = pose_sources(args.bag, seq, args.handeye, args.draws, args.seed,
                           None if args.noise_window is None else tuple(args.noise_window))
    result: dict[str, Any] = {"bag": args.bag.name, "oracle_scale": s_oracle,
                              "set": args.set, "runs": {}}
    if truth_at is not None:
        result["sfs_frame_scale"] = sfs_frame_scales(seq, truth_at, s_oracle).tolist()
    wanted = [s for s in sources if s in args.sources or s.startswith("draw:")
              or s == "bagwin"]
    for name in wanted:
        res = run(seq, sources[name], options, s_oracle,
                  truth_at if not name.startswith("draw:") else None)
        result["runs"][name] = res
        print(f"{name:>10}: demo max {res['demo_max_pct']:.2f} % "
              f"(signed {res['demo_signed_extreme_pct']:+.2f}), final "
              f"{100 * (res['s'][-1] - 1):+.2f} %", flush=True)
    if args.json:
        args.json.write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
