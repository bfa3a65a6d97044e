"""Hand–eye calibration: time and accuracy on synthetic views, and on the simulator's bag.

Run by hand (``make bench`` or ``python bench/bench_handeye.py``); results go
into docs/benchmarks.md under "endo_tracker_bridge hand–eye".

1. Synthetic correspondences (no images): a camera 25 cm from the tracked
   marker swings around a checkerboard; the tracker samples at 60 Hz with
   0.25 mm / 0.1° noise, 3 % dropouts and 23.4 ms latency; corners get
   0.1 px noise. For several numbers of views: solver time and errors.
2. The closed forms alone (``cv2.calibrateHandEye`` through
   ``solve_hand_eye``) on the 20 s synthetic recording at the true offset:
   time per call and error of each method, for several numbers of views.
3. bags/handeye.mcap when present: corner detection time per image, solver
   time, and the errors against <bag>.ground_truth.yaml.
4. The same bag as ``endo-handeye bags/handeye.mcap`` runs it with no board
   flags: board size detection, square size estimated from the tracker, then
   the calibration; its time and errors (square size, hand–eye, offset).
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import cv2
import numpy as np
import scipy
import yaml
from machine import cpu_model

from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.handeye import (
    METHODS,
    MS,
    Checkerboard,
    OffsetSearch,
    calibrate_hand_eye,
    marker_poses_at,
    solve_hand_eye,
)
from endo_tracker_bridge.handeye_cli import (
    NOMINAL_SQUARE_MM,
    calibrate_observations,
    read_observations,
    resolve_board,
    with_estimated_square,
)
from endo_tracker_bridge.synthetic import (
    BOARD,
    CAMERA,
    T_MARKER_CAMERA,
    synthetic_recording,
    transform_error,
)

ROOT = Path(__file__).resolve().parents[1]


def _synthetic(duration_s):
    """The tests' synthetic scene, the tracker clock at phase 0, stamps from 0."""
    return synthetic_recording(duration_s=duration_s, random_phase=False, epoch_ns=0)


def bench_synthetic():
    print("## synthetic correspondences (23.4 ms latency, search ±200 ms)")
    print("| views | solver s | translation error mm | rotation error ° | offset error ms |")
    print("|---|---|---|---|---|")
    for duration in (5.0, 10.0, 20.0):
        views, stamps, poses = _synthetic(duration)
        start = time.perf_counter()
        result = calibrate_hand_eye(views, stamps, poses, BOARD, CAMERA, OffsetSearch())
        elapsed = time.perf_counter() - start
        t_err, r_err = transform_error(T_MARKER_CAMERA, result.T_marker_camera)
        print(
            f"| {len(views)} | {elapsed:.2f} | {t_err:.3f} | {r_err:.3f} | "
            f"{result.time_offset_ns / MS - 23.4:+.3f} |"
        )


def bench_closed_forms():
    views, stamps, poses = _synthetic(20.0)
    A, valid = marker_poses_at(
        stamps, poses, np.array([v.stamp_ns for v in views]) + round(23.4 * MS), 60 * MS
    )
    B = np.stack([v.T_camera_target for v in views])[valid]
    A = A[valid]
    print("## closed forms alone (cv2.calibrateHandEye), 20 s synthetic, true offset")
    print("| views | " + " | ".join(f"{m} ms, mm, °" for m in METHODS) + " |")
    print("|---|" + "---|" * len(METHODS))
    for count in (24, 60, 100, len(A)):
        pick = np.unique(np.linspace(0, len(A) - 1, count).round().astype(int))
        cells = []
        for method in METHODS:
            solve_hand_eye(A[pick], B[pick], method)  # warm-up
            repeats = 5
            start = time.perf_counter()
            for _ in range(repeats):
                X = solve_hand_eye(A[pick], B[pick], method)
            elapsed_ms = 1e3 * (time.perf_counter() - start) / repeats
            t_err, r_err = transform_error(T_MARKER_CAMERA, X)
            cells.append(f"{elapsed_ms:.1f}, {t_err:.3f}, {r_err:.4f}")
        print(f"| {len(pick)} | " + " | ".join(cells) + " |")


