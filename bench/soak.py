"""Soak: the whole live graph on a looping replay; memory, output rate and latency over time.

    .venv/bin/python bench/soak.py                 # 10 minutes, writes docs/benchmarks.md
    .venv/bin/python bench/soak.py --minutes 1 --no-write

Every node is its own OS process, as a user runs them:
``endo-photometric-correction`` → ``endo-sfs`` → ``endo-flow``, and
``endo-tracker-bridge`` → ``endo-flow``, fed by ``endo-replay --loop`` of the
phantom bag (the simulator's true calibration, hand–eye and registration
from its ground truth, so no fitting step runs first). Each ``--interval``
seconds the script samples

* every process's resident memory (``VmRSS`` of ``/proc/<pid>/status``);
* the output rate of each stage as this process receives it:
  ``/endoscope/depth_relative`` (sfs), ``/endoscope/scale`` (flow, one per
  frame) and ``/endoscope/pose`` (bridge);
* latency, per output message: its arrival here minus the arrival here of
  the input with the same stamp (``/endoscope/image_raw`` for depth and
  scale: correction + SFS, and the whole graph; ``/tracker/pose`` for the
  camera pose, whose stamp is the tracker's minus the hand–eye time
  offset). The stamps repeat on every pass; each output is matched with the
  latest input of its stamp. Only header stamps are read (raw subscriptions,
  the stamp parsed from the CDR bytes), so listening costs next to nothing;
* the nodes' ``/diagnostics`` (dropped, lost in transport, clock jumps).

Targets (issue 16): RSS growth ≤ 5 % after the first minute, no drift of
rate or latency (the first full minute after warm-up against the last), and
nothing stuck after any loop (every interval has output of every stage).
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from machine import cpu_model
from rclpy.executors import SingleThreadedExecutor
from results import BENCHMARKS, replace_section
from sensor_msgs.msg import Image

from endo_bringup.dds_profile import with_large_frame_profile
from endo_calib.calibration import ChannelCalibration, PhotometricCalibration
from endo_calib.response import InverseResponse
from endo_io import topics
from endo_io.qos import SENSOR_DATA_QOS
from endo_process.simulated import write_simulated_parameters
from endo_sim.ground_truth import ground_truth_of
from endo_tracker_bridge.handeye_file import HandEyeCalibration

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "bags" / "phantom_colon.mcap"
BIN = Path(sys.executable).parent
TITLE = "## Soak: the live graph on a looping replay"
RUN_HEADING = "### Run of "
INTRO = (
    "`bench/soak.py` (issue 16): the phantom bag (640×480, 30 fps, 3 s) looped by "
    "`endo-replay --loop` into the four nodes, each its own process (true calibration, "
    "hand–eye and registration from the bag's ground truth; the large-frame shared-memory "
    "DDS profile). Every `--interval` seconds: each process's RSS, each stage's output rate "
    "as a listener receives it, and latency = arrival of the output at the listener minus "
    "arrival there of the input with the same stamp (depth: correction + SFS; scale: the "
    "whole graph; pose: the bridge). Targets: RSS growth ≤ 5 % after the first minute, no "
    "rate or latency drift (minute 2 against the last minute), nothing stuck after any loop "
    "(every interval after the first minute has output of every stage). Newest run first; "
    "each run keeps the one before it (`--keep`)."
)
NODES = ("correction", "sfs", "bridge", "flow")
#: Output topic -> (input topic it is matched with, the stream's name in the tables).
OUTPUTS = {
    topics.DEPTH_RELATIVE: (topics.IMAGE_RAW, "depth"),
    topics.SCALE: (topics.IMAGE_RAW, "scale"),
    topics.CAMERA_POSE: (topics.TRACKER_POSE, "pose"),
}


def _stamp_of(data: bytes) -> int:
    """Header stamp (integer ns) of a serialized message that starts with a Header."""
    sec, nanosec = struct.unpack_from("<iI", data, 4)  # after the 4-byte CDR encapsulation
    return sec * 1_000_000_000 + nanosec


def _rss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


@dataclass
class Listener:
    """Arrival times of inputs and outputs, by stamp; the nodes' diagnostics."""

    offset_ns: int
    lock: threading.Lock = field(default_factory=threading.Lock)
    arrivals: dict[str, dict[int, float]] = field(default_factory=lambda: defaultdict(dict))
    latencies: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    status: dict[str, dict[str, str]] = field(default_factory=dict)

    def on_input(self, topic: str, data: bytes) -> None:
        with self.lock:
            stamps = self.arrivals[topic]
            stamps[_stamp_of(data)] = time.monotonic()
            if len(stamps) > 4000:  # bounded: a few passes of the bag
                for old in list(stamps)[:2000]:
                    del stamps[old]

    def on_output(self, topic: str, data: bytes) -> None:
        now = time.monotonic()
        source, name = OUTPUTS[topic]
        stamp = _stamp_of(data) + (self.offset_ns if topic == topics.CAMERA_POSE else 0)
        with self.lock:
            self.counts[name] += 1
            sent = self.arrivals[source].get(stamp)
            if sent is not None and now >= sent:
                self.latencies[name].append(now - sent)

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.status[status.name] = {kv.key: kv.value for kv in status.values}

    def take(self) -> tuple[dict[str, int], dict[str, list[float]]]:
        with self.lock:
            counts, latencies = dict(self.counts), {k: list(v) for k, v in self.latencies.items()}
            self.counts.clear()
            self.latencies.clear()
        return counts, latencies


