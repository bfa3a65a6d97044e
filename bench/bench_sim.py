"""Rendering speed of endo_sim at 640x480 (run by hand: python bench/bench_sim.py).

Times one frame of the colon and abdomen scenes (mono8, noise on, default
photometry) along their trajectories, per stage (ray casting, texture,
shading, sensor) and end to end including the sensor_msgs conversion a live
publisher does, with 1 and 2 worker threads. Prints a Markdown table for
docs/benchmarks.md. Wall-clock medians over the frames after a warm-up (numba
compiles on the first call; its cache makes later runs start fast), and the
process CPU time of render(): on a shared machine the wall clock includes
waiting for a core, so "fps if the cores are free" = threads / CPU time.
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any

import numpy as np
from machine import cpu_model

from endo_io.image import array_to_image
from endo_sim import bands
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.surface import SurfaceHits

FRAMES = 60


def bench_scene(scene: str, workers: int, channels: int = 1) -> dict[str, float]:
    bands.set_workers(workers)
    sequence = build_sequence(
        SimulationConfig(scene=scene, duration_s=FRAMES / 30.0 + 1.0, seed=1, channels=channels)
    )
    renderer = sequence.renderer
    target: Any = sequence.scene_of_frame(0)  # a ColonScene or AbdomenScene
    rng = np.random.default_rng(0)
    stages: dict[str, list[float]] = {
        k: [] for k in ("geometry", "texture", "shading", "sensor", "total", "to_msg", "cpu")
    }
    renderer.render(target, sequence.trajectory.pose_at(0), rng)  # warm-up / compile
    for k in range(FRAMES):
        pose = sequence.trajectory.pose_at(int(sequence.frame_times_ns[k]))
        t0 = time.perf_counter()
        distance, normal, uv = target.trace_geometry(pose, renderer.rays, renderer.mask)
        t1 = time.perf_counter()
        albedo = target.texture.sample(uv, np.isfinite(distance))
        t2 = time.perf_counter()
        irradiance = renderer.irradiance(
            SurfaceHits(distance, normal, albedo, target.specular_weight)
        )
        t3 = time.perf_counter()
        renderer.expose(irradiance, rng)
        t4 = time.perf_counter()
        c4 = time.process_time()
        frame = renderer.render(target, pose, rng)
        t5 = time.perf_counter()
        stages["cpu"].append((time.process_time() - c4) * 1e3)
        array_to_image(frame.image, frame.encoding, 0, "endoscope_optical_frame")
        array_to_image(frame.depth, "32FC1", 0, "endoscope_optical_frame")
        t6 = time.perf_counter()
        names = ("geometry", "texture", "shading", "sensor", "total", "to_msg")
        spans = (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5)
        for name, value in zip(names, spans, strict=True):
            stages[name].append(value * 1e3)
    return {name: statistics.median(values) for name, values in stages.items()}


def main() -> None:
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; load average {os.getloadavg()}")
    rows = []
    for scene in ("colon", "abdomen"):
        for workers in (1, 2):
            result = bench_scene(scene, workers)
            rows.append((scene, "mono8", workers, result))
    rows.append(("colon", "rgb8", 2, bench_scene("colon", 2, channels=3)))
    print()
    print(
        "| scene | encoding | threads | ray cast ms | texture ms | shading ms | sensor ms | "
        "render() ms | fps | render() CPU ms | fps if the cores are free | + Image msgs ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for scene, encoding, workers, r in rows:
        print(
            f"| {scene} | {encoding} | {workers} | {r['geometry']:.1f} | {r['texture']:.1f} | "
            f"{r['shading']:.1f} | {r['sensor']:.1f} | {r['total']:.1f} | {1e3 / r['total']:.0f} | "
            f"{r['cpu']:.1f} | {1e3 * workers / r['cpu']:.0f} | {r['to_msg']:.1f} |"
        )


if __name__ == "__main__":
    main()