def bench_bag(bag: Path):
    truth_path = bag.with_name(bag.stem + ".ground_truth.yaml")
    truth = yaml.safe_load(truth_path.read_text())
    spec = truth["scene"]["checkerboard"]
    board = Checkerboard(*spec["inner_corners"], spec["square_m"])
    start = time.perf_counter()
    unit = LengthUnit.parse(truth["tracker"]["units"])
    observations = read_observations(bag, board, pose_unit=unit)
    detect_s = time.perf_counter() - start
    start = time.perf_counter()
    result = calibrate_observations(observations, board)
    solve_s = time.perf_counter() - start
    X_true = np.asarray(truth["tracker"]["T_marker_camera"], dtype=np.float64).reshape(4, 4)
    t_err, r_err = transform_error(X_true, result.T_marker_camera)
    latency_s = float(truth["tracker"]["latency_s"])
    print(f"## {bag.name}")
    print(
        f"images {observations.images}, board found in {len(observations.views)}; "
        f"read+detect+PnP {detect_s:.2f} s ({1e3 * detect_s / max(1, observations.images):.1f} "
        f"ms/image, 2 threads), solver {solve_s:.2f} s"
    )
    print(
        f"translation error {t_err:.3f} mm, rotation error {r_err:.3f}°, offset error "
        f"{result.time_offset_ns / MS - latency_s * 1e3:+.3f} ms; residuals "
        f"{result.translation_rms_mm:.3f} mm, {result.rotation_rms_deg:.3f}°, "
        f"{result.reprojection_rms_px:.2f} px"
    )


def bench_bag_no_flags(bag: Path):
    """``endo-handeye BAG`` without --board/--square-mm: detection, estimation, calibration."""
    truth = yaml.safe_load(bag.with_name(bag.stem + ".ground_truth.yaml").read_text())
    unit = LengthUnit.parse(truth["tracker"]["units"])
    start = time.perf_counter()
    board = resolve_board(bag, "/endoscope/image_raw", None, NOMINAL_SQUARE_MM)
    detect_s = time.perf_counter() - start
    observations = read_observations(bag, board, pose_unit=unit)
    start = time.perf_counter()
    observations, board = with_estimated_square(observations, board)
    square_m = board.square_m
    square_s = time.perf_counter() - start
    start = time.perf_counter()
    result = calibrate_observations(observations, board)
    solve_s = time.perf_counter() - start
    X_true = np.asarray(truth["tracker"]["T_marker_camera"], dtype=np.float64).reshape(4, 4)
    t_err, r_err = transform_error(X_true, result.T_marker_camera)
    true_square = float(truth["scene"]["checkerboard"]["square_m"])
    print(f"## {bag.name}, no board flags")
    print(
        f"board {board.columns}x{board.rows} detected in {detect_s:.2f} s; square "
        f"{square_m * 1e3:.3f} mm (truth {true_square * 1e3:g}, "
        f"{100 * (square_m / true_square - 1):+.2f} %) in {square_s:.2f} s; solver {solve_s:.2f} s"
    )
    print(
        f"translation error {t_err:.3f} mm, rotation error {r_err:.3f}°, offset error "
        f"{result.time_offset_ns / MS - truth['tracker']['latency_s'] * 1e3:+.3f} ms; residuals "
        f"{result.translation_rms_mm:.3f} mm, {result.rotation_rms_deg:.3f}°, "
        f"{result.reprojection_rms_px:.2f} px"
    )


def main():
    print(
        f"machine: {cpu_model()}, Python {platform.python_version()}, numpy {np.__version__}, "
        f"scipy {scipy.__version__}, OpenCV {cv2.__version__}"
    )
    bench_synthetic()
    bench_closed_forms()
    bag = ROOT / "bags" / "handeye.mcap"
    if bag.exists():
        bench_bag(bag)
        bench_bag_no_flags(bag)


if __name__ == "__main__":
    main()
