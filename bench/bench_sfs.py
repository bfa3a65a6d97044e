"""Benchmark of endo_sfs: near-light ms/frame and the orthographic solver vs scikit-fmm.

Run by hand (``make bench`` runs every bench_*.py):

    .venv/bin/python bench/bench_sfs.py [--frames 30] [--repeats 15]

Part 1, near-light: a camera moving inside a tube (the scene of the
accuracy tests: nearest wall point in view), σ = 0.3, 320×240 and 640×480,
90° horizontal field of view with a circular mask. Each frame is solved
warm-started from the previous frame's solution, exactly as the sfs node
does; wall time per frame (median, 90th percentile) of the whole
``endo_sfs.solve`` call (masking, resampling to the solve grid, sweeping,
resampling back), at solve_scale 1 and 0.5 with one and two threads, plus
the process CPU time, the cold-start time and the AbsRel against the rendered
ground truth.

Part 2, orthographic Eikonal vs scikit-fmm on the same 512² orthographic
sphere image, interleaved in one run: endo_sfs.orthographic (fast sweeping,
orders 1, 2 and 3 = WENO3) against ``skfmm.travel_time`` (orders 1 and 2).
Both get the same image; each computes its speed F = √(1/c² − 1) and its
sources (the brightest pixels) itself, and both are timed from the image to
the depth. scikit-fmm's bare ``travel_time`` call is timed as well. Errors
are mean and max |z − z*| relative to the depth range.
"""

from __future__ import annotations

import os

# numpy's OpenBLAS keeps a worker spinning after each BLAS call (the AbsRel
# fit below), which would take the second core from the solver's threads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import platform
import subprocess
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import skfmm

from endo_io.camera import CameraModel
from endo_io.pose import pose_to_matrix, rigid_transform
from endo_sfs import relative_depth
from endo_sfs.evaluation import depth_error
from endo_sfs.options import SfsOptions
from endo_sfs.orthographic import eikonal_speed, solve_orthographic
from endo_sfs.reflectance import colocated_cosine, colocated_radiance
from endo_sfs.relative_depth import solve
from endo_sfs.synthetic import (
    SCENE_NAMES,
    TubeInterior,
    near_light_surface,
    orthographic_scene,
    posed_tube_sequence,
    quantise_8bit,
    render_near_light,
    render_orthographic,
    scene_camera,
)
from endo_sfs.warm_start import WarmStartChain


def machine() -> str:
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        model = next(line.split(":", 1)[1].strip() for line in text.splitlines()
                     if line.startswith("Model name"))
    except (OSError, subprocess.CalledProcessError, StopIteration):
        model = platform.processor() or "unknown"
    load = open("/proc/loadavg").read().split()[:3]  # noqa: PTH123, SIM115
    return f"{model}, load average {' '.join(load)}"


# ------------------------------------------------------------------ near-light


def tube_frames(camera: CameraModel, frames: int, roughness: float):
    """Renderings of a camera advancing 0.2 % of the tube radius per frame and turning slowly."""
    out = []
    for k in range(frames):
        beta = 1.1 + 0.002 * k
        axis = (0.0, -np.sin(beta), np.cos(beta))
        # The camera moves along the axis: in camera coordinates the axis point moves back.
        point = np.array([0.0, -0.6 + 0.0005 * k, 0.0]) - 0.002 * k * np.asarray(axis)
        out.append(render_near_light(camera, TubeInterior(tuple(point), axis, 1.0), roughness))
    return out


def bench_near_light(frames: int) -> list[str]:
    rows = []
    roughness = 0.3
    for width, height in ((320, 240), (640, 480)):
        focal = (width / 2) / np.tan(np.radians(45.0))
        camera = CameraModel.pinhole(width, height, focal, focal, (width - 1) / 2,
                                     (height - 1) / 2)
        mask = camera.fov_mask(0.5 * width)
        sequence = tube_frames(camera, frames, roughness)
        for scale, threads in ((1.0, 1), (1.0, 2), (0.5, 1), (0.5, 2)):
            options = SfsOptions(roughness=roughness, solve_scale=scale, threads=threads)
            solve(sequence[0].irradiance, camera, options, mask=mask)  # grid, kernels cached
            previous = None
            warm_times, warm_cpu, cold_times, errors, updates = [], [], [], [], []
            for rendering in sequence:
                start, start_cpu = time.perf_counter(), time.process_time()
                solution = solve(rendering.irradiance, camera, options, mask=mask,
                                 warm_start=previous)
                warm_times.append(time.perf_counter() - start)
                warm_cpu.append(time.process_time() - start_cpu)
                if previous is not None:
                    updates.append(solution.info.updates / np.isfinite(
                        solution.node_solution).sum())
                previous = solution
                start = time.perf_counter()
                solve(rendering.irradiance, camera, options, mask=mask)
                cold_times.append(time.perf_counter() - start)
                errors.append(depth_error(solution.depth, rendering.depth, mask).abs_rel)
            warm = np.array(warm_times[1:]) * 1e3
            cpu = np.array(warm_cpu[1:]) * 1e3
            cold = np.array(cold_times) * 1e3
            nodes = np.isfinite(previous.node_solution).sum()
            rows.append(
                f"| {width}×{height} | {scale:g} | {threads} | {nodes} | {np.median(warm):.1f} | "
                f"{np.percentile(warm, 90):.1f} | {np.median(cpu):.1f} | {np.median(cold):.1f} | "
                f"{np.mean(updates):.2f} | {100 * np.mean(errors):.3f} % |"
            )
            print(rows[-1], flush=True)
    return rows


