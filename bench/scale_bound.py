#!/usr/bin/env python3
"""What the tracker's noise allows the depth scale: the information bound beside the filter.

Per sequence (an endo_sim bag with its ``<stem>.ground_truth.yaml``):

1. **The bound** (``endo_flow.scale_information``): σ(ln s)(t), the Cramér–Rao
   bound of any unbiased scale estimate that uses every tracker sample from
   the recording's start to t, on the bag's TRUE camera trajectory (the
   ``/ground_truth/camera_pose`` of each image, interpolated by
   ``endo_io.pose_buffer.PoseBuffer`` at the tracker's samples: the bag's own
   ``/tracker/pose`` stamps minus the latency, so its dropouts are the
   bag's), vision assumed to give the relative trajectory exactly:
   (a) the tracker's rotation noise carried to the camera over the hand–eye
   lever arm, (b) the orientation known from vision (position noise only).
   Printed at the filter's first convergence, at 1 s after 2 mm of motion,
   and the time from which 3σ ≤ 2 %.
2. **An efficient estimator on this noise draw**: the weighted least-squares
   fit of (s, t0) to the bag's actual noisy tracker centres against the true
   relative trajectory (``cumulative_scale_fit``), composed with the true
   hand–eye and with ``eval_flow``'s 1 mm / 0.3° error: its largest error
   after the filter's convergence.
3. **SFS's own per-frame scale** against the sequence's one oracle scale, at
   the ground-truth frames (``eval_flow.per_frame_scales``).
4. **The filter** (``eval_flow.evaluate``, defaults): its largest error after
   convergence with the tracker's poses and with the simulator's true poses.

Usage: ``bench/scale_bound.py BAG ... --calibration photometric.yaml
[--cache DIR] [--json OUT]``; SFS is solved once per bag and cached like
``bench/eval_flow.py``'s (full resolution).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import yaml
from eval_flow import (  # bench/ is on sys.path when run as bench/scale_bound.py
    HANDEYE_ERROR,
    evaluate,
    oracle_scale,
    per_frame_scales,
    read_bag,
)

from endo_calib.calibration import PhotometricCalibration
from endo_flow.errors import FlowInputError
from endo_flow.pipeline import FlowOptions, sample_bilinear
from endo_flow.scale_information import (
    camera_centre_covariances,
    cumulative_scale_fit,
    known_rotation_translation,
    lever_arms,
    scale_information_bound,
    segmented_scale_fit,
)
from endo_flow.tracking import FeatureTracker
from endo_io.bag import BagReader, deserialize
from endo_io.errors import PoseLookupError
from endo_io.pose import invert_transform, motion_onset, pose_to_matrix
from endo_io.pose_buffer import PoseBuffer
from endo_io.stamp import stamp_to_ns
from endo_io.topics import IMAGE_RAW, TRACKER_POSE, TRUE_CAMERA_POSE
from endo_tracker_bridge.composition import compose_camera_pose

#: the bar: |s/s* − 1| ≤ 2 %, held at 3σ
BAR = 0.02


def tracker_track(bag: Path) -> dict[str, np.ndarray]:
    """The bag's tracker samples with the true camera poses at their sample times.

    Returns ``t`` (N,) s since the first image, ``true`` (N, 4, 4) T_world_camera
    (interpolated ground truth), ``measured`` (N, 4, 4) T_tracker_marker as
    published (metres), and the ground truth's ``T_marker_camera``,
    ``T_tracker_world``, noise figures.
    """
    truth = yaml.safe_load(bag.with_suffix(".ground_truth.yaml").read_text())
    tracker = truth["tracker"]
    latency_ns = round(float(tracker["latency_s"]) * 1e9)
    unit = 1e-3 if tracker.get("units", "m") == "mm" else 1.0
    gt = PoseBuffer(capacity=100_000, max_gap_ns=200_000_000)
    first_image = None
    samples: list[tuple[int, np.ndarray]] = []
    with BagReader(bag) as reader:
        for message in reader.messages([IMAGE_RAW, TRUE_CAMERA_POSE, TRACKER_POSE]):
            if message.topic == IMAGE_RAW:
                if first_image is None:
                    first_image = stamp_to_ns(deserialize(message).header.stamp)
                continue
            msg = deserialize(message)
            stamp = stamp_to_ns(msg.header.stamp)
            if message.topic == TRUE_CAMERA_POSE:
                gt.insert(stamp, pose_to_matrix(msg)[0])
            else:
                T = pose_to_matrix(msg)[0].copy()
                T[:3, 3] *= unit
                samples.append((stamp - latency_ns, T))
    assert first_image is not None
    times, true, measured = [], [], []
    for sample_ns, T in sorted(samples, key=lambda item: item[0]):
        try:
            pose = gt.query(sample_ns)
        except PoseLookupError:  # before the first / after the last image: no truth there
            continue
        times.append((sample_ns - first_image) / 1e9)
        true.append(pose)
        measured.append(T)
    return {
        "t": np.array(times),
        "true": np.array(true),
        "measured": np.array(measured),
        "T_marker_camera": np.array(tracker["T_marker_camera"], dtype=np.float64),
        "T_tracker_world": np.array(tracker["T_tracker_world"], dtype=np.float64),
        "position_noise_rms_m": np.float64(tracker["position_noise_rms_m"]),
        "rotation_noise_rms_rad": np.float64(math.radians(tracker["rotation_noise_rms_deg"])),
    }


def at(times: np.ndarray, values: np.ndarray, t: float) -> float:
    """The value of the last sample at or before t (NaN before the first)."""
    index = int(np.searchsorted(times, t, side="right")) - 1
    return float(values[index]) if index >= 0 else math.nan


def first_time(times: np.ndarray, condition: np.ndarray) -> float:
    """The first time from which ``condition`` holds to the end (NaN: never)."""
    bad = np.flatnonzero(~condition)
    if len(bad) == 0:
        return float(times[0])
    return float(times[bad[-1] + 1]) if bad[-1] + 1 < len(times) else math.nan


def vision_trajectory_fit(seq, track: dict, true_poses: bool, min_common: int = 30,
                          anchor_every: int = 0, max_anchors: int = 10) -> dict[str, np.ndarray]:
    """The scale fitted over the vision-relative trajectory against the tracker's centres.

    Lucas–Kanade tracks (``FeatureTracker``, the pipeline's options) carry an
    anchor frame's SFS points (``depth_relative`` at the tracks, in SFS's
    unit) into each later frame; with the rotation from the poses, each
    frame's camera centre relative to the anchor follows linearly
    (``known_rotation_translation``): the vision-relative trajectory, in SFS's
    unit, one segment per anchor. A new anchor when no anchor shares
    ``min_common`` tracks with the frame, and with ``anchor_every`` > 0 also
    every that many frames (at most ``max_anchors`` alive: several anchors
    average their frames' SFS errors; a frame measured against n anchors
    counts each time with its covariance × n, so that it weighs as one
    sample). ln s is the weighted least-squares fit of the frames' tracker
    centres against every segment so far (``segmented_scale_fit``, the
    bound's estimator), its σ from the tracker's noise model.

    Returns ``t``, ``log_scale`` (ln s − ln s*, NaN before a fit), ``sigma``,
    ``segments`` (1,).
    """
    options = FlowOptions()
    tracker = FeatureTracker(options.tracking)
    s_oracle = oracle_scale(seq)
    sigma_p, sigma_r = track["position_noise_rms_m"], track["rotation_noise_rms_rad"]
    hand_eye = track["T_marker_camera"]
    segments: list[tuple[list, list, list]] = []
    anchors: list[dict] = []
    since_anchor = 0
    out: dict[str, list[float]] = {"t": [], "log_scale": [], "sigma": []}
    t0 = seq.stamps[0]
    for stamp in seq.stamps:
        features = tracker.track(seq.images[stamp])
        pose = seq.true_pose.get(stamp) if true_poses else seq.poses[stamp]
        out["t"].append((stamp - t0) / 1e9)
        since_anchor += 1
        if pose is not None and len(features.ids):
            rays = seq.camera.pixels_to_rays(features.uv)
            depth = sample_bilinear(seq.relative[stamp], features.uv)
            points = depth[:, None] / rays[:, 2:3] * rays
            cov = camera_centre_covariances(lever_arms(pose[None], hand_eye), sigma_p, sigma_r)[0]
            measured = []
            for anchor in anchors:
                common = np.intersect1d(anchor["ids"], features.ids)
                if len(common) < min_common:
                    anchor["alive"] = False
                    continue
                a = np.searchsorted(anchor["ids"], common)
                b = np.searchsorted(features.ids, common)
                R = pose[:3, :3].T @ anchor["R"]  # R_view_anchor
                try:
                    t, _ = known_rotation_translation(anchor["points"][a], rays[b], R)
                except FlowInputError:  # too few tracks left off the anchor's centre
                    continue
                measured.append((anchor["segment"], anchor["R"] @ (-R.T @ t)))
            anchors = [anchor for anchor in anchors if anchor["alive"]]
            for segment, relative in measured:
                segments[segment][0].append(relative)
                segments[segment][1].append(pose[:3, 3])
                segments[segment][2].append(cov * len(measured))
            if not anchors or (anchor_every and since_anchor >= anchor_every):
                finite = np.isfinite(points).all(axis=1)
                order = np.argsort(features.ids[finite])
                anchors.append({"ids": features.ids[finite][order],
                                "points": points[finite][order], "R": pose[:3, :3].copy(),
                                "segment": len(segments), "alive": True})
                anchors = anchors[-max_anchors:]
                segments.append(([np.zeros(3)], [pose[:3, 3]], [cov]))
                since_anchor = 0
        fit = [(np.array(r), np.array(m), np.array(c)) for r, m, c in segments if len(r) > 1]
        log_s, sigma = segmented_scale_fit(fit) if fit else (math.nan, math.inf)
        out["log_scale"].append(log_s - math.log(s_oracle))
        out["sigma"].append(sigma)
    result = {key: np.array(value) for key, value in out.items()}
    result["segments"] = np.array([len(segments)])
    return result


def max_error_from(series: dict[str, np.ndarray], start: float) -> float:
    """Largest |s/s* − 1| in % of a filter trace from ``start`` on (NaN: never reached)."""
    after = series["t"] >= start
    if not math.isfinite(start) or not after.any():
        return math.nan
    return 100 * float(np.max(np.abs(series["estimate"][after] - 1.0)))


def analyse(bag: Path, calibration: PhotometricCalibration, cache: Path | None,
            vision: bool = False, anchor_every: int = 0) -> dict:
    """Every figure of one sequence (see the module docstring)."""
    track = tracker_track(bag)
    t = track["t"]
    centres = track["true"][:, :3, 3]
    lever = lever_arms(track["true"], track["T_marker_camera"])
    sigma_p, sigma_r = track["position_noise_rms_m"], track["rotation_noise_rms_rad"]
    cov_a = camera_centre_covariances(lever, sigma_p, sigma_r)
    cov_b = camera_centre_covariances(lever, sigma_p, 0.0)
    bound_a = scale_information_bound(centres, cov_a)
    bound_b = scale_information_bound(centres, cov_b)
    onset = motion_onset(centres, 2e-3)
    t_2mm = math.nan if onset is None else float(t[onset])
    gaps = np.diff(t)
    # the efficient fit on the bag's own noisy samples (the true path as vision's)
    T_world_tracker = invert_transform(track["T_tracker_world"])
    fits = {}
    for name, hand_eye in (("true_handeye", track["T_marker_camera"]),
                           ("handeye_error", track["T_marker_camera"] @ HANDEYE_ERROR)):
        noisy = compose_camera_pose(T_world_tracker, track["measured"], hand_eye)[:, :3, 3]
        fits[name] = cumulative_scale_fit(centres, noisy, cov_a)

    seq = read_bag(bag, calibration, 0.0, cache, 1.0)
    s_oracle = oracle_scale(seq)
    frames = per_frame_scales(seq)
    t0 = seq.stamps[0]
    frame_t = np.array([(stamp - t0) / 1e9 for stamp in sorted(frames)])
    wander = np.log(np.array([frames[stamp] for stamp in sorted(frames)]) / s_oracle)
    vision_fits = {}
    if vision:
        for name, true_poses in (("tracker", False), ("true_poses", True)):
            vision_fits[name] = vision_trajectory_fit(seq, track, true_poses,
                                                      anchor_every=anchor_every)
    runs = {}
    for name, true_poses in (("tracker", False), ("true_poses", True)):
        series: dict[str, list[float]] = {}
        result = evaluate(seq, FlowOptions(), (0.02, 0.08), bag.stem, true_poses=true_poses,
                          series=series)
        runs[name] = (result, {key: np.array(value) for key, value in series.items()})
    del seq
    result, series = runs["tracker"]
    t_conv = float(result["first_usable_s"])
    after = series["t"] >= t_conv
    filter_err = np.abs(series["usable"][after] - 1.0)  # |s/s* − 1|, as eval_flow
    true_result, true_series = runs["true_poses"]
    true_after = true_series["t"] >= float(true_result["first_usable_s"])
    fit_after = t >= t_conv
    late = frame_t >= t_conv
    threshold = BAR / 3.0
    out = {
        "sequence": bag.stem,
        "tracker_samples": len(t),
        "tracker_gap_max_s": float(gaps.max()),
        "moved_2mm_at_s": t_2mm,
        "path_length_mm_at_2mm_plus_1s": 1e3 * float(np.sum(np.linalg.norm(
            np.diff(centres[t <= t_2mm + 1.0], axis=0), axis=1))),
        "spread_mm_at_2mm_plus_1s": 1e3 * float(np.sqrt(np.sum(np.var(
            centres[t <= t_2mm + 1.0], axis=0)))),
        "filter_converged_s": t_conv,
        "filter_converged_after_2mm_s": t_conv - t_2mm,
        "bound_a_at_convergence_pct": 100 * at(t, bound_a, t_conv),
        "bound_b_at_convergence_pct": 100 * at(t, bound_b, t_conv),
        "bound_a_at_2mm_plus_1s_pct": 100 * at(t, bound_a, t_2mm + 1.0),
        "bound_b_at_2mm_plus_1s_pct": 100 * at(t, bound_b, t_2mm + 1.0),
        "bound_a_at_end_pct": 100 * float(bound_a[-1]),
        "bound_a_3sigma_within_bar_from_s": first_time(t, bound_a <= threshold),
        "bound_b_3sigma_within_bar_from_s": first_time(t, bound_b <= threshold),
        "bound_a_3sigma_within_bar_after_2mm_s": first_time(t, bound_a <= threshold) - t_2mm,
        "bound_b_3sigma_within_bar_after_2mm_s": first_time(t, bound_b <= threshold) - t_2mm,
        "efficient_fit_max_after_conv_pct": {
            name: 100 * float(np.nanmax(np.abs(fit[fit_after]))) for name, fit in fits.items()},
        "efficient_fit_at_2mm_plus_1s_pct": {
            name: 100 * at(t, fit, t_2mm + 1.0) for name, fit in fits.items()},
        "efficient_fit_end_pct": {name: 100 * float(fit[-1]) for name, fit in fits.items()},
        "sfs_wander_max_pct": 100 * float(np.max(np.abs(wander))),
        "sfs_wander_max_after_conv_pct": 100 * float(np.max(np.abs(wander[late])))
        if late.any() else math.nan,
        "sfs_wander_std_pct": 100 * float(np.std(wander)),
        # what a cumulative estimator inherits: the running mean of the per-frame wander
        "sfs_running_mean_max_after_conv_pct": 100 * float(np.max(np.abs(
            (np.cumsum(wander) / np.arange(1, len(wander) + 1))[late]))) if late.any()
        else math.nan,
        "sfs_wander_range_pct": 100 * float(np.ptp(wander)),
        "sfs_wander_trace": [(round(float(a), 2), round(100 * float(b), 2))
                             for a, b in zip(frame_t, wander, strict=True)],
        "filter_max_after_conv_pct": 100 * float(np.max(filter_err)),
        # the same filter, "converged" only once the tracker's information allows the bar
        # (3σ(a) ≤ 2 %), and from 1 s after 2 mm (the bar's own deadline) on
        "filter_max_after_bound_pct": max_error_from(
            series, max(t_conv, first_time(t, bound_a <= threshold))),
        "filter_max_from_2mm_plus_1s_pct": max_error_from(series, max(t_conv, t_2mm + 1.0)),
        "true_poses_max_after_bound_pct": max_error_from(
            true_series, max(float(true_result["first_usable_s"]),
                             first_time(t, bound_a <= threshold))),
        "filter_rms_after_conv_pct": 100 * float(np.sqrt(np.mean(filter_err**2))),
        "filter_final_pct": 100 * float(np.log(series["estimate"][-1])),
        "filter_true_poses_converged_s": float(true_result["first_usable_s"]),
        "filter_true_poses_max_after_conv_pct": 100 * float(np.max(np.abs(
            true_series["usable"][true_after] - 1.0))),
        "oracle_scale": s_oracle,
        # at the ground-truth frames: s*·d_rel / z_true and z_triangulated / z_true (medians
        # at the accepted tracks), SFS's own scale where the tracks are
        "sfs_at_tracks": result["gt_sfs_ratio_at_tracks"],
        "triangulation_at_tracks": result["gt_triangulation_ratio"],
        "true_poses_sfs_at_tracks": true_result["gt_sfs_ratio_at_tracks"],
        "filter_trace": [
            (round(float(a), 2), round(100 * float(np.log(b)), 2),
             round(100 * at(t, bound_a, float(a)), 2), round(100 * at(t, fits["true_handeye"],
                                                                      float(a)), 2))
            for a, b in zip(series["t"][::3], series["estimate"][::3], strict=True)],
    }
    for name, fit in vision_fits.items():
        usable = fit["sigma"] <= BAR / 3.0
        t_usable = float(fit["t"][np.argmax(usable)]) if usable.any() else math.nan
        err = np.abs(np.expm1(fit["log_scale"][fit["t"] >= t_usable]))
        loose = fit["sigma"] <= 0.01
        t_loose = float(fit["t"][np.argmax(loose)]) if loose.any() else math.nan
        err_loose = np.abs(np.expm1(fit["log_scale"][fit["t"] >= t_loose]))
        out[f"vision_fit_{name}"] = {
            "segments": int(fit["segments"][0]),
            "converged_after_2mm_s": t_usable - t_2mm,
            "max_after_pct": 100 * float(np.nanmax(err)) if len(err) else math.nan,
            "final_pct": 100 * float(np.expm1(fit["log_scale"][-1])),
            "sigma_0.01_converged_after_2mm_s": t_loose - t_2mm,
            "sigma_0.01_max_after_pct": 100 * float(np.nanmax(err_loose))
            if len(err_loose) else math.nan,
            "trace": [(round(float(a), 2), round(100 * float(b), 2), round(100 * float(c), 2))
                      for a, b, c in zip(fit["t"][::3], fit["log_scale"][::3], fit["sigma"][::3],
                                         strict=True)],
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--calibration", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None, help="append results here")
    parser.add_argument("--vision-fit", action="store_true",
                        help="also the scale fitted over the vision-relative trajectory")
    parser.add_argument("--anchor-every", type=int, default=0,
                        help="with --vision-fit: a new anchor every N frames (0: when the "
                        "tracks run out)")
    args = parser.parse_args(argv)
    calibration = PhotometricCalibration.load(args.calibration)
    header = ("sequence", "2mm s", "conv s", "σa@conv", "σb@conv", "σa@2mm+1s", "σb@2mm+1s",
              "3σa≤2% after 2mm", "3σb≤2%", "fit max", "fit(he) max", "SFS wander",
              "filter max", "true-pose max")
    rows = []
    for bag in args.bags:
        result = analyse(bag, calibration, args.cache, args.vision_fit, args.anchor_every)
        if args.json:
            with args.json.open("a") as stream:
                stream.write(json.dumps(result) + "\n")
        row = (result["sequence"], result["moved_2mm_at_s"], result["filter_converged_s"],
               result["bound_a_at_convergence_pct"], result["bound_b_at_convergence_pct"],
               result["bound_a_at_2mm_plus_1s_pct"], result["bound_b_at_2mm_plus_1s_pct"],
               result["bound_a_3sigma_within_bar_after_2mm_s"],
               result["bound_b_3sigma_within_bar_after_2mm_s"],
               result["efficient_fit_max_after_conv_pct"]["true_handeye"],
               result["efficient_fit_max_after_conv_pct"]["handeye_error"],
               result["sfs_wander_max_after_conv_pct"], result["filter_max_after_conv_pct"],
               result["filter_true_poses_max_after_conv_pct"])
        rows.append(row)
        print(" | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in row),
              flush=True)
    print("\n| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in row)
              + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
