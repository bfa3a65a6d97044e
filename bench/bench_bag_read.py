"""Bag reading and writing throughput: endo_io.bag vs the raw ``mcap`` reader.

Builds a 200-frame 640x480 rgb8 image bag (smooth moving texture plus sensor
noise, so that compression has realistic work) in a temporary directory for
each chunk compression, then measures, best of three runs:

* raw ``mcap`` reading: ``make_reader(f).iter_messages()`` (log-time order,
  no decoding), the physical limit of reading this file in Python;
* ``BagReader.messages()`` (raw CDR BagMessages, CRC validation on, default);
* ``BagWriter.write()`` of the same CDR payloads.

MB/s counts message payload bytes (1e6 bytes per MB). Prints a table and
appends it to docs/benchmarks.md under "## endo_io bag reading and writing".
Run by hand: ``.venv/bin/python bench/bench_bag_read.py``.
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import cpu_model
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from results import BENCHMARKS, replace_section
from sensor_msgs.msg import Image

from endo_io.bag import BagReader, BagWriter

FRAMES = 200
HEIGHT, WIDTH = 480, 640
REPEATS = 3
SECTION = "## endo_io bag reading and writing"


def make_payloads() -> list[bytes]:
    """CDR of FRAMES rgb8 images: a drifting smooth pattern plus noise (sigma 3 DN)."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    payloads = []
    for i in range(FRAMES):
        phase = 0.05 * i
        base = 128 + 60 * np.sin(x / 37.0 + phase) * np.cos(y / 23.0 - phase)
        rgb = np.stack([base, 0.8 * base + 20, 0.6 * base + 30], axis=-1)
        rgb += rng.normal(0, 3, size=rgb.shape).astype(np.float32)
        pixels = np.clip(rgb, 0, 255).astype(np.uint8)
        msg = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", step=3 * WIDTH)
        msg.header.stamp.sec = i
        msg.header.frame_id = "endoscope_optical_frame"
        msg.data = pixels.tobytes()
        payloads.append(serialize_message(msg))
    return payloads


def best_time(run) -> float:
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def write_bag(path: Path, payloads: list[bytes], compression: str) -> None:
    with BagWriter(path, compression=compression) as writer:
        writer.add_topic("/endoscope/image_raw", "sensor_msgs/msg/Image")
        for i, payload in enumerate(payloads):
            writer.write("/endoscope/image_raw", payload, 1_000_000_000 + i * 33_333_333)


def read_raw_mcap(path: Path) -> int:
    total = 0
    with path.open("rb") as stream:
        for _, _, message in make_reader(stream).iter_messages():
            total += len(message.data)
    return total


def read_ours(path: Path, validate_crcs: bool = True) -> int:
    total = 0
    with BagReader(path, validate_crcs=validate_crcs) as reader:
        for message in reader.messages():
            total += len(message.data)
    return total


def machine() -> str:
    return f"{cpu_model()}, 2 cores shared"


def main() -> None:
    payloads = make_payloads()
    payload_mb = sum(len(p) for p in payloads) / 1e6
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for compression in ("zstd", "lz4", "none"):
            write_times = []
            for repeat in range(REPEATS):
                target = Path(tmp) / f"w_{compression}_{repeat}.mcap"
                start = time.perf_counter()
                write_bag(target, payloads, compression)
                write_times.append(time.perf_counter() - start)
                target.unlink()
            write_s = min(write_times)
            path = Path(tmp) / f"bag_{compression}.mcap"
            write_bag(path, payloads, compression)
            assert read_raw_mcap(path) == read_ours(path) == round(payload_mb * 1e6)
            raw_s = best_time(lambda path=path: read_raw_mcap(path))
            ours_s = best_time(lambda path=path: read_ours(path))
            ours_nocrc_s = best_time(lambda path=path: read_ours(path, validate_crcs=False))
            rows.append(
                (
                    compression,
                    path.stat().st_size / 1e6,
                    payload_mb / raw_s,
                    payload_mb / ours_s,
                    payload_mb / ours_nocrc_s,
                    payload_mb / write_s,
                    FRAMES / ours_s,
                )
            )
    header = (
        "| chunks | file MB | raw mcap read MB/s | BagReader MB/s, CRC on (default) | ratio | "
        "BagReader MB/s, CRC off | ratio | BagWriter MB/s | BagReader frames/s |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    lines = [
        f"| {c} | {size:.1f} | {raw:.0f} | {ours:.0f} | {ours / raw:.0%} | {nocrc:.0f} | "
        f"{nocrc / raw:.0%} | {write:.0f} | {fps:.0f} |"
        for c, size, raw, ours, nocrc, write, fps in rows
    ]
    table = "\n".join([header, *lines])
    print(table)
    section = (
        f"{SECTION}\n\n"
        f"`bench/bench_bag_read.py`, {time.strftime('%Y-%m-%d')}, {machine()}, "
        f"load average {os.getloadavg()[0]:.1f} at the end, Python {platform.python_version()}.\n"
        f"{FRAMES} frames of {WIDTH}x{HEIGHT} rgb8 (sensor_msgs/Image CDR, "
        f"{payload_mb:.0f} MB of payload), 1 MiB chunks, best of {REPEATS}. "
        "MB/s = payload bytes / wall time; raw mcap = `make_reader(f).iter_messages()` "
        "(log-time order, no decoding).\n\n"
        f"{table}\n"
    )
    replace_section(section, SECTION)
    print(f"updated {BENCHMARKS}")


if __name__ == "__main__":
    main()
