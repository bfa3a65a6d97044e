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
"""

from __future__ import annotations

import platform
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import scipy
import yaml
from scipy.spatial.transform import Rotation

from endo_io.camera import CameraModel
from endo_tracker_bridge.composition import invert_transform
from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.handeye import (
    METHODS,
    Checkerboard,
    OffsetSearch,
    board_view,
    calibrate_hand_eye,
    marker_poses_at,
    solve_hand_eye,
)
from endo_tracker_bridge.handeye_cli import read_observations

ROOT = Path(__file__).resolve().parents[1]
MS = 1_000_000
BOARD = Checkerboard(9, 6, 0.005)
CAMERA = CameraModel.pinhole(
    640, 480, 520.0, 515.0, 322.0, 241.0, D=np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
)


def _transform(rotvec, translation):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


X_TRUE = _transform([0.3, -2.5, 0.4], [0.012, -0.008, -0.24])
W_TRUE = _transform([0.1, 0.2, -0.3], [0.1, -0.05, -1.2])


def _camera_pose(t):
    centre = W_TRUE[:3, :3] @ np.array([0.02, 0.0125, 0.0]) + W_TRUE[:3, 3]
    angles = [
        0.5 * np.sin(2 * np.pi * t / 7.0),
        0.4 * np.sin(2 * np.pi * t / 5.0 + 0.5),
        0.6 * np.sin(2 * np.pi * t / 9.0),
    ]
    R = W_TRUE[:3, :3] @ Rotation.from_euler("yxz", angles).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, centre - R[:, 2] * (0.06 + 0.01 * np.sin(2 * np.pi * t / 3.0))
    return T


def _synthetic(duration_s, seed=0, latency_ms=23.4):
    rng = np.random.default_rng(seed)
    t_tracker = np.arange(0.0, duration_s, 1 / 60)
    t_tracker = t_tracker[rng.random(len(t_tracker)) > 0.03]
    poses = []
    for t in t_tracker:
        A = _camera_pose(t) @ invert_transform(X_TRUE)
        A[:3, 3] += rng.normal(0.0, 0.25e-3 / np.sqrt(3), 3)
        wobble = rng.normal(0.0, np.radians(0.1) / np.sqrt(3), 3)
        A[:3, :3] = A[:3, :3] @ Rotation.from_rotvec(wobble).as_matrix()
        poses.append(A)
    stamps = np.round((t_tracker + latency_ms * 1e-3) * 1e9).astype(np.int64)
    P = BOARD.object_points()
    views = []
    for t in np.arange(0.1, duration_s - 0.1, 1 / 30):
        B = invert_transform(_camera_pose(t)) @ W_TRUE
        uv = CAMERA.project(P @ B[:3, :3].T + B[:3, 3]) + rng.normal(0.0, 0.1, (len(P), 2))
        views.append(board_view(round(t * 1e9), uv, BOARD, CAMERA))
    return views, stamps, np.stack(poses)


def _errors(X_true, X):
    delta = invert_transform(X_true) @ X
    return 1e3 * np.linalg.norm(delta[:3, 3]), np.degrees(
        Rotation.from_matrix(delta[:3, :3]).magnitude()
    )


def bench_synthetic():
    print("## synthetic correspondences (23.4 ms latency, search ±200 ms)")
    print("| views | solver s | translation error mm | rotation error ° | offset error ms |")
    print("|---|---|---|---|---|")
    for duration in (5.0, 10.0, 20.0):
        views, stamps, poses = _synthetic(duration)
        start = time.perf_counter()
        result = calibrate_hand_eye(views, stamps, poses, BOARD, CAMERA, OffsetSearch())
        elapsed = time.perf_counter() - start
        t_err, r_err = _errors(X_TRUE, result.T_marker_camera)
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
            t_err, r_err = _errors(X_TRUE, X)
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
    result = calibrate_hand_eye(
        observations.views,
        observations.tracker_stamps_ns,
        observations.tracker_poses,
        board,
        observations.camera,
    )
    solve_s = time.perf_counter() - start
    X_true = np.asarray(truth["tracker"]["T_marker_camera"], dtype=np.float64).reshape(4, 4)
    t_err, r_err = _errors(X_true, result.T_marker_camera)
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


def main():
    cpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = next(
        (line.split(":", 1)[1].strip() for line in cpu.splitlines() if "Model name" in line), "?"
    )
    print(
        f"machine: {model}, Python {platform.python_version()}, numpy {np.__version__}, "
        f"scipy {scipy.__version__}, OpenCV {cv2.__version__}"
    )
    bench_synthetic()
    bench_closed_forms()
    bag = ROOT / "bags" / "handeye.mcap"
    if bag.exists():
        bench_bag(bag)


if __name__ == "__main__":
    main()
