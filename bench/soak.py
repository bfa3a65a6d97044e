"""Soak: the whole live graph on a looping replay; memory, output rate and latency over time.

    .venv/bin/python bench/soak.py                 # 10 minutes, writes docs/benchmarks.md
    .venv/bin/python bench/soak.py --minutes 1 --no-write

Every node is its own OS process, as a user runs them:
``endo-photometric-correction`` → ``endo-sfs`` → ``endo-flow``, and
``endo-tracker-bridge`` → ``endo-flow``, fed by ``endo-replay --loop`` of the
phantom bag (the simulator's true calibration, hand–eye and registration
from its ground truth, so no fitting step runs first). Each ``--interval``
seconds the script samples

* every process's resident memory (``VmRSS`` of ``/proc/<pid>/status``), and
  how much of it is private (``RssAnon``: the heap, Python's and the
  libraries') and shared memory (``RssShmem``: the pages of Fast DDS's
  shared-memory segments this process has touched, its own and its peers'
  64 MB segments; they fill as frames cycle through the segments and stop at
  their size);
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
* the nodes' ``/diagnostics`` (dropped, lost in transport, clock jumps);
* at the end, every process's ``[ERROR]`` and ``[WARN]`` log lines, counted
  by cause (normal operation, loops included, should log no error).

Targets (issue 16): RSS growth ≤ 5 % after the first minute, no drift of
rate or latency (the first full minute after warm-up against the last), and
nothing stuck after any loop (every interval has output of every stage).

``--twin-flow-env NAME=VALUE[,NAME=VALUE...]`` compares allocator settings
inside one run: each occurrence starts one more ``endo-flow`` (``flow_b``,
``flow_c``, ...) on the same inputs, its outputs remapped under
``/flow_b/...``, with those environment variables (e.g.
``MALLOC_ARENA_MAX=2``) or, written ``name:=value``, parameters (e.g.
``map_enabled:=false``); every flow's memory is sampled side by side.
``--node-env NODE:NAME=VALUE`` sets a variable for one node of the graph.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
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


#: Fields of /proc/<pid>/status sampled (kB there, MB here): VmRSS = RssAnon + RssFile + RssShmem.
MEMORY_FIELDS = ("VmRSS", "RssAnon", "RssShmem")


def _memory_mb(pid: int) -> dict[str, float]:
    """VmRSS, RssAnon and RssShmem of ``pid`` in MB (0 when it is gone)."""
    found = dict.fromkeys(MEMORY_FIELDS, 0.0)
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key = line.split(":", 1)[0]
            if key in found:
                found[key] = int(line.split()[1]) / 1024
    except OSError:
        pass
    return found


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
    """One interval: elapsed s, load average, memory (MB) per process, rate (1/s) and latency.

    ``rss_mb`` is VmRSS; ``anon_mb`` and ``shmem_mb`` its private and
    shared-memory parts (:data:`MEMORY_FIELDS`).
    """

    t_s: float
    load: float
    rss_mb: dict[str, float]
    rate: dict[str, float]
    latency_ms: dict[str, tuple[float, float]]  # (median, p95)
    anon_mb: dict[str, float] = field(default_factory=dict)
    shmem_mb: dict[str, float] = field(default_factory=dict)


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


#: flow's outputs, remapped under /<twin name> for the extra flows of --twin-flow-env
FLOW_OUTPUTS = (topics.DEPTH, topics.POINTS, topics.MAP, topics.SCALE)


def _twin_names(count: int) -> list[str]:
    return [f"flow_{chr(ord('b') + k)}" for k in range(count)]


def _commands(photometric: Path, handeye: Path, params: Path, rate: float, *,
              twins: int = 0, twin_params: list[list[str]] | None = None
              ) -> dict[str, list[str]]:
    def ros(*extra: str) -> list[str]:
        return ["--ros-args", "--params-file", str(params), *extra]

    commands = {
        "correction": [str(BIN / "endo-photometric-correction"),
                       *ros("-p", f"calibration_file:={photometric}")],
        "sfs": [str(BIN / "endo-sfs"), *ros()],
        "bridge": [str(BIN / "endo-tracker-bridge"), *ros("-p", f"handeye_file:={handeye}")],
        "flow": [str(BIN / "endo-flow"), *ros()],
    }
    for k, twin in enumerate(_twin_names(twins)):
        remaps = [arg for topic in FLOW_OUTPUTS for arg in ("-r", f"{topic}:=/{twin}{topic}")]
        overrides = [arg for value in (twin_params or [[]] * twins)[k] for arg in ("-p", value)]
        # the same parameters under its own name: the file's /** section is for every node
        commands[twin] = [str(BIN / "endo-flow"),
                          *ros("-r", f"__node:={twin}", *remaps, *overrides)]
    commands["replay"] = [
        str(BIN / "endo-replay"), str(BAG), "--loop", "--rate", f"{rate:g}",
        "--topics", topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE,
        "--wait-for-subscribers", "1", "--wait-timeout", "120",
    ]
    return commands


def _assignments(values: list[str], what: str) -> dict[str, str]:
    """``NAME=VALUE`` strings as a dict (exit 2 on a malformed one)."""
    found = {}
    for value in values:
        name, sep, setting = value.partition("=")
        if not sep or not name:
            raise SystemExit(f"soak: {what} {value!r} is not NAME=VALUE")
        found[name] = setting
    return found


def log_causes(text: str) -> Counter[str]:
    """``[ERROR]``/``[WARN]`` lines of a node's log, counted as ``"ERROR <cause>"``.

    The cause: the exception class of ``dropped message (N so far): <Cause>: ...``
    and of ``<Cause> (N so far): ...``, else the line's words before its first
    parenthesis or colon (``clock jump``, ``lost in transport``).
    """
    found: Counter[str] = Counter()
    for line in text.splitlines():
        level = "ERROR" if line.startswith("[ERROR]") else "WARN" if line.startswith(
            "[WARN]") else None
        if level is None:
            continue
        body = line.split("]: ", 1)[-1]
        dropped = re.match(r"dropped message \(\d+ so far\): (\w+)", body)
        words = re.match(r"([^(:]{1,60})", body)
        cause = dropped.group(1) if dropped else (words.group(1).strip() if words else body)
        found[f"{level} {cause}"] += 1
    return found


def _summarise(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    ordered = sorted(values)
    return 1e3 * statistics.median(ordered), 1e3 * ordered[int(0.95 * (len(ordered) - 1))]


def run(minutes: float, interval_s: float, rate: float, solve_scale: float, *,
        node_env: dict[str, dict[str, str]] | None = None,
        twin_envs: list[dict[str, str]] | None = None,
        twin_params: list[list[str]] | None = None,
        ) -> tuple[list[Sample], dict[str, dict[str, str]], dict[str, int],
                   dict[str, Counter[str]]]:
    """Run the graph for ``minutes``: samples, final diagnostics, exit codes, log causes.

    The log causes: each process's error and warning lines (:func:`log_causes`).

    ``node_env``: node name -> extra environment variables of that node;
    ``twin_envs``: one more flow per entry, with its variables, and ``twin_params`` its
    ``name:=value`` parameters (see the module docstring).
    """
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
        extra = dict(node_env or {})
        twin_envs = twin_envs or []
        for twin, twin_env in zip(_twin_names(len(twin_envs)), twin_envs, strict=True):
            extra[twin] = {**extra.get("flow", {}), **twin_env}
        commands = _commands(photometric, handeye, params, rate, twins=len(twin_envs),
                             twin_params=twin_params)
        for name, argv in commands.items():
            logs[name] = (work / f"{name}.log").open("wb")
            processes[name] = subprocess.Popen(argv, env={**env, **extra.get(name, {})},
                                               stdout=logs[name], stderr=subprocess.STDOUT)
        start = time.monotonic()
        listener.take()
        end = start + 60.0 * minutes
        next_sample = start + interval_s
        while time.monotonic() < end:
            time.sleep(max(0.0, next_sample - time.monotonic()))
            next_sample += interval_s
            counts, latencies = listener.take()
            memory = {n: _memory_mb(p.pid) for n, p in processes.items()}
            sample = Sample(
                t_s=time.monotonic() - start,
                load=os.getloadavg()[0],
                rss_mb={n: m["VmRSS"] for n, m in memory.items()},
                rate={name: counts.get(name, 0) / interval_s for _, name in OUTPUTS.values()},
                latency_ms={name: _summarise(latencies.get(name, []))
                            for _, name in OUTPUTS.values()},
                anon_mb={n: m["RssAnon"] for n, m in memory.items()},
                shmem_mb={n: m["RssShmem"] for n, m in memory.items()},
            )
            samples.append(sample)
            dead = [n for n, p in processes.items() if p.poll() is not None]
            print(f"{sample.t_s:6.0f} s load {sample.load:5.1f} "
                  + " ".join(f"{n} {sample.rss_mb[n]:.0f}MB (anon {sample.anon_mb[n]:.0f}, "
                             f"shm {sample.shmem_mb[n]:.0f})" for n in processes)
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
    for log in logs.values():
        log.close()
    causes = {name: log_causes((work / f"{name}.log").read_text(errors="replace"))
              for name in logs}
    return samples, dict(listener.status), codes, causes


def _steady(r0: float, r1: float, l0: float, l1: float) -> bool:
    """No drift: the rate lost at most 20 % and the median latency within 1.5× + 20 ms.

    A leak, a growing queue or a stuck stage slows the graph down over time;
    a rate that rises because the shared machine got quieter is no drift.
    """
    return r1 >= 0.8 * r0 and l1 <= 1.5 * l0 + 20.0


def _minute(samples: list[Sample], first_s: float, last_s: float) -> list[Sample]:
    return [s for s in samples if first_s < s.t_s <= last_s]


def report(samples: list[Sample], status: dict[str, dict[str, str]], codes: dict[str, int],
           args: argparse.Namespace, log_lines: dict[str, Counter[str]] | None = None) -> str:
    """One run's subsection of docs/benchmarks.md: verdicts first, then every sample."""
    names = list(samples[0].rss_mb)
    streams = list(samples[0].rate)
    total = samples[-1].t_s
    after_1min = _minute(samples, 60.0 - 1e-6, 60.0 + args.interval)
    base = after_1min[0] if after_1min else samples[0]
    first = _minute(samples, 60.0, 120.0)
    last = _minute(samples, total - 60.0, total)
    loads = [s.load for s in samples]
    cores = os.cpu_count() or 1
    settings = "".join(f" --node-env {v}" for v in args.node_env) + "".join(
        f" --twin-flow-env {v}" for v in args.twin_flow_env)
    # the graph itself keeps about two cores busy: only a load well above that is other work
    busy = statistics.median(loads) > 2 * cores
    lines = [
        f"{RUN_HEADING}{datetime.now(UTC):%Y-%m-%d %H:%M} UTC: `bench/soak.py --minutes "
        f"{args.minutes:g} --rate {args.rate:g} --solve-scale {args.solve_scale:g} --interval "
        f"{args.interval:g}{settings}`",
        "",
        f"{cpu_model()}, {cores} cores, Python {sys.version.split()[0]}. "
        f"**Load average {min(loads):.1f}–{max(loads):.1f} (median "
        f"{statistics.median(loads):.1f}) on {cores} cores during the run"
        + ("**: a shared machine, so rates and latencies measure the load as much as the graph."
           if busy else "**."),
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
    if samples[-1].anon_mb:  # where the growth is: the heap, or shared-memory pages touched
        lines.append(
            "| (not a target: VmRSS = private (RssAnon) + shared memory (RssShmem) + files; "
            "each part after the first minute → at the end, MB) | "
            + ", ".join(f"{n} anon {base.anon_mb[n]:.0f}→{samples[-1].anon_mb[n]:.0f}, "
                        f"shm {base.shmem_mb[n]:.0f}→{samples[-1].shmem_mb[n]:.0f}"
                        for n in names)
            + " | — |"
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
    if log_lines is not None:
        lines += ["", "Log lines of each process over the run, `[ERROR]` and `[WARN]` by cause "
                  "(normal operation should log no error):", ""]
        for name, found in log_lines.items():
            text = ", ".join(f"{k} {v}" for k, v in sorted(found.items())) or "none"
            lines.append(f"* {name}: {text}")
    lines += ["", f"Exit codes after SIGINT: {', '.join(f'{n} {c}' for n, c in codes.items())}.",
              "", "Every sample (RSS in MB, with its private (anon) and shared-memory (shm) "
              "parts; rate in messages/s; latency median/p95 in ms):", "",
              "| t (s) | load | " + " | ".join(f"RSS {n} (anon/shm)" for n in names) + " | "
              + " | ".join(f"{s} /s | {s} ms" for s in streams) + " |",
              "|" + "---|" * (2 + len(names) + 2 * len(streams))]
    for s in samples:
        lines.append(
            f"| {s.t_s:.0f} | {s.load:.1f} | "
            + " | ".join(f"{s.rss_mb[n]:.0f} ({s.anon_mb.get(n, 0):.0f}/{s.shmem_mb.get(n, 0):.0f})"
                         for n in names) + " | "
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
    parser.add_argument("--node-env", action="append", default=[], metavar="NODE:NAME=VALUE",
                        help="an environment variable for one node (repeatable)")
    parser.add_argument("--twin-flow-env", action="append", default=[],
                        metavar="NAME=VALUE[,NAME=VALUE]",
                        help="one more flow (flow_b, flow_c, ...; outputs under /flow_b/...) "
                        "with these variables, to compare memory inside one run (repeatable)")
    args = parser.parse_args()
    node_env: dict[str, dict[str, str]] = defaultdict(dict)
    for value in args.node_env:
        node, sep, assignment = value.partition(":")
        if not sep or node not in (*NODES, "replay"):
            parser.error(f"--node-env {value!r}: NODE:NAME=VALUE with NODE one of "
                         f"{', '.join(NODES)}, replay")
        node_env[node].update(_assignments([assignment], "--node-env"))
    groups = [group.split(",") for group in args.twin_flow_env]
    twins = [_assignments([v for v in g if ":=" not in v], "--twin-flow-env") for g in groups]
    twin_params = [[v for v in g if ":=" in v] for g in groups]
    samples, status, codes, causes = run(args.minutes, args.interval, args.rate, args.solve_scale,
                                 node_env=dict(node_env), twin_envs=twins,
                                 twin_params=twin_params)
    if not samples:
        print("soak: no sample taken", file=sys.stderr)
        return 2
    run_text = report(samples, status, codes, args, causes)
    print(run_text)
    if not args.no_write:
        section = "\n".join([TITLE, "", INTRO, "", run_text, *previous_runs(args.keep)])
        replace_section(section.rstrip("\n") + "\n", TITLE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
