"""Throughput of endo-replay and endo-record on a 640x480 rgb8 image bag, next to raw mcap reading.

Writes a bag of 300 frames (30 Hz, 10 s of bag time), then measures:

1. raw ``mcap`` reading of the file (the physical limit here), and BagReader;
2. ``endo-replay`` with ``endo-record`` listening, as separate processes over
   loopback DDS, at ``--rate 2`` (60 fps, the issue's target), ``--rate 4``
   (120 fps) and ``--rate inf`` (as fast as possible): frames/s and MB/s
   published, achieved rate, and how many frames the recorder got and wrote
   (frames/s and MB/s over its receive span).

Run by hand (``make bench``); prints a Markdown table to paste into
docs/benchmarks.md. Uses the environment's ROS_DOMAIN_ID, loopback discovery.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from sensor_msgs.msg import Image

from endo_io.bag import BagReader, BagWriter, serialize
from endo_io.errors import BagError
from endo_io.stamp import ns_to_stamp

BIN = Path(sys.executable).parent
TOPIC = "/endoscope/image_raw"
WIDTH, HEIGHT, FRAMES, FPS = 640, 480, 300, 30
T0 = 1_763_800_000_000_000_000


def write_bag(path: Path) -> int:
    """300 frames of a moving vignetted gradient with sensor noise; returns payload bytes."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    r2 = ((x - WIDTH / 2) ** 2 + (y - HEIGHT / 2) ** 2) / (WIDTH / 2) ** 2
    vignette = np.clip(1.0 - 0.8 * r2, 0.0, 1.0)
    total = 0
    with BagWriter(path) as writer:
        writer.add_topic(TOPIC, "sensor_msgs/msg/Image")
        for i in range(FRAMES):
            base = 0.5 + 0.5 * np.sin((x + 4 * i) / 40.0)[..., None] * np.array([1.0, 0.6, 0.5])
            noise = rng.normal(0.0, 0.03, (HEIGHT, WIDTH, 3))
            pixels = np.clip((base * vignette[..., None] + noise) * 255, 0, 255).astype(np.uint8)
            t = T0 + round(i * 1e9 / FPS)
            msg = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", step=WIDTH * 3)
            msg.header.stamp, msg.header.frame_id = ns_to_stamp(t), "endoscope_optical_frame"
            msg.data = pixels.tobytes()
            data = serialize(msg)
            writer.write(TOPIC, data, t)
            total += len(data)
    return total


def raw_mcap_read(path: Path) -> tuple[float, int]:
    start = time.perf_counter()
    n_bytes = 0
    with path.open("rb") as f:
        for _, _, message in make_reader(f).iter_messages():
            n_bytes += len(message.data)
    return time.perf_counter() - start, n_bytes


def bag_reader_read(path: Path) -> tuple[float, int]:
    start = time.perf_counter()
    n_bytes = 0
    with BagReader(path) as reader:
        for message in reader.messages():
            n_bytes += len(message.data)
    return time.perf_counter() - start, n_bytes


def recorded(path: Path) -> tuple[int, int, float]:
    """(frames, bytes, receive span in s) of a finished recording."""
    with BagReader(path) as reader:
        times, n_bytes = [], 0
        for message in reader.messages():
            times.append(message.log_time_ns)
            n_bytes += len(message.data)
    span = (times[-1] - times[0]) / 1e9 if len(times) > 1 else float("nan")
    return len(times), n_bytes, span


def replay_with_recorder(bag: Path, out: Path, rate: str, env: dict[str, str]) -> dict[str, float]:
    recorder = subprocess.Popen(
        [BIN / "endo-record", "--topics", TOPIC, "-o", out, "--flush-period", "0.5"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        replay = subprocess.run(
            [BIN / "endo-replay", bag, "--rate", rate, "--wait-for-subscribers", "1"],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        )
        # Let the recorder drain what DDS has delivered, then finalise it.
        deadline = time.monotonic() + 10
        last = -1
        while time.monotonic() < deadline:
            time.sleep(0.5)
            try:
                with BagReader(out) as reader:
                    count = sum(1 for _ in reader.messages())
            except BagError:  # still being written: count what is intact
                count = last
            if count == last or count >= FRAMES:
                break
            last = count
        recorder.send_signal(signal.SIGINT)
        recorder.wait(20)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    line = next(x for x in replay.stdout.splitlines() if "total:" in x)
    match = re.search(
        r"in ([\d.]+) s \(([\d.]+) msg/s, ([\d.]+) MB/s\).*achieved rate ([\d.]+)x", line
    )
    assert match, line
    wall, msg_s, mb_s, achieved = map(float, match.groups())
    frames, n_bytes, span = recorded(out)
    return {
        "replay_s": wall,
        "replay_fps": msg_s,
        "replay_mb_s": mb_s,
        "achieved_rate": achieved,
        "recorded": frames,
        "record_mb_s": n_bytes / 1e6 / span,
        "record_fps": (frames - 1) / span,
    }


def main() -> int:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", "43")
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "images.mcap"
        payload = write_bag(bag)
        size_mb = bag.stat().st_size / 1e6
        print(
            f"bag: {FRAMES} frames {WIDTH}x{HEIGHT} rgb8, {payload / 1e6:.1f} MB payload, "
            f"{size_mb:.1f} MB on disk (zstd); domain {env['ROS_DOMAIN_ID']}"
        )
        raw = min(raw_mcap_read(bag)[0] for _ in range(3))
        ours = min(bag_reader_read(bag)[0] for _ in range(3))
        runs = {
            rate: replay_with_recorder(bag, Path(tmp) / f"rate_{rate}.mcap", rate, env)
            for rate in ("2", "4", "inf")
        }
    rows = [
        ("raw mcap read (make_reader.iter_messages)", FRAMES / raw, payload / 1e6 / raw, ""),
        ("BagReader.messages", FRAMES / ours, payload / 1e6 / ours, ""),
    ]
    for rate, run in runs.items():
        fps = "as fast as possible" if rate == "inf" else f"{FPS * float(rate):g} fps"
        rows.append(
            (
                f"endo-replay --rate {rate} ({fps}), recorder listening",
                run["replay_fps"],
                run["replay_mb_s"],
                f"achieved {run['achieved_rate']:.3f}x",
            )
        )
        rows.append(
            (
                f"endo-record during --rate {rate}",
                run["record_fps"],
                run["record_mb_s"],
                f"recorded {run['recorded']}/{FRAMES} frames",
            )
        )
    print("| what | frames/s | MB/s | notes |")
    print("|---|---:|---:|---|")
    for what, fps, mb_s, notes in rows:
        print(f"| {what} | {fps:.1f} | {mb_s:.1f} | {notes} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