# ------------------------------------------------------------------ warm starts


def _noisy(pose: np.ndarray, rng: np.random.Generator, metres: float, degrees: float):
    """A pose with tracker-like noise (per-axis RMS ``metres`` and ``degrees``)."""
    noise = rigid_transform(rng.normal(0.0, np.radians(degrees), 3), rng.normal(0.0, metres, 3))
    return pose @ noise


def _warm_start_modes(true_scale: float | None) -> dict[str, dict]:
    modes: dict[str, dict] = {"previous frame as is": {"predict": False}}
    modes["pose-predicted, scale fitted"] = {"predict": True}
    if true_scale is not None:
        modes["pose-predicted, true scale"] = {"predict": True, "scale": true_scale}
    modes["pose-predicted, rotation only"] = {"predict": True, "rotation_only": True}
    return modes


def compare_warm_starts(
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    camera: CameraModel,
    options: SfsOptions,
    mask: np.ndarray | None,
    true_scale: float | None,
    lag: int,
    label: str,
    scaling: str = "least_squares",
) -> list[str]:
    """Each warm start on one sequence, interleaved frame by frame (so load hits all alike).

    frames: (irradiance, T_world_camera, true depth or None). lag: the warm
    start is the frame ``lag`` before (2: two SFS workers taking every other
    frame). Returns table rows.
    """
    modes = _warm_start_modes(true_scale)
    chains = {name: WarmStartChain(predict=mode["predict"], keep=lag + 1)
              for name, mode in modes.items()}
    for name, mode in modes.items():
        if "scale" in mode:
            chains[name].set_scale(mode["scale"])
    poses = {k: frame[1] for k, frame in enumerate(frames)}
    stats: dict[str, list[tuple[float, float, float]]] = {name: [] for name in modes}
    errors: dict[str, list[float]] = {name: [] for name in modes}
    rotation_only = {k: np.block([[p[:3, :3], np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]])
                     for k, p in poses.items()}
    solve(frames[0][0], camera, options, mask=mask)  # kernels and grid loaded
    for k, (irradiance, _, truth) in enumerate(frames):
        for name, mode in modes.items():
            table = rotation_only if mode.get("rotation_only") else poses
            chain = chains[name]
            start, start_cpu = time.perf_counter(), time.process_time()
            # The frame `lag` back is the newest one solved before this one.
            warm = chain.warm_start(k, lambda stamp, table=table: table.get(stamp))
            solution = solve(irradiance, camera, options, mask=mask, warm_start=warm)
            wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
            chain.add(k, solution)
            if k >= lag:
                nodes = np.isfinite(solution.node_solution).sum()
                stats[name].append((wall, cpu, solution.info.updates / nodes))
            if truth is not None:
                errors[name].append(depth_error(solution.depth, truth, mask,
                                                scaling=scaling).abs_rel)
            if lag > 1:
                # Another worker solved the frames in between: this chain
                # only ever starts from its own frame `lag` back.
                chain._frames = {s: f for s, f in chain._frames.items() if (k - s) % lag == 0}
    rows = []
    for name in modes:
        r = np.array(stats[name])
        rows.append(f"| {label} | {lag} | {name} | {1e3 * np.median(r[:, 0]):.1f} | "
                    f"{1e3 * np.median(r[:, 1]):.1f} | {np.mean(r[:, 2]):.2f} | "
                    f"{np.mean(errors[name]):.4f} |")
        print(rows[-1], flush=True)
    return rows


