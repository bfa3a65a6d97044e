#!/usr/bin/env python3
"""Speed of endo_flow: the per-frame step at 640×480, and the voxel map over 10 minutes.

1. ``FlowPipeline.process`` on a rendered 640×480 abdomen sequence (endo_sim,
   textured, specular; depth_relative = true depth / s; poses with the
   tracker's noise), map off: wall time per frame of tracking + triangulation
   + scale + metric depth + world cloud, the process's CPU time per frame
   (which the machine's load inflates far less than the wall time) and the
   wall time's median and 90th percentile after a warm-up, for several
   tracking configurations compared in the same run (interleaved frame by
   frame, so that load changes hit all alike).
2. ``VoxelMap.insert`` of a 10-minute sequence: 18 000 frames of the decimated
   cloud (every 4th pixel: 19 200 points), a camera advancing 10 mm/s along a
   22 mm tube (a colon), 1 mm voxels: insert time per frame and memory.

3. With ``--reference DIR`` (an older endo_flow source tree, e.g.
   ``git archive main src/endo_flow | tar -x -C DIR``): the default step alone
   in one process, as the live node runs it, for the reference and for this
   tree in alternating child processes (``--rounds`` each), on the same
   frames: CPU per frame and the ratio new / reference per round.
4. With ``--rss-loops N``: the step with the map on over the frames played N
   times as a looping bag plays them (each loop a clock jump: every state and
   the map reset), the process's RSS after every frame.

5. With ``--map``: instead of the tracking configurations of 1., the step
   with the map on, at the map's decimations and rates (``map_decimation``,
   ``map_every``) against the map off, interleaved frame by frame alike: what
   the map at full resolution costs per frame.

Usage: ``bench/bench_flow.py [--frames 150] [--map-minutes 10] [--cache FILE]
[--reference DIR --rounds 2] [--rss-loops 0] [--skip-configs] [--map]``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine import cpu_model  # bench/ is on sys.path when run as bench/bench_flow.py

from endo_flow.pipeline import FlowFrame, FlowOptions, FlowPipeline
from endo_flow.tracking import TrackingOptions
from endo_flow.voxel_map import VoxelMap
from endo_io.pose import invert_transform
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.tracker import TrackerModel
from endo_tracker_bridge.composition import compose_camera_pose

S = 0.04


def render(frames: int) -> tuple[list[FlowFrame], np.ndarray]:
    """A 640×480 abdomen sweep with noisy tracker poses."""
    config = SimulationConfig(scene="abdomen", duration_s=frames / 30.0 + 0.1, seed=3)
    seq = build_sequence(config)
    times = seq.frame_times_ns[:frames]
    poses = seq.trajectory.poses_at(times)
    model = TrackerModel()
    noisy = model.add_noise(model.true_marker_poses(poses), np.random.default_rng(0))
    tracked = compose_camera_pose(invert_transform(model.T_tracker_world), noisy,
                                  model.T_marker_camera)
    rng = np.random.default_rng(3)
    out = []
    for k, t in enumerate(times):
        frame = seq.renderer.render(seq.scenes[0], poses[k], rng)
        valid = seq.renderer.mask & np.isfinite(frame.depth)
        image = np.where(valid, frame.irradiance[..., 0] / seq.renderer.light_map, np.nan)
        out.append(FlowFrame(int(config.start_ns + t), image.astype(np.float32),
                             (frame.depth / S).astype(np.float32), seq.camera, tracked[k]))
    return out, poses


def per_frame(frames: list[FlowFrame], configs: dict[str, FlowOptions], warmup: int
              ) -> dict[str, dict[str, float]]:
    """Interleaved runs of every configuration; per-frame wall-time statistics."""
    pipes = {name: FlowPipeline(options) for name, options in configs.items()}
    wall: dict[str, list[float]] = {name: [] for name in configs}
    cpu: dict[str, list[float]] = {name: [] for name in configs}
    stages: dict[str, dict[str, list[float]]] = {name: {} for name in configs}
    errors: dict[str, float] = {}
    for k, frame in enumerate(frames):
        for name, pipe in pipes.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            out = pipe.process(frame)
            elapsed, elapsed_cpu = time.perf_counter() - start, time.process_time() - start_cpu
            if k >= warmup:
                wall[name].append(elapsed)
                cpu[name].append(elapsed_cpu)
                for stage, ms in out.diagnostics.timings_ms.items():
                    stages[name].setdefault(stage, []).append(ms)
            if k == len(frames) - 1:
                errors[name] = out.scale.value / S - 1.0
    result = {}
    for name in configs:
        ms = 1e3 * np.array(wall[name])
        row = {"median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)),
               "cpu_ms": 1e3 * float(np.mean(cpu[name])),
               "mean_ms": float(ms.mean()), "scale_error": errors[name]}
        for stage, values in stages[name].items():
            row[f"{stage}_ms"] = float(np.median(values))
        result[name] = row
    return result


def tube_cloud(t_s: float, rng: np.random.Generator, n: int = 19_200) -> np.ndarray:
    """World points of one frame: the wall of a 22 mm tube 5–60 mm ahead of a camera at 10 mm/s."""
    z = 0.010 * t_s + rng.uniform(0.005, 0.060, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    r = 0.022 + 0.0003 * rng.standard_normal(n)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def map_bench(minutes: float, max_voxels: int) -> dict[str, float]:
    """Insert a whole sequence into a voxel map; time per frame, voxels, memory."""
    rng = np.random.default_rng(0)
    voxel_map = VoxelMap(1e-3, max_voxels)
    frames = int(minutes * 60 * 30)
    grey = rng.uniform(0, 255, 19_200)
    times, cpu = [], []
    voxel_map.insert(tube_cloud(0.0, rng), grey)  # numba load
    for k in range(frames):
        points = tube_cloud(k / 30.0, rng)
        start, start_cpu = time.perf_counter(), time.process_time()
        voxel_map.insert(points, grey)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    ms = 1e3 * np.array(times)
    cpu_ms = 1e3 * np.array(cpu)
    return {"frames": frames, "median_ms": float(np.median(ms)),
            "cpu_mean_ms": float(cpu_ms.mean()), "cpu_max_ms": float(cpu_ms.max()),
            "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
            "voxels": len(voxel_map), "evicted": voxel_map.evicted,
            "memory_mb": voxel_map.nbytes / 2**20, "max_voxels": max_voxels}


def load_frames(frames: int, cache: str | None) -> list[FlowFrame]:
    """The rendered frames, from ``cache`` if it holds them (written there otherwise)."""
    if cache and Path(cache).is_file():
        with Path(cache).open("rb") as stream:
            held: list[FlowFrame] = pickle.load(stream)
        if len(held) >= frames:
            return held[:frames]
    rendered, _ = render(frames)
    if cache:
        with Path(cache).open("wb") as stream:
            pickle.dump(rendered, stream)
    return rendered


def step_alone(frames: list[FlowFrame], warmup: int) -> dict[str, float]:
    """The default step (map off) alone in this process: CPU and wall per frame."""
    pipe = FlowPipeline(FlowOptions(map_enabled=False))
    cpu, wall = [], []
    stages: dict[str, list[float]] = {}
    out = None
    for k, frame in enumerate(frames):
        start, start_cpu = time.perf_counter(), time.process_time()
        out = pipe.process(frame)
        elapsed, elapsed_cpu = time.perf_counter() - start, time.process_time() - start_cpu
        if k >= warmup:
            wall.append(elapsed)
            cpu.append(elapsed_cpu)
            for stage, ms in out.diagnostics.timings_ms.items():
                stages.setdefault(stage, []).append(ms)
    assert out is not None
    row = {"cpu_ms": 1e3 * float(np.mean(cpu)), "cpu_max_ms": 1e3 * float(np.max(cpu)),
           "wall_median_ms": 1e3 * float(np.median(wall)),
           "wall_p90_ms": 1e3 * float(np.percentile(wall, 90)),
           "scale_error": out.scale.value / S - 1.0}
    for stage, values in stages.items():
        row[f"{stage}_ms"] = float(np.mean(values))
    return row


def compare_reference(reference: str, cache: str, frames: int, warmup: int, rounds: int
                      ) -> list[tuple[dict[str, float], dict[str, float]]]:
    """Alternate child processes of the reference tree and this one; their step_alone rows."""
    source = Path(reference) / "src" / "endo_flow"
    if not (source / "endo_flow" / "pipeline.py").is_file():
        raise SystemExit(f"{source} holds no endo_flow package")
    command = [sys.executable, __file__, "--worker", "--cache", cache, "--frames", str(frames),
               "--warmup", str(warmup)]
    results = []
    for _ in range(rounds):
        pair = []
        for path in (str(source), None):
            env = dict(os.environ)
            if path:  # ahead of the editable install of this tree
                env["PYTHONPATH"] = os.pathsep.join(filter(None, [path,
                                                                   env.get("PYTHONPATH")]))
            done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
            pair.append(json.loads(done.stdout.strip().splitlines()[-1]))
        results.append((pair[0], pair[1]))
    return results


def rss_mb() -> float:
    """Resident set size of this process, MB."""
    resident = int(Path("/proc/self/statm").read_text().split()[1])
    return resident * os.sysconf("SC_PAGE_SIZE") / 2**20


def rss_over_loops(frames: list[FlowFrame], loops: int) -> list[float]:
    """The step with the map on over ``loops`` plays of the frames; RSS after every frame."""
    from endo_io.errors import ClockJumpError

    pipe = FlowPipeline(FlowOptions())
    samples = []
    for _ in range(loops):
        for frame in frames:
            # the loop's first frame: every state reset, as the node does
            with contextlib.suppress(ClockJumpError):
                pipe.process(frame)
            samples.append(rss_mb())
    return samples


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--map-minutes", type=float, default=10.0)
    parser.add_argument("--cache", help="pickle of the rendered frames (read, or written)")
    parser.add_argument("--reference", help="an older tree holding src/endo_flow to compare")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--rss-loops", type=int, default=0)
    parser.add_argument("--skip-configs", action="store_true")
    parser.add_argument("--map", action="store_true",
                        help="compare the map's decimations and rates instead of tracking's")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:  # one child of --reference: the step alone, one JSON line
        print(json.dumps(step_alone(load_frames(args.frames, args.cache), args.warmup)))
        return 0
    print(f"# bench_flow {datetime.date.today()} on {cpu_model()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    frames = load_frames(args.frames, args.cache)
    alone = step_alone(frames, args.warmup)
    print(f"default step alone ({len(frames) - args.warmup} frames after {args.warmup}): CPU "
          f"{alone['cpu_ms']:.2f} ms per frame (max {alone['cpu_max_ms']:.1f}), wall median "
          f"{alone['wall_median_ms']:.2f} ms, p90 {alone['wall_p90_ms']:.2f} ms; stages (wall, "
          "mean ms): " + ", ".join(f"{k[:-3]} {v:.2f}" for k, v in alone.items()
                                   if k.endswith("_ms") and not k.startswith(("cpu", "wall")))
          + f"; scale error at the end {100 * alone['scale_error']:+.3f} %", flush=True)
    if args.reference:
        cache = args.cache or "/tmp/bench_flow_frames.pkl"
        if not Path(cache).is_file():
            with Path(cache).open("wb") as stream:
                pickle.dump(frames, stream)
        print(f"reference {args.reference} against this tree, alternated, {args.rounds} rounds:")
        print("| round | reference CPU ms | this tree CPU ms | ratio | reference wall median |"
              " this tree wall median | scale error reference / this tree |")
        print("|---|---|---|---|---|---|---|")
        for k, (old, new) in enumerate(compare_reference(args.reference, cache, args.frames,
                                                          args.warmup, args.rounds), 1):
            print(f"| {k} | {old['cpu_ms']:.2f} | {new['cpu_ms']:.2f} | "
                  f"{new['cpu_ms'] / old['cpu_ms']:.2f} | {old['wall_median_ms']:.2f} | "
                  f"{new['wall_median_ms']:.2f} | {100 * old['scale_error']:+.4f} % / "
                  f"{100 * new['scale_error']:+.4f} % |", flush=True)
    if args.rss_loops > 0:
        samples = np.array(rss_over_loops(frames, args.rss_loops))
        n = len(frames)
        per_loop = samples.reshape(args.rss_loops, n)
        print(f"RSS with the map on over {args.rss_loops} loops of {n} frames (MB): first frame "
              f"{samples[0]:.0f}; per loop min/max "
              + ", ".join(f"{lo:.0f}/{hi:.0f}" for lo, hi in zip(per_loop.min(axis=1),
                                                                per_loop.max(axis=1),
                                                                strict=True)), flush=True)
    base = FlowOptions(map_enabled=False)

    def tracking(**changes: object) -> FlowOptions:
        return dataclasses.replace(base, tracking=dataclasses.replace(TrackingOptions(),
                                                                      **changes))

    configs: dict[str, FlowOptions] = {} if args.skip_configs else {
        "default (200 tracks, half res, 2 levels, reseed/10)": base,
        "100 tracks": tracking(max_tracks=100),
        "400 tracks": tracking(max_tracks=400),
        "full resolution, 3 levels": tracking(downsample=1, pyramid_levels=3),
        "seeds not checked for highlights": tracking(mask_highlights=False),
        "cloud every 8th pixel": dataclasses.replace(base, cloud_decimation=8),
    }
    if args.map and not args.skip_configs:
        on = dataclasses.replace(base, map_enabled=True)
        configs = {
            "map off": base,
            "map every 4th pixel, every frame": dataclasses.replace(on, map_decimation=4),
            "map full resolution, every frame": dataclasses.replace(on, map_decimation=1),
            **{f"map full resolution, every {n}th frame":
               dataclasses.replace(on, map_decimation=1, map_every=n) for n in (2, 4, 8)},
        }
    results = per_frame(frames, configs, args.warmup) if configs else {}
    if results:
        print("| configuration | CPU ms (mean) | wall median ms | p90 ms | tracking |"
              " triangulation | scale | depth | cloud | map (median of frames fused) |"
              " scale error at the end |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, row in results.items():
        print(f"| {name} | {row['cpu_ms']:.1f} | {row['median_ms']:.1f} | {row['p90_ms']:.1f} | "
              f"{row.get('tracking_ms', 0):.1f} | {row.get('triangulation_ms', 0):.1f} | "
              f"{row.get('scale_ms', 0):.1f} | {row.get('depth_ms', 0):.1f} | "
              f"{row.get('cloud_ms', 0):.1f} | {row.get('map_ms', 0):.1f} | "
              f"{100 * row['scale_error']:+.2f} % |", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.1f}", flush=True)
    if args.map_minutes > 0:
        result = map_bench(args.map_minutes, 2_000_000)
        print(f"voxel map, {args.map_minutes:g} min ({result['frames']} frames of 19 200 "
              f"points, 1 mm voxels, capacity {result['max_voxels']}): insert median "
              f"{result['median_ms']:.2f} ms, p99 {result['p99_ms']:.2f} ms, max "
              f"{result['max_ms']:.1f} ms (CPU mean {result['cpu_mean_ms']:.2f} ms, max "
              f"{result['cpu_max_ms']:.1f} ms); {result['voxels']} voxels held, "
              f"{result['evicted']} evicted; memory {result['memory_mb']:.0f} MB (fixed)")
        print(f"load average after: {os.getloadavg()[0]:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
