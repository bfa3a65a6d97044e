"""Benchmark: endo-foxglove's conversions per message (endo_foxglove.convert).

Times what the bridge's sending thread does for one message before handing
it to foxglove-sdk: a 640x480 organised world cloud (10 % NaN) to a
decimated packed PointCloud (100 000 points, the default, and all 276 480
finite points), a 200 000-point rgb map, a 640x480 32FC1 depth image, a
640x480 rgb8 image, a 32FC3 colour irradiance frame (scaled to rgb8) and a
CameraInfo; each once more with the protobuf encoding the SDK does on
``log`` (``.encode()``); the table twice, and the finite-point selection
against numpy's row reduction. Writes its section of docs/benchmarks.md.
Run: .venv/bin/python bench/bench_foxglove.py
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from importlib.metadata import version
from typing import Any

import numpy as np
from machine import cpu_model
from results import BENCHMARKS, replace_section

from endo_foxglove.convert import camera_calibration, point_cloud, raw_image
from endo_io.camera import CameraModel
from endo_io.image import array_to_image
from endo_io.pointcloud import xyz_to_pointcloud2

SECTION = "## endo_foxglove conversions"


def time_ms(fn: Callable[[], Any], repeats: int) -> tuple[float, float]:
    for _ in range(3):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(samples)), float(np.percentile(samples, 90))


def finite_rows_by_reduction(points: np.ndarray) -> np.ndarray:
    """The obvious way (numpy's row reduction), kept here to measure against."""
    return np.flatnonzero(np.isfinite(points).all(axis=1))


def finite_rows_by_columns(points: np.ndarray) -> np.ndarray:
    """What pack_points does: x + y + z column by column, non-finite if any is."""
    total = points[:, 0] + points[:, 1]
    total += points[:, 2]
    return np.flatnonzero(np.isfinite(total))


def one_run(cases: list[tuple[str, Callable[[], Any], int]]) -> list[tuple[str, float, float]]:
    rows = []
    for name, make, repeats in cases:
        convert = time_ms(make, repeats)
        both = time_ms(lambda make=make: make().encode(), repeats)
        rows.append((name, convert[0], both[0]))
    return rows


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
        ("points 640x480 (10 % NaN) → 100 000",
         lambda: point_cloud(cloud, max_points=100_000).message, 50),
        ("points 640x480 → all 276 480 finite",
         lambda: point_cloud(cloud, max_points=10**7).message, 50),
        ("map 200 000 with rgb → 200 000",
         lambda: point_cloud(cloud_map, max_points=300_000).message, 30),
        ("depth 640x480 32FC1", lambda: raw_image(depth), 100),
        ("image 640x480 rgb8", lambda: raw_image(rgb), 100),
        ("irradiance 640x480 32FC3 → rgb8", lambda: raw_image(colour), 50),
        ("camera_info", lambda: camera_calibration(info), 500),
    ]
    runs = [one_run(cases) for _ in range(2)]
    flat = organised.reshape(-1, 3)
    ratios = []
    for _ in range(2):
        reduction = time_ms(lambda: finite_rows_by_reduction(flat), 30)[0]
        columns = time_ms(lambda: finite_rows_by_columns(flat), 30)[0]
        ratios.append((reduction, columns))
    header = (
        "| message | convert, run 1 / run 2 (ms) | convert + encode, run 1 / run 2 (ms) |\n"
        "|---|---|---|"
    )
    lines = [
        f"| {a[0]} | {a[1]:.2f} / {b[1]:.2f} | {a[2]:.2f} / {b[2]:.2f} |"
        for a, b in zip(runs[0], runs[1], strict=True)
    ]
    table = "\n".join([header, *lines])
    finite = "; ".join(f"{r:.2f} ms vs {c:.2f} ms ({r / c:.0f}x)" for r, c in ratios)
    section = (
        f"{SECTION}\n\n"
        f"`bench/bench_foxglove.py`, {time.strftime('%Y-%m-%d')}, {cpu_model()}, "
        f"{os.cpu_count()} cores shared with other work (load average "
        f"{os.getloadavg()[0]:.1f} at the end), Python {platform.python_version()}, "
        f"numpy {np.__version__}, foxglove-sdk {version('foxglove-sdk')}.\n"
        "What endo-foxglove's sending thread does per message before the SDK takes it "
        "(`endo_foxglove.convert`, from the ROS message to the Foxglove message, and with "
        "the protobuf encoding the SDK does on `log`); medians, the whole table run twice.\n\n"
        f"{table}\n\n"
        "- Finite-point selection of the 307 200-point cloud, numpy's row reduction "
        "(`isfinite(p).all(axis=1)`) vs the column adds `pack_points` uses, twice: "
        f"{finite}.\n"
        "- Clouds with rgb cost most in `endo_io.pointcloud.pointcloud2_to_xyz` (unpacking "
        "the colour); the map is throttled to 1 Hz by default.\n"
    )
    print(section)
    replace_section(section, SECTION)
    print(f"updated {BENCHMARKS}")


if __name__ == "__main__":
    main()
