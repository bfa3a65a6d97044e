"""What the bag side's safety checks cost: bounded decompression and the CDR check.

* Bounded decompression (``endo_io.bag.mcap_records``): a 1 MiB chunk of
  640x480 rgb8 image data decompressed in bounded steps, against the one-shot
  ``zstandard.decompress`` / ``lz4.frame.decompress`` the ``mcap`` package
  calls (which allocate the declared size up front).
* The CDR check that endo-replay and endo-record run on every message
  (``endo_io.bag.serde.cdr_check``: images by ``endo_io.image.image_from_cdr``,
  other types by rclpy's deserialisation), against the size of the message
  and against rclpy's deserialisation of the same bytes, for a 640x480 rgb8
  image, a 640x480 32FC1 depth image, a CameraInfo and a PoseStamped.
* The same two image checks on fresh messages: each of ``FRESH`` distinct
  copies of a 32FC1 image checked once (mean and median), as a recorder meets
  them, against the warm minimum over repeats of one message.
* ``endo_io.camera.CameraInfoCache``: building the model of a 640x480
  plumb_bob CameraInfo (``CameraModel.from_camera_info``), and with its ray
  table (the first ``unit_rays``, which a new model rebuilds), against the
  cache's answer for the same camera restamped.

Times are the minimum over many repeats (the machine is shared; the minimum
is the least disturbed), in one run, so the ratios compare like with like.
Prints a table and replaces the section "## endo_io bag safety checks" of
docs/benchmarks.md. Run by hand: ``.venv/bin/python bench/bench_bag_checks.py``.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable

import lz4.frame
import numpy as np
import zstandard
from geometry_msgs.msg import PoseStamped
from machine import cpu_model
from mcap.records import Chunk
from rclpy.serialization import deserialize_message
from results import BENCHMARKS, replace_section
from sensor_msgs.msg import CameraInfo, Image

from endo_io.bag import message_class, serialize
from endo_io.bag.mcap_records import decompress_chunk
from endo_io.bag.serde import cdr_check
from endo_io.camera import CameraInfoCache, CameraModel
from endo_io.image import image_from_cdr

REPEATS = 200
#: Distinct messages of the fresh-message rows.
FRESH = 50
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
        cls = message_class(msgtype)
        check_ms = best_ms(lambda check=check, data=data: check(data))
        rclpy_ms = best_ms(lambda data=data, cls=cls: deserialize_message(data, cls))
        copy_ms = best_ms(lambda data=data: bytearray(data))
        rows.append(
            f"| {label} | {len(data)} | {check_ms:.3f} | {rclpy_ms:.3f} | {copy_ms:.3f} | "
            f"{check_ms / FRAME_PERIOD_MS:.2%} |"
        )
    return rows


def depth_image_bytes() -> bytes:
    depth = Image(height=480, width=640, encoding="32FC1", step=2560)
    depth.data = np.linspace(0.01, 0.2, 640 * 480, dtype=np.float32).tobytes()
    return serialize(depth)


def fresh_rows() -> list[str]:
    """Each of FRESH distinct copies of a 32FC1 image checked once, both ways."""
    data = depth_image_bytes()
    rows = []
    for label, run in (
        ("image_from_cdr (cdr_check)", image_from_cdr),
        ("rclpy deserialize_message", lambda b: deserialize_message(b, Image)),
    ):
        copies = [bytes(bytearray(data)) for _ in range(FRESH)]
        times = []
        for copy in copies:
            start = time.perf_counter()
            run(copy)
            times.append((time.perf_counter() - start) * 1e3)
        warm = best_ms(lambda run=run: run(data))
        rows.append(f"| {label} | {statistics.mean(times):.3f} | "
                    f"{statistics.median(times):.3f} | {warm:.3f} |")
    return rows


def camera_rows() -> list[str]:
    model = CameraModel.pinhole(640, 480, 520.0, 521.0, 319.5, 239.5)
    info = model.to_camera_info(1_000_000_000)
    info.distortion_model, info.d = "plumb_bob", [0.1, -0.05, 0.001, 0.0, 0.0]
    restamped = model.to_camera_info(2_000_000_000)
    restamped.distortion_model, restamped.d = info.distortion_model, info.d
    cache = CameraInfoCache()
    cache.model_of(info)
    build_ms = best_ms(lambda: CameraModel.from_camera_info(info))
    rays_ms = best_ms(lambda: CameraModel.from_camera_info(info).unit_rays(), repeats=20)
    hit_ms = best_ms(lambda: cache.model_of(restamped))
    assert cache.model_of(restamped)[0] is cache.model
    return [f"| 640x480 plumb_bob | {build_ms:.3f} | {rays_ms:.2f} | {hit_ms:.3f} |"]


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
            "| message | bytes | CDR check ms | rclpy's deserialisation ms | copying its bytes ms "
            "| check of a 30 Hz frame period |",
            "|---|---:|---:|---:|---:|---:|",
            *check_rows(),
        ]
    )
    fresh = "\n".join(
        [
            f"| 640x480 32FC1, {FRESH} fresh messages | mean ms | median ms | warm minimum ms |",
            "|---|---:|---:|---:|",
            *fresh_rows(),
        ]
    )
    cameras = "\n".join(
        [
            "| CameraInfo | from_camera_info ms | and its ray table (first unit_rays) ms "
            "| CameraInfoCache, same camera ms |",
            "|---|---:|---:|---:|",
            *camera_rows(),
        ]
    )
    table = f"{decompression}\n\n{checks}\n\n{fresh}\n\n{cameras}"
    section = (
        f"{SECTION}\n\n"
        f"`bench/bench_bag_checks.py`, {time.strftime('%Y-%m-%d')}, {cpu_model()}, 2 cores "
        f"shared (load average {load:.1f} at the start), Python {platform.python_version()}. "
        f"Minimum of {REPEATS} repeats. Decompression: the one-shot call the `mcap` package "
        "makes (it allocates the declared size) against `decompress_chunk` (bounded steps, "
        "output checked against the declared size). CDR check: `cdr_check`, as endo-replay "
        "and endo-record run it on every message (images: `image_from_cdr`, every field and "
        "length, the pixels not copied; other types: rclpy's deserialisation), beside rclpy's "
        "deserialisation of the same bytes and the time to copy them once. Fresh messages: "
        f"{FRESH} distinct copies of one 32FC1 image, each checked once (what a recorder "
        "meets: bytes not in the cache, rclpy's 1.2 MB array allocated anew), against the "
        "warm minimum over repeats of one message. CameraInfoCache: the model built from a "
        "CameraInfo, alone and with its ray table (a new model rebuilds it at its first "
        "use; minimum of 20), against the cache's answer for the same camera restamped "
        "(what the flow and sfs nodes pay per frame).\n\n"
        f"{table}\n"
    )
    replace_section(section, SECTION)
    print(f"updated {BENCHMARKS}")


if __name__ == "__main__":
    main()