@dataclass
class Sample:
    """One interval: elapsed s, load average, RSS (MB) per process, rate (1/s) and latency."""

    t_s: float
    load: float
    rss_mb: dict[str, float]
    rate: dict[str, float]
    latency_ms: dict[str, tuple[float, float]]  # (median, p95)


def _setup(out: Path, solve_scale: float, bag: Path = BAG) -> tuple[Path, Path, Path]:
    """The true photometric.yaml, handeye.yaml and parameter file of ``bag`` (the phantom)."""
    lut = np.load(bag.with_suffix(".inverse_response.npy"))
    light = np.load(bag.with_suffix(".light_map.npy"))
    fov = light > 0
    channel = ChannelCalibration("mono", InverseResponse(lut, 8), np.where(fov, light, 0.0), None)
    photometric = PhotometricCalibration([channel], fov, None, "pixels").save(
        out / "photometric.yaml"
    )
    tracker = ground_truth_of(bag)["tracker"]
    handeye = out / "handeye.yaml"
    HandEyeCalibration(
        T_marker_camera=np.asarray(tracker["T_marker_camera"], np.float64),
        time_offset_ns=round(float(tracker["latency_s"]) * 1e9),
    ).save(handeye)
    params = write_simulated_parameters(bag, out / "endo3d.yaml", solve_scale=solve_scale)
    return photometric, handeye, params


def _commands(photometric: Path, handeye: Path, params: Path, rate: float) -> dict[str, list[str]]:
    def ros(*extra: str) -> list[str]:
        return ["--ros-args", "--params-file", str(params), *extra]

    return {
        "correction": [str(BIN / "endo-photometric-correction"),
                       *ros("-p", f"calibration_file:={photometric}")],
        "sfs": [str(BIN / "endo-sfs"), *ros()],
        "bridge": [str(BIN / "endo-tracker-bridge"), *ros("-p", f"handeye_file:={handeye}")],
        "flow": [str(BIN / "endo-flow"), *ros()],
        "replay": [str(BIN / "endo-replay"), str(BAG), "--loop", "--rate", f"{rate:g}",
                   "--topics", topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE,
                   "--wait-for-subscribers", "1", "--wait-timeout", "120"],
    }


