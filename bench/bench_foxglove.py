"""Benchmark: endo-foxglove's conversions per message (endo_foxglove.convert).

Times what the bridge's sending thread does for one message before handing
it to foxglove-sdk: a 640x480 organised world cloud (10 % NaN) to a
decimated packed PointCloud (100 000 points, the default, and all 276 480
finite points), a 200 000-point rgb map, a 640x480 32FC1 depth image, a
640x480 rgb8 image, a 32FC3 colour irradiance frame (scaled to rgb8) and a
CameraInfo; each once more with the protobuf encoding the SDK does on
``log`` (``.encode()``). Prints a Markdown table for docs/benchmarks.md.
Run: .venv/bin/python bench/bench_foxglove.py
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from machine import cpu_model

from endo_foxglove.convert import camera_calibration, point_cloud, raw_image
from endo_io.camera import CameraModel
from endo_io.image import array_to_image
from endo_io.pointcloud import xyz_to_pointcloud2


def time_ms(fn: Callable[[], Any], repeats: int) -> tuple[float, float]:
    for _ in range(3):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 90))


def main() -> None:
    rng = np.random.default_rng(0)
    organised = rng.normal(size=(480, 640, 3)).astype(np.float32)
    organised[rng.random((480, 640)) < 0.1] = np.nan
    cloud = xyz_to_pointcloud2(organised, 1, "world")
    colours = rng.integers(0, 256, (200_000, 3), dtype=np.uint8)
    cloud_map = xyz_to_pointcloud2(rng.normal(size=(200_000, 3)), 1, "world", rgb=colours)
    depth = array_to_image(rng.uniform(0.02, 0.1, (480, 640)).astype(np.float32), "32FC1", 1)
    rgb = array_to_image(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), "rgb8", 1)
    colour = array_to_image(rng.uniform(0, 1, (480, 640, 3)).astype(np.float32), "32FC3", 1)
    info = CameraModel.pinhole(640, 480, 500.0, 500.0, 319.5, 239.5).to_camera_info(1)
    cases: list[tuple[str, Callable[[], Any], int]] = [
        ("points 640x480 → 100 000", lambda: point_cloud(cloud, max_points=100_000).message, 50),
        ("points 640x480 → all finite", lambda: point_cloud(cloud, max_points=10**7).message, 50),
        ("map 200 000 rgb → 200 000",
         lambda: point_cloud(cloud_map, max_points=300_000).message, 50),
        ("depth 640x480 32FC1", lambda: raw_image(depth), 100),
        ("image 640x480 rgb8", lambda: raw_image(rgb), 100),
        ("irradiance 640x480 32FC3 → rgb8", lambda: raw_image(colour), 50),
        ("camera_info", lambda: camera_calibration(info), 500),
    ]
    load = os.getloadavg()[0]
    print(f"{time.strftime('%Y-%m-%d')}, {cpu_model()}, {os.cpu_count()} cores, "
          f"load average {load:.1f}")
    print("| message | convert median / p90 ms | convert + encode median / p90 ms |")
    print("|---|---|---|")
    for name, make, repeats in cases:
        convert = time_ms(make, repeats)
        both = time_ms(lambda make=make: make().encode(), repeats)
        print(f"| {name} | {convert[0]:.2f} / {convert[1]:.2f} | {both[0]:.2f} / {both[1]:.2f} |")


if __name__ == "__main__":
    main()