def bench_warm_starts(frames: int, phantom_bag: str | None, calibration: str | None,
                      threads: int) -> None:
    """Warm starts compared on the posed tube and, given a bag and calibration, the phantom."""
    print("\nwarm starts (ms per frame, wall and process CPU; node solves per node; AbsRel)")
    print("| sequence | lag | warm start | wall median | CPU median | solves/node | AbsRel |")
    print("|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(3)
    camera = CameraModel.pinhole(640, 480, 320.0, 320.0, 319.5, 239.5)
    mask = camera.fov_mask(240.0)
    # The phantom's motion per frame: ~1 % of the wall distance, 0.2°.
    tube = posed_tube_sequence(camera, frames, 0.3, turn_deg=0.2, approach=0.01, advance=0.02)
    for scale in (1.0, 0.5):
        options = SfsOptions(roughness=0.3, solve_scale=scale, threads=threads)
        sequence = [(r.irradiance, _noisy(pose, rng, 0.25e-3 / 0.02, 0.1), r.depth)
                    for r, pose in tube]
        for lag in (1, 2):
            compare_warm_starts(sequence, camera, options, mask, 1.0, lag,
                                f"tube 640×480, solve_scale {scale:g}")
    if not (phantom_bag and calibration):
        return
    sequence, camera, true_scale = phantom_sequence(phantom_bag, calibration, rng)
    mask = camera.fov_mask(240.0)
    for scale in (1.0, 0.5):
        options = SfsOptions(roughness=0.3, solve_scale=scale, mask_highlights=True,
                             threads=threads)
        for lag in (1, 2):
            compare_warm_starts(sequence, camera, options, mask, true_scale, lag,
                                f"phantom, solve_scale {scale:g}", scaling="median")


def phantom_sequence(bag: str, calibration: str, rng: np.random.Generator):
    """(irradiance, noisy true T_world_camera, true depth or None) per frame, camera, scale.

    The poses are the simulator's true camera poses with the bag's tracker
    noise (0.25 mm, 0.1° RMS) added, standing in for the tracker bridge's;
    the true scale (metres per depth_relative unit) is the median ratio of
    the true to the solved depth on the first frame.
    """
    from endo_calib.calibration import PhotometricCalibration
    from endo_calib.raw_image import to_raw_frame
    from endo_io.bag import BagReader, deserialize
    from endo_io.image import image_to_array
    from endo_io.stamp import stamp_to_ns

    wanted = ("/endoscope/image_raw", "/endoscope/camera_info", "/ground_truth/depth",
              "/ground_truth/camera_pose")
    topics: dict[str, dict[int, object]] = {name: {} for name in wanted}
    with BagReader(bag) as reader:
        for message in reader.messages(list(wanted)):
            msg = deserialize(message)
            topics[message.topic][stamp_to_ns(msg.header.stamp)] = msg
    images, infos, depths, poses = topics.values()
    stamps = sorted(set(images) & set(infos) & set(poses))
    correction = PhotometricCalibration.load(calibration)
    camera = CameraModel.from_camera_info(infos[stamps[0]])
    sequence = []
    for stamp in stamps:
        raw = to_raw_frame(image_to_array(images[stamp]), images[stamp].encoding)
        irradiance = correction.luminance(correction.correct(raw))
        pose = _noisy(pose_to_matrix(poses[stamp])[0], rng, 0.25e-3, 0.1)
        truth = image_to_array(depths[stamp]) if stamp in depths else None
        sequence.append((irradiance, pose, truth))
    first = solve(sequence[0][0], camera, SfsOptions(roughness=0.3, mask_highlights=True),
                  mask=camera.fov_mask(240.0))
    truth = sequence[0][2]
    both = np.isfinite(truth) & np.isfinite(first.depth)
    return sequence, camera, float(np.median(truth[both] / first.depth[both]))


# ------------------------------------------------------------------ workers


def _process_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (/proc/<pid>/stat)."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()  # noqa: PTH123, SIM115
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


#: Seconds after which the workers bench sends a frame again.
RESEND_S = 2.0


def run_workers(
    images: list[np.ndarray], camera: CameraModel, stamps: list[int], workers: int,
    parameters: list[str],
) -> tuple[dict[int, np.ndarray], list[float], float, int, int]:
    """Solve ``images`` with ``workers`` endo-sfs processes; depth by stamp, CPU s each, wall s.

    Frames are published as the workers free up (one in flight per worker),
    so the wall time is the throughput of the workers. Best effort loses a
    large image now and then under load: a frame whose depth has not come
    back after RESEND_S is sent again while it is the newest sent (counted),
    and counted lost once a newer one went out (the nodes refuse an older
    stamp).
    """
    import signal
    import sys
    from pathlib import Path

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo, Image

    from endo_io import topics
    from endo_io.image import array_to_image, image_to_array
    from endo_io.qos import SENSOR_DATA_QOS, reliable_qos
    from endo_io.stamp import stamp_to_ns

    binary = Path(sys.executable).parent / "endo-sfs"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    processes = [subprocess.Popen(
        [str(binary), "--ros-args", "-r", f"__node:=sfs_{index}", *parameters,
         "-p", f"worker_count:={workers}", "-p", f"worker_index:={index}"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    ) for index in range(workers)]
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_sfs_workers", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    received: dict[int, np.ndarray] = {}
    subscription = node.create_subscription(
        Image, topics.DEPTH_RELATIVE,
        lambda msg: received.__setitem__(stamp_to_ns(msg.header.stamp), image_to_array(msg)),
        reliable_qos(100))
    image_pub = node.create_publisher(Image, topics.IMAGE_CORRECTED, SENSOR_DATA_QOS)
    info_pub = node.create_publisher(CameraInfo, topics.CAMERA_INFO, SENSOR_DATA_QOS)

    def spin_until(condition: Callable[[], bool], seconds: float) -> bool:
        deadline = time.monotonic() + seconds
        while not condition() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        return condition()

    try:
        if not spin_until(lambda: image_pub.get_subscription_count() >= workers
                          and info_pub.get_subscription_count() >= workers
                          and subscription.get_publisher_count() >= workers, 180.0):
            raise RuntimeError("the workers did not come up in 180 s")
        spin_until(lambda: False, 2.0)  # discovery of the workers' own depth subscriptions
        cpu_start = [_process_cpu_s(p.pid) for p in processes]
        start = time.perf_counter()
        in_flight: dict[int, tuple[int, float]] = {}  # stamp -> (frame, last sent)

        def send(k: int) -> None:
            info = camera.to_camera_info(stamps[k])
            info_pub.publish(info)
            image_pub.publish(array_to_image(images[k].astype(np.float32), "32FC1", stamps[k],
                                             info.header.frame_id))
            in_flight[stamps[k]] = (k, time.monotonic())

        def settle(limit: int) -> None:
            # best effort loses a 1.2 MB image now and then under load: resend it
            nonlocal resent
            while True:
                for stamp in [s for s in in_flight if s in received]:
                    del in_flight[stamp]
                if len(in_flight) <= limit:
                    return
                executor.spin_once(timeout_sec=0.01)
                newest = max(k for k, _ in in_flight.values())
                for stamp, (k, sent) in list(in_flight.items()):
                    if time.monotonic() - sent <= RESEND_S:
                        continue
                    if k == newest:
                        send(k)
                        resent += 1
                    else:
                        # a newer frame went out: the workers refuse an older stamp
                        del in_flight[stamp]
                        lost.append(stamp)

        resent = 0
        lost: list[int] = []
        for k in range(len(images)):
            settle(workers - 1)
            send(k)
        settle(0)
        wall = time.perf_counter() - start
        cpu = [_process_cpu_s(p.pid) - c for p, c in zip(processes, cpu_start, strict=True)]
    finally:
        for process in processes:
            process.send_signal(signal.SIGINT)
        for process in processes:
            try:
                process.wait(15)
            except subprocess.TimeoutExpired:
                process.kill()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
    return received, cpu, wall, resent, len(lost)


def bench_workers(bag: str, calibration: str, solve_scale: float, frames: int) -> None:
    """One endo-sfs process against two workers on the phantom: frames, CPU per frame, output."""
    sequence, camera, _ = phantom_sequence(bag, calibration, np.random.default_rng(0))
    sequence = sequence[:frames]
    stamps = [1_800_000_000 * 10**9 + k * (10**9 // 30) for k in range(len(sequence))]
    images = [irradiance for irradiance, _, _ in sequence]
    parameters = ["-p", "threads:=1", "-p", "roughness:=0.3", "-p", "fov_radius:=240.0",
                  "-p", f"solve_scale:={solve_scale}"]
    print(f"\nSFS workers, phantom {len(images)} frames, solve_scale {solve_scale:g}, one thread "
          "per worker (separate processes over DDS)")
    print("| workers | frames out | frames sent again | frames lost | CPU s per worker | "
          "CPU ms per frame (all workers) | wall s | frames/s | depth vs one worker: max / "
          "median relative difference |")
    print("|---|---|---|---|---|---|---|---|---|")
    reference: dict[int, np.ndarray] = {}
    for workers in (1, 2):
        depths, cpu, wall, resent, lost = run_workers(images, camera, stamps, workers, parameters)
        if workers == 1:
            reference = depths
        differences = []
        for stamp, depth in depths.items():
            if stamp in reference:
                both = np.isfinite(depth) & np.isfinite(reference[stamp])
                differences.append(np.abs(depth[both] / reference[stamp][both] - 1.0))
        spread = np.concatenate(differences) if differences else np.array([np.nan])
        cpu_each = " / ".join(f"{c:.1f}" for c in cpu)
        print(f"| {workers} | {len(depths)} | {resent} | {lost} | {cpu_each} | "
              f"{1e3 * sum(cpu) / max(1, len(depths)):.1f} | {wall:.1f} | "
              f"{len(depths) / wall:.1f} | {spread.max():.1e} / {np.median(spread):.1e} |",
              flush=True)


# ------------------------------------------------------------------ orthographic


def sphere_image(size: int):
    focal = size / 2.0
    centre = (size - 1) / 2.0 + 0.3
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = (u - centre) / focal, (v - centre + 0.5) / focal
    radius = 0.9
    rho2 = x * x + y * y
    valid = rho2 < (0.85 * radius) ** 2
    root = np.sqrt(np.maximum(radius * radius - rho2, 0.0))
    truth = np.where(valid, 1.0 + radius - root, np.nan)
    image = np.where(valid, colocated_radiance(root / radius, 0.0), np.nan)
    return image, valid, truth, 1.0 / focal


def bench_orthographic(repeats: int) -> list[str]:
    size = 512
    image, valid, truth, h = sphere_image(size)
    depth_range = np.nanmax(truth) - np.nanmin(truth)
    singular_tolerance = 1e-4

    def ours(order: int):
        return lambda: solve_orthographic(image, valid, (h, h), roughness=0.0, order=order,
                                          singular_tolerance=singular_tolerance)[0]

    def skfmm_inputs():
        speed = eikonal_speed(np.where(valid, image, 0.0), 0.0)
        c = colocated_cosine(image, 0.0)
        sources = valid & (c >= np.nanmax(c) - singular_tolerance)
        phi = np.ma.MaskedArray(np.where(sources, -1.0, 1.0), ~valid)
        return phi, 1.0 / np.maximum(speed, 1e-12), sources

    def theirs(order: int):
        def run():
            phi, velocity, sources = skfmm_inputs()
            travel = skfmm.travel_time(phi, velocity, dx=h, order=order)
            depth = 1.0 + np.ma.filled(travel, np.nan)
            depth[sources] = 1.0
            return depth
        return run

    phi, velocity, _ = skfmm_inputs()

    def theirs_bare(order: int):
        return lambda: skfmm.travel_time(phi, velocity, dx=h, order=order)

    methods = {
        "endo_sfs fast sweeping, order 1": ours(1),
        "endo_sfs fast sweeping, order 2": ours(2),
        "endo_sfs fast sweeping, WENO3": ours(3),
        "scikit-fmm travel_time, order 1": theirs(1),
        "scikit-fmm travel_time, order 2": theirs(2),
        "scikit-fmm bare travel_time call, order 2": theirs_bare(2),
    }
    times: dict[str, list[float]] = {name: [] for name in methods}
    cpu: dict[str, list[float]] = {name: [] for name in methods}
    results = {name: fn() for name, fn in methods.items()}  # warm-up, results
    for _ in range(repeats):  # interleaved, so load changes hit every method
        for name, fn in methods.items():
            if "WENO" in name and len(times[name]) >= 3:
                continue  # seconds per call: three runs are enough
            start, start_cpu = time.perf_counter(), time.thread_time()
            fn()
            times[name].append(time.perf_counter() - start)
            cpu[name].append(time.thread_time() - start_cpu)
    rows = []
    for name in methods:
        result = results[name]
        if "bare" in name:
            mean = maximum = float("nan")
        else:
            error = np.abs(np.asarray(result) - truth)[valid & np.isfinite(result)]
            mean, maximum = error.mean() / depth_range, error.max() / depth_range
        t = np.array(times[name]) * 1e3
        c = np.array(cpu[name]) * 1e3
        rows.append(f"| {name} | {np.median(t):.1f} | {np.percentile(t, 90):.1f} | "
                    f"{np.median(c):.1f} | {100 * mean:.4f} % | {100 * maximum:.4f} % |")
        print(rows[-1], flush=True)
    return rows


# ------------------------------------------------------------------ accuracy


def accuracy_table(seeds: int = 3, smoothing: float = 0.0) -> list[str]:
    """AbsRel after one least-squares scale, model × σ × surface × noise, 256²."""
    rows = []
    size = 256
    camera = scene_camera(size)
    mask = camera.fov_mask(0.48 * size)
    for model in ("near_light", "orthographic"):
        for name in SCENE_NAMES:
            for roughness in (0.0, 0.3):
                if model == "near_light":
                    rendering = render_near_light(camera, near_light_surface(name), roughness)
                    region, peak = mask, 0.95
                    boundary, concave = None, False
                else:
                    scene = orthographic_scene(name, camera)
                    rendering = render_orthographic(
                        scene.height, scene.gradient_x, scene.gradient_y, roughness
                    )
                    region = None
                    boundary, concave = scene.boundary_depth, scene.concave
                    peak = 1.0
                cells = []
                for noise_dn in (None, 1.0, 3.0):
                    errors, height_errors = [], []
                    for seed in range(1 if noise_dn is None else seeds):
                        image = rendering.irradiance
                        if noise_dn is not None:
                            rng = np.random.default_rng(seed)
                            image = quantise_8bit(image, rng, noise_dn, peak)
                        options = SfsOptions(
                            model=model, roughness=roughness, concave=concave,
                            smoothing=smoothing if noise_dn else 0.0,
                            singular_tolerance=1e-4 if noise_dn is None else 1e-3,
                        )
                        depth = solve(image, camera, options, mask=region,
                                      boundary_depth=boundary).depth
                        errors.append(depth_error(depth, rendering.depth, region).abs_rel)
                        if model == "orthographic":
                            truth = rendering.depth
                            both = np.isfinite(truth) & np.isfinite(depth)
                            height_errors.append(
                                np.mean(np.abs(depth[both] - truth[both]))
                                / (np.nanmax(truth) - np.nanmin(truth))
                            )
                    cell = f"{100 * np.mean(errors):.3f} %"
                    if height_errors:
                        cell += f" ({100 * np.mean(height_errors):.2f} %)"
                    cells.append(cell)
                rows.append(f"| {model} | {name} | {roughness:g} | " + " | ".join(cells) + " |")
                print(rows[-1], flush=True)
    return rows


def convergence_table() -> list[str]:
    """Error vs grid size and scheme order on the sphere (noise-free, σ = 0)."""
    rows = []
    for size in (64, 128, 256, 512):
        camera = scene_camera(size)
        mask = camera.fov_mask(0.48 * size)
        rendering = render_near_light(camera, near_light_surface("sphere"))
        distance = rendering.depth / camera.unit_rays()[..., 2]
        with np.errstate(invalid="ignore"):
            interior = mask & (rendering.irradiance * distance**2 > 0.3)
        scene = orthographic_scene("sphere", camera)
        ortho = render_orthographic(scene.height, scene.gradient_x, scene.gradient_y)
        depth_range = np.nanmax(scene.height) - np.nanmin(scene.height)
        cells = []
        for order in (1, 2, 3):
            options = SfsOptions(order=order, tolerance=1e-9, max_iterations=300)
            depth = solve(rendering.irradiance, camera, options, mask=mask).depth
            cells.append(f"{100 * depth_error(depth, rendering.depth, interior).abs_rel:.4f} %")
        for order in (1, 2, 3):
            options = SfsOptions(model="orthographic", order=order, singular_tolerance=1e-6,
                                 tolerance=1e-10, max_iterations=300)
            depth = solve(ortho.irradiance, camera, options).depth
            both = np.isfinite(depth) & np.isfinite(scene.height)
            error = np.mean(np.abs(depth[both] - scene.height[both])) / depth_range
            cells.append(f"{100 * error:.4f} %")
        rows.append(f"| {size}² | " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    return rows


def phantom(bag: str, calibration: str, roughness: float, mask_highlights: bool,
            solve_scale: float, fov_radius: float, threads: int, first_sweeps: bool = True,
            highlight_downsample: int = 0) -> None:
    """Median-scaled AbsRel on an endo_sim bag, after endo_calib's correction.

    fov_radius: the field-of-view mask's radius in pixels (0: no mask, as the
    sfs node and endo-process solve by default). highlight_downsample:
    :attr:`endo_sfs.options.SfsOptions.highlight_downsample` (0: the default).
    """
    from recorded_frames import read_recorded_frames

    from endo_calib.calibration import PhotometricCalibration
    from endo_calib.raw_image import to_raw_frame
    from endo_io.image import image_to_array

    frames = read_recorded_frames(bag)
    images, infos, depths, stamps = frames.images, frames.infos, frames.depths, frames.stamps
    correction = PhotometricCalibration.load(calibration)
    camera = CameraModel.from_camera_info(infos[stamps[0]])
    mask = camera.fov_mask(fov_radius) if fov_radius > 0.0 else None
    previous = None
    options = SfsOptions(roughness=roughness, solve_scale=solve_scale,
                         mask_highlights=mask_highlights, threads=threads,
                         first_sweeps=first_sweeps, highlight_downsample=highlight_downsample)
    errors, scales, coverage, wall, updates = [], [], [], [], []
    # Every frame in order, warm-started from the previous one as the node
    # does; the error on the frames with ground truth.
    for stamp in stamps:
        raw = to_raw_frame(image_to_array(images[stamp]), images[stamp].encoding)
        irradiance = correction.luminance(correction.correct(raw))
        start = time.perf_counter()
        warm = previous is not None
        previous = solve(irradiance, camera, options, warm_start=previous, mask=mask)
        if warm:
            wall.append(time.perf_counter() - start)
            updates.append(previous.info.updates / np.isfinite(previous.node_solution).sum())
        if stamp in depths:
            error = depth_error(previous.depth, image_to_array(depths[stamp]), scaling="median")
            errors.append(error.abs_rel)
            scales.append(error.scale)
            coverage.append(error.coverage)
    print(f"{bag}: {len(stamps)} frames ({len(errors)} with depth) {camera.width}×"
          f"{camera.height}, σ = {roughness}, "
          f"mask_highlights {mask_highlights}, solve_scale {solve_scale}, threads {threads}, "
          f"mask radius {fov_radius:g} px, highlight_downsample "
          f"{options.detection_downsample(camera.height)}")
    print("per frame: " + ", ".join(f"{e:.4f}" for e in errors))
    print(f"median-scaled AbsRel: mean {np.mean(errors):.4f}, median {np.median(errors):.4f}, "
          f"max {np.max(errors):.4f}; coverage {np.mean(coverage):.3f}; per-frame scale "
          f"spread {np.std(scales) / np.mean(scales):.3f} (cv)")
    print(f"warm-started wall time per frame (whole solve call, highlight detection "
          f"included): median {1e3 * np.median(wall):.1f} ms, p90 "
          f"{1e3 * np.percentile(wall, 90):.1f} ms; {np.mean(updates):.2f} node solves per node")


def load_reference(tree: str) -> Any:
    """An older ``endo_sfs`` source tree, importable beside this one, as a package of its own.

    tree: a checkout holding ``src/endo_sfs/endo_sfs`` (e.g. ``git worktree add
    /tmp/ref main``). Its files are copied to ``out/bench_sfs_reference/`` with
    every ``endo_sfs`` import renamed ``endo_sfs_reference``, so both solve in one
    process (their numba kernels are cached apart). Returns the reference's
    ``relative_depth`` module.
    """
    import importlib
    import re
    import shutil
    import sys
    from pathlib import Path

    source = Path(tree) / "src" / "endo_sfs" / "endo_sfs"
    if not source.is_dir():
        raise SystemExit(f"--reference: no src/endo_sfs/endo_sfs under {tree}")
    root = Path(__file__).resolve().parents[1] / "out" / "bench_sfs_reference"
    target = root / "endo_sfs_reference"
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    for path in source.glob("*.py"):
        text = re.sub(r"\bendo_sfs\b", "endo_sfs_reference", path.read_text(encoding="utf-8"))
        (target / path.name).write_text(text, encoding="utf-8")
        shutil.copystat(path, target / path.name)  # numba's cache checks the stamp
    sys.path.insert(0, str(root))
    return importlib.import_module("endo_sfs_reference.relative_depth")


def breakdown(bag: str, calibration: str, frames: int, threads: list[int], downsample: int,
              reference: str | None, fov_radius: float = 240.0,
              scales: tuple[float, ...] = (1.0, 0.5),
              tolerances: tuple[float, ...] = ()) -> None:
    """Where the wall and CPU time of a warm phantom frame go, by stage, at solve_scale 1 and 0.5.

    Every frame of the bag in order, warm-started as the node does, highlights
    masked; the median over the frames after the first of each stage of
    :attr:`endo_sfs.relative_depth.SfsSolution.timings` and of the whole
    ``solve`` call (wall and process CPU: on the live graph's two shared
    cores the CPU time is what the other processes lose). One chain per
    thread count in ``threads``; with ``reference`` (an older tree,
    :func:`load_reference`) its chains are solved too. All chains take each
    frame in turn, in an order that alternates, so that load hits them alike:
    per-frame ratios of this tree's wall and CPU time to the reference's (per
    thread count) and of each thread count's to the first's, and the largest
    relative depth difference to the reference. fov_radius: the field-of-view
    mask's radius in pixels (0: no mask, as the sfs node and endo-process
    solve by default; highlight detection then fills the NaN holes). scales:
    the solve_scale values, in turn. tolerances: instead of a reference, one
    chain of this tree per stopping tolerance (``SfsOptions.tolerance``) and
    thread count, each compared with the first tolerance's chain as with a
    reference.
    """
    sequence, camera, _ = phantom_sequence(bag, calibration, np.random.default_rng(0))
    sequence = sequence[:frames]
    mask = camera.fov_mask(fov_radius) if fov_radius > 0.0 else None
    trees: dict[str, Any] = {"this tree": relative_depth}
    tolerance_of: dict[str, float] = {}
    if reference:
        trees["reference"] = load_reference(reference)
    elif tolerances:
        tolerance_of = {f"tolerance {tolerance:g}": tolerance for tolerance in tolerances}
        trees = dict.fromkeys(tolerance_of, relative_depth)
    chains = {(tree, count): module for tree, module in trees.items() for count in threads}
    first = next(iter(trees))

    def label(chain: tuple[str, int]) -> str:
        return f"{chain[0]}, {chain[1]} thread{'s' if chain[1] > 1 else ''}"

    print(f"\nbreakdown, {bag} ({len(sequence)} frames), threads {threads}, "
          f"highlight_downsample {downsample}, mask radius {fov_radius:g} px, chains: "
          f"{', '.join(label(chain) for chain in chains)}")
    for scale in scales:
        options = {}
        for chain, module in chains.items():
            extra: dict[str, int] = {}
            if downsample and "highlight_downsample" in module.SfsOptions.__dataclass_fields__:
                extra["highlight_downsample"] = downsample  # 0: each tree's default
            if chain[0] in tolerance_of:
                extra["tolerance"] = tolerance_of[chain[0]]
            options[chain] = module.SfsOptions(roughness=0.3, solve_scale=scale,
                                               mask_highlights=True, threads=chain[1], **extra)
        previous = {chain: module.solve(sequence[0][0], camera, options[chain], mask=mask)
                    for chain, module in chains.items()}
        walls: dict[tuple[str, int], list[float]] = {chain: [] for chain in chains}
        cpus: dict[tuple[str, int], list[float]] = {chain: [] for chain in chains}
        work: dict[tuple[str, int], list[float]] = {chain: [] for chain in chains}
        stages: dict[int, dict[str, list[float]]] = {count: {} for count in threads}
        differences: dict[tuple[str, int], list[np.ndarray]] = {chain: [] for chain in chains}
        for k, (irradiance, _, _) in enumerate(sequence[1:]):
            names = list(chains) if k % 2 == 0 else list(chains)[::-1]
            for chain in names:
                start, start_cpu = time.perf_counter(), time.process_time()
                previous[chain] = chains[chain].solve(irradiance, camera, options[chain],
                                                      mask=mask, warm_start=previous[chain])
                walls[chain].append(time.perf_counter() - start)
                cpus[chain].append(time.process_time() - start_cpu)
            for chain in chains:
                solution = previous[chain]
                work[chain].append(solution.info.updates
                                   / np.isfinite(solution.node_solution).sum())
            for count in threads:
                ours = previous[(first, count)]
                for stage, seconds in ours.timings.items():
                    stages[count].setdefault(stage, []).append(seconds)
                for chain in chains:
                    if chain[1] != count or chain[0] == first:
                        continue
                    theirs = previous[chain].depth
                    both = np.isfinite(theirs) & np.isfinite(ours.depth)
                    differences[chain].append(np.abs(theirs[both] / ours.depth[both] - 1.0))
        nodes = int(np.isfinite(previous[(first, threads[0])].node_solution).sum())
        print(f"solve_scale {scale:g}: {nodes} nodes")
        for chain in chains:
            print(f"  {label(chain)}: whole solve median {1e3 * np.median(walls[chain]):.1f} ms "
                  f"wall (p90 {1e3 * np.percentile(walls[chain], 90):.1f}, mean "
                  f"{1e3 * np.mean(walls[chain]):.1f}, max {1e3 * np.max(walls[chain]):.1f}), "
                  f"{1e3 * np.median(cpus[chain]):.1f} ms CPU "
                  f"(p90 {1e3 * np.percentile(cpus[chain], 90):.1f}), "
                  f"{np.mean(work[chain]):.2f} node solves per node")
        def ratios(ours: tuple[str, int], theirs: tuple[str, int],
                   walls: dict = walls, cpus: dict = cpus) -> str:
            wall = np.array(walls[ours]) / np.array(walls[theirs])
            cpu = np.array(cpus[ours]) / np.array(cpus[theirs])
            return f"wall {np.median(wall):.3f}, CPU {np.median(cpu):.3f}"

        for count in threads[1:]:
            print(f"  {count} / {threads[0]} threads ({first}), median of per-frame ratios: "
                  + ratios((first, count), (first, threads[0])))
        for count in threads if reference else []:
            print(f"  this tree / reference, {count} thread(s), median of per-frame ratios: "
                  + ratios(("this tree", count), ("reference", count)))
            pooled = np.concatenate(differences[("reference", count)])
            print(f"  relative depth difference to the reference, every pixel of every frame: "
                  f"largest {pooled.max(initial=0.0):.1e}, 99.9th percentile "
                  f"{np.percentile(pooled, 99.9):.1e}")
        for tree in list(tolerance_of)[1:]:
            for count in threads:
                pooled = np.concatenate(differences[(tree, count)])
                print(f"  {tree} / {first}, {count} thread(s), median of per-frame ratios: "
                      + ratios((tree, count), (first, count))
                      + f"; relative depth difference, every pixel of every frame: largest "
                      f"{pooled.max(initial=0.0):.1e}, 99.9th percentile "
                      f"{np.percentile(pooled, 99.9):.1e}, median {np.median(pooled):.1e}")
        for count in threads:
            print(f"{first}, {count} thread(s):")
            print("| stage | median ms | p90 ms |")
            print("|---|---|---|")
            for stage, values in stages[count].items():
                print(f"| {stage} | {1e3 * np.median(values):.2f} | "
                      f"{1e3 * np.percentile(values, 90):.2f} |")
            total = np.sum([np.array(v) for v in stages[count].values()], axis=0)
            rest = np.array(walls[(first, count)]) - total
            print(f"| (rest: checks, warm-start lookup, Python) | {1e3 * np.median(rest):.2f} | "
                  f"{1e3 * np.percentile(rest, 90):.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--accuracy", action="store_true",
                        help="also print the accuracy table of docs/sfs.md")
    parser.add_argument("--phantom", metavar="BAG", help="only evaluate an endo_sim bag")
    parser.add_argument("--calibration", metavar="YAML", help="endo_calib photometric.yaml")
    parser.add_argument("--roughness", type=float, default=0.3)
    parser.add_argument("--no-highlight-mask", action="store_true",
                        help="phantom: solve highlights as diffuse shading")
    parser.add_argument("--solve-scale", type=float, default=1.0)
    parser.add_argument("--no-first-sweeps", action="store_true",
                        help="--phantom: SfsOptions.first_sweeps off (each node solved in the "
                        "first sweep that reaches it)")
    parser.add_argument("--threads", default="1",
                        help="solver threads (--breakdown: a comma-separated list, one chain "
                        "each, e.g. 1,2)")
    parser.add_argument("--fov-radius", type=float, default=240.0,
                        help="--phantom, --breakdown: field-of-view mask radius in pixels "
                        "(--breakdown: 0 = no mask, as the node and endo-process)")
    parser.add_argument("--warm-starts", action="store_true",
                        help="only compare warm starts (previous frame, pose-predicted) on the "
                        "posed tube and, with --phantom-bag/--calibration, the phantom")
    parser.add_argument("--first-pass", action="store_true",
                        help="--warm-starts: always solve with the value-ordered first pass "
                        "(the chain otherwise sweeps once it costs > 2.5 solves per node)")
    parser.add_argument("--phantom-bag", metavar="BAG",
                        help="--warm-starts, --workers: the phantom bag")
    parser.add_argument("--workers", action="store_true",
                        help="only run one endo-sfs process against two workers on the "
                        "phantom (--phantom-bag, --calibration; ROS_DOMAIN_ID from the "
                        "environment)")
    parser.add_argument("--breakdown", action="store_true",
                        help="only time the stages of a warm phantom frame at solve_scale 1 and "
                        "0.5 (--phantom-bag, --calibration, --threads, --frames)")
    parser.add_argument("--scales", default="1,0.5",
                        help="--breakdown: comma-separated solve_scale values (default 1,0.5)")
    parser.add_argument("--highlight-downsample", type=int, default=0,
                        help="--breakdown, --phantom: SfsOptions.highlight_downsample (0: each "
                        "tree's default)")
    parser.add_argument("--tolerances", default="",
                        help="--breakdown: comma-separated SfsOptions.tolerance values, one chain "
                        "each, compared with the first's (instead of --reference)")
    parser.add_argument("--reference", metavar="TREE",
                        help="--breakdown: also solve with the endo_sfs of this older checkout, "
                        "frame by frame in one process (ratios)")
    args = parser.parse_args()
    print(f"machine: {machine()}")
    if args.breakdown:
        if not (args.phantom_bag and args.calibration):
            parser.error("--breakdown needs --phantom-bag and --calibration")
        breakdown(args.phantom_bag, args.calibration, args.frames,
                  [int(count) for count in args.threads.split(",")], args.highlight_downsample,
                  args.reference, args.fov_radius,
                  tuple(float(scale) for scale in args.scales.split(",")),
                  tuple(float(value) for value in args.tolerances.split(",") if value))
        print(f"machine after: {machine()}")
        return
    if args.workers:
        if not (args.phantom_bag and args.calibration):
            parser.error("--workers needs --phantom-bag and --calibration")
        bench_workers(args.phantom_bag, args.calibration, args.solve_scale, args.frames)
        print(f"machine after: {machine()}")
        return
    if args.warm_starts:
        if args.first_pass:
            relative_depth.FIRST_PASS_WORK_LIMIT = float("inf")
            print("value-ordered first pass on every frame")
        bench_warm_starts(args.frames, args.phantom_bag, args.calibration, int(args.threads))
        print(f"machine after: {machine()}")
        return
    if args.phantom:
        if not args.calibration:
            parser.error("--phantom needs --calibration")
        phantom(args.phantom, args.calibration, args.roughness, not args.no_highlight_mask,
                args.solve_scale, args.fov_radius, int(args.threads), not args.no_first_sweeps,
                args.highlight_downsample)
        return
    if args.accuracy:
        print("\nAbsRel after one least-squares scale, 256² (8-bit: mean of 3 noise seeds;"
              " orthographic in brackets: mean |z − z*| / depth range, no fit)")
        print("| model | surface | σ | noise-free | 8-bit, 1 DN noise | 8-bit, 3 DN noise |")
        print("|---|---|---|---|---|---|")
        accuracy_table()
        print("\nAbsRel (smoothing = 1 px on the 8-bit images)")
        accuracy_table(smoothing=1.0)
        print("\nconvergence on the sphere: near-light AbsRel where cos θ > 0.3 | "
              "orthographic mean |z − z*| / range")
        print("| grid | NL order 1 | NL order 2 | NL WENO3 | ortho order 1 | ortho order 2 | "
              "ortho WENO3 |")
        print("|---|---|---|---|---|---|---|")
        convergence_table()
    print("\nnear_light, σ = 0.3, tube sequence, warm-started (ms per frame, wall clock)")
    print("| image | solve_scale | threads | nodes | warm median | warm p90 | "
          "warm CPU (process) median | cold median | updates/node | AbsRel |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    bench_near_light(args.frames)
    print("\northographic sphere 512², same image (ms, wall clock)")
    print("| method | median | p90 | CPU (thread) median | mean error / range | "
          "max error / range |")
    print("|---|---|---|---|---|---|")
    bench_orthographic(args.repeats)
    print(f"machine after: {machine()}")


if __name__ == "__main__":
    main()