def _summarise(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    ordered = sorted(values)
    return 1e3 * statistics.median(ordered), 1e3 * ordered[int(0.95 * (len(ordered) - 1))]


def run(minutes: float, interval_s: float, rate: float, solve_scale: float
        ) -> tuple[list[Sample], dict[str, dict[str, str]], dict[str, int]]:
    """Run the graph for ``minutes``; returns the samples, final diagnostics, exit codes."""
    work = Path(tempfile.mkdtemp(prefix="endo3d_soak_"))
    photometric, handeye, params = _setup(work, solve_scale)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    env, profile_note = with_large_frame_profile(env, work)
    print(f"soak: {profile_note}; logs in {work}", flush=True)
    offset_ns = HandEyeCalibration.load(handeye).time_offset_ns
    listener = Listener(offset_ns)
    rclpy.init()
    node = rclpy.create_node("soak_listener")
    for topic in (topics.IMAGE_RAW, topics.TRACKER_POSE):
        msg_type = Image if topic == topics.IMAGE_RAW else PoseStamped
        node.create_subscription(msg_type, topic, lambda d, t=topic: listener.on_input(t, d),
                                 SENSOR_DATA_QOS, raw=True)
    for topic, msg_type in ((topics.DEPTH_RELATIVE, Image), (topics.SCALE, Vector3Stamped),
                            (topics.CAMERA_POSE, PoseStamped)):
        node.create_subscription(msg_type, topic, lambda d, t=topic: listener.on_output(t, d),
                                 SENSOR_DATA_QOS, raw=True)
    node.create_subscription(DiagnosticArray, "/diagnostics", listener.on_diagnostics, 50)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    processes: dict[str, subprocess.Popen[bytes]] = {}
    logs = {}
    samples: list[Sample] = []
    try:
        for name, argv in _commands(photometric, handeye, params, rate).items():
            logs[name] = (work / f"{name}.log").open("wb")
            processes[name] = subprocess.Popen(argv, env=env, stdout=logs[name],
                                               stderr=subprocess.STDOUT)
        start = time.monotonic()
        listener.take()
        end = start + 60.0 * minutes
        next_sample = start + interval_s
        while time.monotonic() < end:
            time.sleep(max(0.0, next_sample - time.monotonic()))
            next_sample += interval_s
            counts, latencies = listener.take()
            sample = Sample(
                t_s=time.monotonic() - start,
                load=os.getloadavg()[0],
                rss_mb={n: _rss_kb(p.pid) / 1024 for n, p in processes.items()},
                rate={name: counts.get(name, 0) / interval_s for _, name in OUTPUTS.values()},
                latency_ms={name: _summarise(latencies.get(name, []))
                            for _, name in OUTPUTS.values()},
            )
            samples.append(sample)
            dead = [n for n, p in processes.items() if p.poll() is not None]
            print(f"{sample.t_s:6.0f} s load {sample.load:5.1f} "
                  + " ".join(f"{n} {sample.rss_mb[n]:.0f}MB" for n in processes)
                  + " | " + " ".join(f"{k} {v:.1f}/s {sample.latency_ms[k][0]:.0f}ms"
                                     for k, v in sample.rate.items())
                  + (f" | DEAD {dead}" if dead else ""), flush=True)
    finally:
        for process in processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        codes = {}
        for name, process in processes.items():
            try:
                codes[name] = process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                codes[name] = process.wait()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return samples, dict(listener.status), codes


def _steady(r0: float, r1: float, l0: float, l1: float) -> bool:
    """No drift: the rate lost at most 20 % and the median latency within 1.5× + 20 ms.

    A leak, a growing queue or a stuck stage slows the graph down over time;
    a rate that rises because the shared machine got quieter is no drift.
    """
    return r1 >= 0.8 * r0 and l1 <= 1.5 * l0 + 20.0


def _minute(samples: list[Sample], first_s: float, last_s: float) -> list[Sample]:
    return [s for s in samples if first_s < s.t_s <= last_s]


def report(samples: list[Sample], status: dict[str, dict[str, str]], codes: dict[str, int],
           args: argparse.Namespace) -> str:
    """One run's subsection of docs/benchmarks.md: verdicts first, then every sample."""
    names = list(samples[0].rss_mb)
    streams = list(samples[0].rate)
    total = samples[-1].t_s
    after_1min = _minute(samples, 60.0 - 1e-6, 60.0 + args.interval)
    base = after_1min[0] if after_1min else samples[0]
    first = _minute(samples, 60.0, 120.0)
    last = _minute(samples, total - 60.0, total)
    loads = [s.load for s in samples]
    lines = [
        f"{RUN_HEADING}{datetime.now(UTC):%Y-%m-%d %H:%M} UTC: `bench/soak.py --minutes "
        f"{args.minutes:g} --rate {args.rate:g} --solve-scale {args.solve_scale:g} --interval "
        f"{args.interval:g}`",
        "",
        f"{cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}. "
        f"**The machine was shared with other helpers' test suites and benchmarks: load "
        f"average {min(loads):.1f}–{max(loads):.1f} (median {statistics.median(loads):.1f}) "
        f"on {os.cpu_count()} cores during the run**, so rates and latencies measure the load "
        "as much as the graph.",
        "",
        "| target | measured | met |",
        "|---|---|---|",
    ]
    growth = {n: 100.0 * (samples[-1].rss_mb[n] / base.rss_mb[n] - 1.0)
              for n in names if base.rss_mb[n] > 0}
    worst = max(growth, key=lambda n: growth[n])
    lines.append(
        "| RSS growth ≤ 5 % after the first minute | "
        + ", ".join(f"{n} {growth[n]:+.1f} % ({base.rss_mb[n]:.0f}→{samples[-1].rss_mb[n]:.0f} MB)"
                    for n in names)
        + f" | {'yes' if growth[worst] <= 5.0 else 'no'} |"
    )
    if first and last:  # a sawtooth (heap high water) against a steady climb (a leak)
        floors = {n: (min(s.rss_mb[n] for s in first), min(s.rss_mb[n] for s in last))
                  for n in names}
        lines.append(
            "| (not a target: the lowest RSS of the last minute against the lowest of minute 2) | "
            + ", ".join(f"{n} {100.0 * (b / a - 1.0):+.1f} %" for n, (a, b) in floors.items()
                        if a > 0)
            + " | — |"
        )
    drift = []
    for stream in streams:
        r0 = statistics.mean(s.rate[stream] for s in first) if first else float("nan")
        r1 = statistics.mean(s.rate[stream] for s in last) if last else float("nan")
        l0 = statistics.median(s.latency_ms[stream][0] for s in first) if first else float("nan")
        l1 = statistics.median(s.latency_ms[stream][0] for s in last) if last else float("nan")
        drift.append((stream, r0, r1, l0, l1))
    lines.append(
        "| no rate or latency drift (minute 2 vs the last minute) | "
        + "; ".join(f"{s}: {r0:.1f}→{r1:.1f}/s, median {l0:.0f}→{l1:.0f} ms"
                    for s, r0, r1, l0, l1 in drift)
        + f" | {'yes' if all(_steady(*d[1:]) for d in drift) else 'no'} "
        "(rate down by at most 20 %, median latency within 1.5× + 20 ms) |"
    )
    stuck = [(s.t_s, k) for s in samples if s.t_s > 60.0 for k, v in s.rate.items() if v == 0]
    lines.append(
        f"| nothing stuck after any loop (every {args.interval:g} s has output of every stage)"
        f" | {len(stuck)} empty intervals of {len(samples)} × {len(streams)}"
        + (f" (first at {stuck[0][0]:.0f} s: {stuck[0][1]})" if stuck else "")
        + f" | {'yes' if not stuck else 'no'} |"
    )
    lines += ["", "The nodes' /diagnostics at the end (counters since their start):", "",
              "| status | received | processed | dropped | lost | clock jumps |",
              "|---|---|---|---|---|---|"]
    for name, values in sorted(status.items()):
        if values.get("received") is None:
            continue
        causes = ", ".join(f"{k.split('.', 1)[1]} {v}" for k, v in values.items()
                           if k.startswith("dropped.")) or "—"
        lines.append(f"| {name} | {values.get('received')} | {values.get('processed')} | "
                     f"{values.get('dropped')} ({causes}) | {values.get('lost')} | "
                     f"{values.get('clock_jumps')} |")
    lines += ["", f"Exit codes after SIGINT: {', '.join(f'{n} {c}' for n, c in codes.items())}.",
              "", "Every sample (RSS in MB; rate in messages/s; latency median/p95 in ms):", "",
              "| t (s) | load | " + " | ".join(f"RSS {n}" for n in names) + " | "
              + " | ".join(f"{s} /s | {s} ms" for s in streams) + " |",
              "|" + "---|" * (2 + len(names) + 2 * len(streams))]
    for s in samples:
        lines.append(
            f"| {s.t_s:.0f} | {s.load:.1f} | "
            + " | ".join(f"{s.rss_mb[n]:.0f}" for n in names) + " | "
            + " | ".join(f"{s.rate[k]:.1f} | {s.latency_ms[k][0]:.0f}/{s.latency_ms[k][1]:.0f}"
                         for k in streams) + " |"
        )
    return "\n".join(lines) + "\n"


def previous_runs(keep: int, path: Path = BENCHMARKS) -> list[str]:
    """The newest ``keep`` run subsections already in the soak section of ``path``."""
    text = path.read_text(encoding="utf-8") if path.exists() else ""
    if TITLE not in text or keep <= 0:
        return []
    start = text.index(TITLE)
    following = text.find("\n## ", start + len(TITLE))
    section = text[start:following if following >= 0 else len(text)]
    runs = section.split("\n" + RUN_HEADING)[1:]
    return [RUN_HEADING + run.strip("\n") + "\n" for run in runs[:keep]]


def main() -> int:
    """Run the soak; print each sample; write the section unless --no-write."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--interval", type=float, default=10.0, help="seconds per sample")
    parser.add_argument("--rate", type=float, default=0.5, help="replay rate (0.5)")
    parser.add_argument("--solve-scale", type=float, default=0.5)
    parser.add_argument("--no-write", action="store_true", help="do not edit docs/benchmarks.md")
    parser.add_argument("--keep", type=int, default=1,
                        help="earlier runs kept in docs/benchmarks.md below this one (1)")
    args = parser.parse_args()
    samples, status, codes = run(args.minutes, args.interval, args.rate, args.solve_scale)
    if not samples:
        print("soak: no sample taken", file=sys.stderr)
        return 2
    run_text = report(samples, status, codes, args)
    print(run_text)
    if not args.no_write:
        section = "\n".join([TITLE, "", INTRO, "", run_text, *previous_runs(args.keep)])
        replace_section(section.rstrip("\n") + "\n", TITLE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
