"""What the bag side's safety checks cost: bounded decompression and the CDR check.

* Bounded decompression (``endo_io.bag.mcap_records``): a 1 MiB chunk of
  640x480 rgb8 image data decompressed in bounded steps, against the one-shot
  ``zstandard.decompress`` / ``lz4.frame.decompress`` the ``mcap`` package
  calls (which allocate the declared size up front).
* The CDR check that endo-replay and endo-record run on every message
  (``endo_io.bag.serde.cdr_check``, rclpy's deserialisation), against the
  size of the message, for a 640x480 rgb8 image, a 640x480 32FC1 depth image,
  a CameraInfo and a PoseStamped.

Times are the minimum over many repeats (the machine is shared; the minimum
is the least disturbed), in one run, so the ratios compare like with like.
Prints a table and replaces the section "## endo_io bag safety checks" of
docs/benchmarks.md. Run by hand: ``.venv/bin/python bench/bench_bag_checks.py``.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable

import lz4.frame
import numpy as np
import zstandard
from geometry_msgs.msg import PoseStamped
from machine import cpu_model
from mcap.records import Chunk
from results import BENCHMARKS, replace_section
from sensor_msgs.msg import CameraInfo, Image

from endo_io.bag import serialize
from endo_io.bag.mcap_records import decompress_chunk
from endo_io.bag.serde import cdr_check

REPEATS = 200
FRAME_PERIOD_MS = 1e3 / 30  # one frame at 30 Hz
SECTION = "## endo_io bag safety checks"


def best_ms(run: Callable[[], object], repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times) * 1e3


def image_bytes() -> bytes:
    """640x480 rgb8 of a smooth pattern with sensor noise (as bench_bag_read.py's frames)."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:480, 0:640].astype(np.float32)
    base = 128 + 60 * np.sin(x / 37.0) * np.cos(y / 23.0)
    rgb = np.stack([base, 0.8 * base + 20, 0.6 * base + 30], axis=-1)
    rgb += rng.normal(0, 3, size=rgb.shape).astype(np.float32)
    return np.clip(rgb, 0, 255).astype(np.uint8).tobytes()


def decompression_rows() -> list[str]:
    data = (image_bytes() * 2)[: 1 << 20]
    rows = []
    for name, compress, one_shot in (
        ("zstd", zstandard.compress, lambda z: zstandard.decompress(z, len(data))),
        ("lz4", lz4.frame.compress, lz4.frame.decompress),
    ):
        packed = compress(data)
        chunk = Chunk(
            compression=name,
            data=packed,
            message_start_time=0,
            message_end_time=0,
            uncompressed_crc=0,
            uncompressed_size=len(data),
        )
        assert decompress_chunk(chunk, 1 << 30) == data
        mcap_ms = best_ms(lambda packed=packed, one_shot=one_shot: one_shot(packed))
        ours_ms = best_ms(lambda chunk=chunk: decompress_chunk(chunk, 1 << 30))
        rows.append(
            f"| 1 MiB of rgb8, {name} ({len(packed) / 1e6:.2f} MB stored) | "
            f"{mcap_ms:.3f} | {ours_ms:.3f} | {ours_ms / mcap_ms:.2f} |"
        )
    return rows


def check_rows() -> list[str]:
    image = Image(height=480, width=640, encoding="rgb8", step=1920, data=image_bytes())
    depth = Image(height=480, width=640, encoding="32FC1", step=2560)
    depth.data = np.linspace(0.01, 0.2, 640 * 480, dtype=np.float32).tobytes()
    info = CameraInfo(height=480, width=640, distortion_model="plumb_bob")
    info.d = [0.1, -0.05, 0.0, 0.0, 0.0]
    pose = PoseStamped()
    pose.pose.orientation.w = 1.0
    rows = []
    for label, msg, msgtype in (
        ("Image 640x480 rgb8", image, "sensor_msgs/msg/Image"),
        ("Image 640x480 32FC1", depth, "sensor_msgs/msg/Image"),
        ("CameraInfo", info, "sensor_msgs/msg/CameraInfo"),
        ("PoseStamped", pose, "geometry_msgs/msg/PoseStamped"),
    ):
        data = serialize(msg)
        check = cdr_check(msgtype, "/bench")
        check_ms = best_ms(lambda check=check, data=data: check(data))
        copy_ms = best_ms(lambda data=data: bytearray(data))
        rows.append(
            f"| {label} | {len(data)} | {check_ms:.3f} | {copy_ms:.3f} | "
            f"{check_ms / FRAME_PERIOD_MS:.2%} |"
        )
    return rows


def main() -> None:
    load = os.getloadavg()[0]
    decompression = "\n".join(
        [
            "| chunk | mcap's one-shot ms | bounded ms | ratio |",
            "|---|---:|---:|---:|",
            *decompression_rows(),
        ]
    )
    checks = "\n".join(
        [
            "| message | bytes | CDR check ms | copying its bytes ms | of a 30 Hz frame period |",
            "|---|---:|---:|---:|---:|",
            *check_rows(),
        ]
    )
    table = f"{decompression}\n\n{checks}"
    section = (
        f"{SECTION}\n\n"
        f"`bench/bench_bag_checks.py`, {time.strftime('%Y-%m-%d')}, {cpu_model()}, 2 cores "
        f"shared (load average {load:.1f} at the start), Python {platform.python_version()}. "
        f"Minimum of {REPEATS} repeats. Decompression: the one-shot call the `mcap` package "
        "makes (it allocates the declared size) against `decompress_chunk` (bounded steps, "
        "output checked against the declared size). CDR check: `cdr_check` (rclpy's "
        "deserialisation, as endo-replay and endo-record run it on every message), with the "
        "time to copy the message's bytes once for scale.\n\n"
        f"{table}\n"
    )
    replace_section(section, SECTION)
    print(f"updated {BENCHMARKS}")


if __name__ == "__main__":
    main()
