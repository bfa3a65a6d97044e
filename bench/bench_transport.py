"""What one image hop costs over DDS, and what a 16-bit corrected image would lose.

    .venv/bin/python bench/bench_transport.py            # writes docs/benchmarks.md
    .venv/bin/python bench/bench_transport.py --no-write

1. **Hop cost.** A child process publishes 640×480 frames at 30 Hz through
   rclpy (``endo_io.image.array_to_image``, a reliable publisher, the
   large-frame shared-memory DDS profile, as in the graph); this process
   receives them (raw, then ``image_to_array``, as a node's guard does) on a
   sensor-data subscription. Per encoding: 32FC1 (the corrected image and the
   depth today, 1.2 MB), 16UC1 fixed point (0.6 MB, the candidate) and mono8
   (the camera's raw image, 0.3 MB). Latency = reception here, decoded,
   minus the DDS source timestamp of the publish; the publisher's own cost
   per frame (conversion + publish) and this side's decode, CPU ms.
2. **Accuracy of 16-bit fixed point.** The corrected image's encoding since
   2026-12-02 (:func:`endo_io.image.encode_irradiance`): ``u = round(x /
   scale)``, ``scale`` = 1e-4 irradiance units per count (65534 counts: 0 …
   6.55), 65535 reserved for NaN, values above the range clipped. Every ground-truth frame of the
   phantom (tuned on: none; the colon render seed 2 as the second scene when
   ``--second`` names it) is corrected with its true calibration, solved by
   ``endo_sfs.relative_depth.solve`` from the float image and from the
   encoded-decoded one, at solve_scale 1 and 0.5, and scored by median-scaled
   AbsRel against the truth (:func:`endo_sfs.evaluation.depth_error`).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from machine import cpu_model
from results import replace_section

from endo_io.image import (
    IRRADIANCE_MAX,
    IRRADIANCE_PER_COUNT,
    decode_irradiance,
    encode_irradiance,
)

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "bags" / "phantom_colon.mcap"
TITLE = "## Transport: one image hop, and the corrected image in 16 bits (bench_transport)"
TOPIC = "/bench_transport/image"
FRAMES = 150


def encode_fixed_point(x: np.ndarray) -> np.ndarray:
    """(H, W) float irradiance -> uint16 counts (the correction node's codec)."""
    return encode_irradiance(x, "16UC1").pixels


def decode_fixed_point(u: np.ndarray) -> np.ndarray:
    """uint16 counts -> float32 irradiance, NaN for the reserved count (the nodes' codec)."""
    return decode_irradiance(u, "16UC1")


def _frame(encoding: str, k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    irradiance = rng.random((480, 640), dtype=np.float32) * 3.0
    if encoding == "32FC1":
        return irradiance
    if encoding == "16UC1":
        return irradiance  # encoded in the publisher's timed step
    return (irradiance * 80).astype(np.uint8)


def publish(encoding: str, domain: str) -> None:
    """Child: publish FRAMES frames at 30 Hz; print its per-frame costs as JSON."""
    import rclpy

    from endo_io.image import array_to_image
    from endo_io.qos import create_reliable_publisher

    del domain
    rclpy.init()
    node = rclpy.create_node("bench_transport_publisher")
    from sensor_msgs.msg import Image

    publisher = create_reliable_publisher(node, Image, TOPIC)
    deadline = time.monotonic() + 30.0
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    frames = [_frame(encoding, k) for k in range(8)]
    costs = []
    start = time.monotonic()
    for k in range(FRAMES):
        time.sleep(max(0.0, start + k / 30.0 - time.monotonic()))
        t0 = time.thread_time()
        data = frames[k % len(frames)]
        if encoding == "16UC1":
            data = encode_fixed_point(data)
        publisher.publish(array_to_image(data, encoding, 1_000_000_000 + k * 33_333_333, "c"))
        costs.append((time.thread_time() - t0) * 1e3)
    time.sleep(0.5)
    print(json.dumps({"publish_cpu_ms": statistics.median(costs)}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


def hop(encoding: str, env: dict[str, str]) -> dict[str, float]:
    """One encoding through one hop; latency and costs (ms)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    from endo_io.image import image_to_array
    from endo_io.qos import SENSOR_DATA_QOS

    latencies: list[float] = []
    decode: list[float] = []
    lock = threading.Lock()

    def on_message(data: bytes, info: dict[str, Any]) -> None:
        t0 = time.thread_time()
        array = image_to_array(deserialize_message(data, Image))
        if encoding == "16UC1":
            array = decode_fixed_point(array)
        cost = (time.thread_time() - t0) * 1e3
        with lock:
            latencies.append((time.time_ns() - int(info["source_timestamp"])) / 1e6)
            decode.append(cost)

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_transport_subscriber", context=context)
    node.create_subscription(Image, TOPIC, on_message, SENSOR_DATA_QOS, raw=True)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    child = subprocess.Popen(
        [sys.executable, __file__, "--publish", encoding], env=env,
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    while child.poll() is None:
        executor.spin_once(timeout_sec=0.05)
    out = child.stdout.read() if child.stdout else ""
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)
    publisher = json.loads(out.strip().splitlines()[-1])
    ordered = sorted(latencies)
    return {
        "received": float(len(latencies)),
        "p50": statistics.median(ordered),
        "p95": ordered[int(0.95 * (len(ordered) - 1))],
        "publish_cpu_ms": publisher["publish_cpu_ms"],
        "decode_cpu_ms": statistics.median(decode),
    }


def accuracy(bags: list[Path]) -> list[tuple[str, float, float, float, int]]:
    """(bag, solve_scale, AbsRel float, AbsRel 16-bit, frames) over each bag's truth frames."""
    from endo_calib.calibration import ChannelCalibration, PhotometricCalibration
    from endo_calib.raw_image import to_raw_frame
    from endo_calib.response import InverseResponse
    from endo_io.bag import BagReader, deserialize
    from endo_io.camera import CameraModel
    from endo_io.image import image_to_array
    from endo_io.stamp import stamp_to_ns
    from endo_sfs.evaluation import depth_error
    from endo_sfs.options import SfsOptions
    from endo_sfs.relative_depth import solve
    from endo_sim.ground_truth import ground_truth_of

    rows = []
    for bag in bags:
        source = bag if bag.with_suffix(".light_map.npy").exists() else PHANTOM
        lut = np.load(source.with_suffix(".inverse_response.npy"))
        light = np.load(source.with_suffix(".light_map.npy"))
        fov = light > 0
        channel = ChannelCalibration("mono", InverseResponse(lut, 8),
                                     np.where(fov, light, 0.0), None)
        calibration = PhotometricCalibration([channel], fov, None, "pixels")
        truth = ground_truth_of(bag)
        radius = float(truth["camera"]["fov_radius_px"])  # type: ignore[index]
        roughness = float(truth["photometry"]["roughness_rad"])  # type: ignore[index]
        topics = ("/endoscope/image_raw", "/endoscope/camera_info", "/ground_truth/depth")
        by: dict[str, dict[int, Any]] = {t: {} for t in topics}
        with BagReader(bag) as reader:
            for message in reader.messages(list(topics)):
                msg = deserialize(message)
                by[message.topic][stamp_to_ns(msg.header.stamp)] = msg
        stamps = sorted(set(by[topics[0]]) & set(by[topics[1]]) & set(by[topics[2]]))[:6]
        for scale in (1.0, 0.5):
            options = SfsOptions(roughness=roughness, mask_highlights=True, solve_scale=scale)
            errors: dict[str, list[float]] = {"float": [], "16bit": []}
            for s in stamps:
                image = by[topics[0]][s]
                camera = CameraModel.from_camera_info(by[topics[1]][s])
                irradiance = calibration.luminance(
                    calibration.correct(to_raw_frame(image_to_array(image), image.encoding)))
                depth_true = image_to_array(by[topics[2]][s])
                mask = camera.fov_mask(radius)
                for name, x in (("float", irradiance),
                                ("16bit", decode_fixed_point(encode_fixed_point(irradiance)))):
                    depth = solve(x, camera, options, mask=mask).depth
                    errors[name].append(depth_error(depth, depth_true, scaling="median").abs_rel)
            rows.append((bag.stem, scale, float(np.mean(errors["float"])),
                         float(np.mean(errors["16bit"])), len(stamps)))
            finite = irradiance[np.isfinite(irradiance)]
            print(f"{bag.stem} scale {scale:g}: AbsRel float {rows[-1][2]:.5f}, 16-bit "
                  f"{rows[-1][3]:.5f}; irradiance max {finite.max():.3f}, "
                  f"clipped {(finite > IRRADIANCE_MAX).mean():.2%}",
                  flush=True)
    return rows


def main() -> int:
    """Measure both parts; print; write the section unless --no-write."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--publish", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--second", type=Path, default=None, help="a second rendered bag")
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--accuracy-only", action="store_true",
                        help="only the accuracy part, printed (no DDS, nothing written)")
    args = parser.parse_args()
    if args.publish:
        publish(args.publish, os.environ.get("ROS_DOMAIN_ID", ""))
        return 0
    if args.accuracy_only:
        for bag, scale, a, b, n in accuracy([PHANTOM] + ([args.second] if args.second else [])):
            print(f"| {bag} | {scale:g} | {n} | {a:.5f} | {b:.5f} | {b - a:+.5f} |")
        return 0
    from endo_bringup.dds_profile import with_large_frame_profile

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", "43")
    env, _ = with_large_frame_profile(env, Path(tempfile.mkdtemp(prefix="endo3d_transport_")))
    os.environ.update(env)
    hops = []
    for run in range(1, args.runs + 1):
        for encoding in ("32FC1", "16UC1", "mono8"):
            load = os.getloadavg()[0]
            figures = hop(encoding, env)
            print(run, encoding, f"load {load:.1f}", figures, flush=True)
            hops.append((run, encoding, load, figures))
    rows = accuracy([PHANTOM] + ([args.second] if args.second else []))
    lines = [
        TITLE, "",
        f"`bench/bench_transport.py`, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {cpu_model()}, "
        f"{os.cpu_count()} cores. **Shared machine: load average "
        f"{min(h[2] for h in hops):.1f}–{max(h[2] for h in hops):.1f} on {os.cpu_count()} "
        "cores**; compare encodings inside one pass. One hop: a publisher process → this "
        f"process, {FRAMES} frames of 640×480 at 30 Hz, the graph's DDS settings.", "",
        "| pass | encoding | bytes | load | received | latency p50 / p95 ms | publisher CPU ms "
        "(convert + publish) | subscriber CPU ms (deserialize + decode) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    size = {"32FC1": "1.23 MB", "16UC1": "0.61 MB", "mono8": "0.31 MB"}
    for run, encoding, load, f in hops:
        lines.append(f"| {run} | {encoding} | {size[encoding]} | {load:.1f} | "
                     f"{f['received']:.0f}/{FRAMES} | {f['p50']:.1f} / {f['p95']:.1f} | "
                     f"{f['publish_cpu_ms']:.2f} | {f['decode_cpu_ms']:.2f} |")
    lines += ["", f"16-bit fixed point of the corrected image ({IRRADIANCE_PER_COUNT:g} per count, "
              "65535 = NaN): SFS median-scaled AbsRel against the truth, mean over the "
              "ground-truth frames:", "",
              "| bag | solve_scale | frames | AbsRel float | AbsRel 16-bit | difference |",
              "|---|---|---|---|---|---|"]
    for bag, scale, a, b, n in rows:
        lines.append(f"| {bag} | {scale:g} | {n} | {a:.5f} | {b:.5f} | {b - a:+.5f} |")
    section = "\n".join(lines) + "\n"
    print(section)
    if not args.no_write:
        replace_section(section, TITLE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
