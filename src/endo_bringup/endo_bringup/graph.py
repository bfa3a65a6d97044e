"""The endo3d graph as it exists so far, run on sample bags as separate OS processes.

Two parts, both driving the same command-line tools a user runs:

* :func:`run_offline_calibrations`: ``endo-calibrate`` on the gray-card bag
  (photometric.yaml) and ``endo-handeye`` on the hand–eye bag (handeye.yaml).
* :func:`run_live_graph`: ``endo-photometric-correction``, ``endo-sfs`` and
  ``endo-tracker-bridge`` (source ros) as nodes, ``endo-record`` recording
  their outputs and the ground truth, then ``endo-replay`` of a phantom bag
  into them. Every process talks to the others over DDS only:

  ============================  =======================================  ==========================
  process                       subscribes                               publishes
  ============================  =======================================  ==========================
  endo-replay (the bag)                                                  /endoscope/image_raw,
                                                                         /endoscope/camera_info,
                                                                         /tracker/driver_pose (the
                                                                         bag's /tracker/pose),
                                                                         /ground_truth/depth,
                                                                         /ground_truth/camera_pose
  endo-photometric-correction   /endoscope/image_raw                     /endoscope/image_corrected
  endo-sfs                      /endoscope/image_corrected, camera_info  /endoscope/depth_relative
  endo-tracker-bridge           /tracker/driver_pose                     /endoscope/pose
  endo-record (graph.mcap)      the three outputs + the ground truth
  ============================  =======================================  ==========================

Scoring the recording is :mod:`endo_bringup.evaluation`'s job.
"""

from __future__ import annotations

import contextlib
import re
import subprocess
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from endo_bringup.process_group import ProcessGroup, console_script
from endo_io.bag import BagReader
from endo_io.errors import BagError
from endo_io.topics import (
    CAMERA_INFO,
    CAMERA_POSE,
    DEPTH_RELATIVE,
    IMAGE_CORRECTED,
    IMAGE_RAW,
    TRACKER_POSE,
    TRUE_CAMERA_POSE,
    TRUE_DEPTH,
)

#: What the recorder keeps: the graph's outputs and the bag's ground truth.
RECORDED_TOPICS = [IMAGE_CORRECTED, DEPTH_RELATIVE, CAMERA_POSE, TRUE_DEPTH, TRUE_CAMERA_POSE]
#: Topics the nodes publish; the recorder must have subscribed to them before playing.
NODE_OUTPUT_TOPICS = [IMAGE_CORRECTED, DEPTH_RELATIVE, CAMERA_POSE]
#: The bag's topics that are played, and where the tracker poses go: the
#: bridge publishes /tracker/pose itself, so the bag's driver poses are
#: played on the bridge's input topic (its ``ros_topic`` default).
DRIVER_TOPIC = "/tracker/driver_pose"
PLAYED_TOPICS = [IMAGE_RAW, CAMERA_INFO, TRACKER_POSE, TRUE_DEPTH, TRUE_CAMERA_POSE]


class GraphError(RuntimeError):
    """A process of the graph failed to start or to finish its part."""


def ground_truth_of(bag: Path) -> dict[str, object]:
    """The simulator's ``<stem>.ground_truth.yaml`` beside ``bag``."""
    path = bag.with_name(bag.stem + ".ground_truth.yaml")
    if not path.exists():
        raise GraphError(f"{path} not found (endo-sim writes it beside the bag)")
    loaded = yaml.safe_load(path.read_text())
    if not isinstance(loaded, dict):
        raise GraphError(f"{path} is not a ground-truth mapping")
    return loaded


# --------------------------------------------------------------------------
# Offline calibrations


@dataclass
class OfflineStep:
    """One offline command: its command line, exit status, output and result file."""

    argv: list[str]
    return_code: int
    output: str
    result: Path
    seconds: float


def _run_step(argv: list[str], result: Path, env: dict[str, str], log: Path) -> OfflineStep:
    start = time.monotonic()
    completed = subprocess.run(
        argv, env=env, capture_output=True, text=True, check=False, timeout=300
    )
    output = completed.stdout + completed.stderr
    log.write_text("$ " + " ".join(argv) + "\n" + output)
    return OfflineStep(argv, completed.returncode, output, result, time.monotonic() - start)


def run_offline_calibrations(
    graycard_bag: Path, handeye_bag: Path, out_dir: Path, env: dict[str, str]
) -> tuple[OfflineStep, OfflineStep]:
    """``endo-calibrate`` and ``endo-handeye`` on the sample bags, as a user runs them.

    The card distance, board size, square size and tracker unit are the ones
    the simulator used (read from the bags' ground-truth YAML), i.e. what a
    user measures and types in. Writes ``out_dir/photometric.yaml`` and
    ``out_dir/handeye.yaml``; returns the two steps (check ``return_code``).
    """
    card = ground_truth_of(graycard_bag)["scene"]["gray_card"]  # type: ignore[index]
    handeye_truth = ground_truth_of(handeye_bag)
    board = handeye_truth["scene"]["checkerboard"]  # type: ignore[index]
    columns, rows = board["inner_corners"]
    photometric = out_dir / "photometric.yaml"
    handeye = out_dir / "handeye.yaml"
    calibrate = [
        console_script("endo-calibrate"),
        "--bag", str(graycard_bag),
        "--card-distance", f"{float(card['distance_m']):g}",
        "-o", str(photometric),
    ]  # fmt: skip
    handeye_argv = [
        console_script("endo-handeye"),
        str(handeye_bag),
        "-o", str(handeye),
        "--board", f"{columns}x{rows}",
        "--square-mm", f"{float(board['square_m']) * 1e3:g}",
        "--pose-unit", str(handeye_truth["tracker"]["units"]),  # type: ignore[index]
    ]  # fmt: skip
    logs = out_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    return (
        _run_step(calibrate, photometric, env, logs / "endo-calibrate.log"),
        _run_step(handeye_argv, handeye, env, logs / "endo-handeye.log"),
    )


# --------------------------------------------------------------------------
# The live graph


@dataclass
class GraphSettings:
    """How the live graph is run.

    rate: playback speed factor of the phantom bag. model, roughness,
    solve_scale: the SFS node's parameters. T_world_tracker: (4, 4) tracker
    frame → world frame (metres), the bridge's registration parameter.
    startup_timeout_s: how long the nodes may take to come up (when the
    kernel cache is empty the SFS node first compiles its numba kernels:
    about 20 s of CPU, more while the other processes start);
    drain_timeout_s: how long to wait for the outputs after the replay ends.
    """

    rate: float = 0.25
    model: str = "near_light"
    roughness: float = 0.0
    solve_scale: float = 0.5
    T_world_tracker: np.ndarray = field(default_factory=lambda: np.eye(4))
    startup_timeout_s: float = 90.0
    drain_timeout_s: float = 20.0


@dataclass
class GraphRun:
    """What a live-graph run left behind.

    recording: the MCAP of RECORDED_TOPICS; played: messages in the bag per
    played topic; return_codes: exit status of each process (None: killed);
    log_dir: one log per process; seconds: wall time of the run.
    """

    recording: Path
    played: dict[str, int]
    return_codes: dict[str, int | None]
    log_dir: Path
    seconds: float
    commands: dict[str, list[str]]


def _float_list(values: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.ravel(values)) + "]"


def node_commands(
    photometric: Path, handeye: Path, settings: GraphSettings
) -> dict[str, list[str]]:
    """Command lines of the three nodes, with their parameters and remappings."""
    return {
        "endo-photometric-correction": [
            console_script("endo-photometric-correction"),
            "--ros-args",
            "-p", f"calibration_file:={photometric}",
            "-r", f"image_raw:={IMAGE_RAW}",
            "-r", f"image_corrected:={IMAGE_CORRECTED}",
        ],
        "endo-sfs": [
            console_script("endo-sfs"),
            "--ros-args",
            "-p", f"model:={settings.model}",
            "-p", f"roughness:={float(settings.roughness)!r}",
            "-p", f"solve_scale:={float(settings.solve_scale)!r}",
            "-r", f"image_corrected:={IMAGE_CORRECTED}",
            "-r", f"camera_info:={CAMERA_INFO}",
            "-r", f"depth_relative:={DEPTH_RELATIVE}",
        ],
        "endo-tracker-bridge": [
            console_script("endo-tracker-bridge"),
            "--ros-args",
            "-p", "source:=ros",
            "-p", f"ros_topic:={DRIVER_TOPIC}",
            "-p", f"handeye_file:={handeye}",
            "-p", f"T_world_tracker:={_float_list(settings.T_world_tracker)}",
        ],
    }  # fmt: skip


def count_messages(path: Path) -> Counter[str]:
    """Messages per topic readable so far in a (possibly still written) bag."""
    counts: Counter[str] = Counter()
    try:
        with BagReader(path) as reader:
            try:
                for message in reader.messages():
                    counts[message.topic] += 1
            except BagError:
                pass  # the unfinished tail of a file being written
    except BagError:
        pass
    return counts


_SUBSCRIBED = re.compile(r"subscribed to (\S+) \[")


def _wait_for_recorder(group: ProcessGroup, topics: list[str], timeout_s: float) -> None:
    """Wait until the recorder logs a subscription to each of ``topics``.

    The recorder subscribes to a topic when a publisher of it appears, so
    this also means that every node is up (the SFS node creates its
    publisher after loading its kernels).
    """
    deadline = time.monotonic() + timeout_s
    while True:
        subscribed = set(_SUBSCRIBED.findall(group.log("endo-record")))
        missing = [t for t in topics if t not in subscribed]
        if not missing:
            return
        for name in group.processes:
            if not group.running(name):
                raise GraphError(f"{name} exited early:\n{group.log(name)}")
        if time.monotonic() > deadline:
            raise GraphError(f"no publisher of {', '.join(missing)} after {timeout_s:g} s")
        time.sleep(0.1)


def _wait_for_drain(
    recording: Path, expected: dict[str, int], timeout_s: float, quiet_s: float = 1.5
) -> Counter[str]:
    """Wait until the recording holds ``expected`` or stops growing for ``quiet_s``."""
    deadline = time.monotonic() + timeout_s
    counts = count_messages(recording)
    last_change = time.monotonic()
    while time.monotonic() < deadline:
        if all(counts[t] >= n for t, n in expected.items()):
            break
        time.sleep(0.5)
        now = count_messages(recording)
        if now != counts:
            counts, last_change = now, time.monotonic()
        elif time.monotonic() - last_change >= quiet_s:
            break
    return counts


def run_live_graph(
    bag: Path,
    photometric: Path,
    handeye: Path,
    out_dir: Path,
    env: dict[str, str],
    settings: GraphSettings,
) -> GraphRun:
    """Run the nodes and the recorder, play ``bag`` into them, stop everything.

    Writes ``out_dir/graph.mcap`` and one log per process in
    ``out_dir/logs``. Every child is stopped (SIGINT, then SIGKILL after a
    grace period) before this returns or raises.

    Raises:
        GraphError: a node exited early or did not come up in time.
    """
    recording = out_dir / "graph.mcap"
    log_dir = out_dir / "logs"
    with BagReader(bag) as reader:
        played = {t: reader.topics[t].message_count for t in PLAYED_TOPICS if t in reader.topics}
    commands = node_commands(photometric, handeye, settings)
    commands["endo-record"] = [
        console_script("endo-record"),
        "--topics", *RECORDED_TOPICS,
        "-o", str(recording),
        "--flush-period", "0.2",
    ]  # fmt: skip
    commands["endo-replay"] = [
        console_script("endo-replay"),
        str(bag),
        "--topics", *played,
        "--remap", f"{TRACKER_POSE}:={DRIVER_TOPIC}",
        "--rate", repr(float(settings.rate)),
        "--wait-for-subscribers", "1",
    ]  # fmt: skip
    child_env = dict(env, RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONUNBUFFERED="1")
    start = time.monotonic()
    with ProcessGroup(child_env, log_dir) as group:
        group.start("endo-record", commands["endo-record"])
        for name in ("endo-photometric-correction", "endo-sfs", "endo-tracker-bridge"):
            group.start(name, commands[name])
        _wait_for_recorder(group, NODE_OUTPUT_TOPICS, settings.startup_timeout_s)
        replay = group.start("endo-replay", commands["endo-replay"])
        playing_s = _bag_seconds(bag) / settings.rate
        # A hung player is stopped just below and reported by its exit status.
        with contextlib.suppress(subprocess.TimeoutExpired):
            replay.wait(settings.startup_timeout_s + playing_s + 15.0)
        group.stop(["endo-replay"])
        expected = {
            IMAGE_CORRECTED: played.get(IMAGE_RAW, 0),
            DEPTH_RELATIVE: played.get(IMAGE_RAW, 0),
            TRUE_DEPTH: played.get(TRUE_DEPTH, 0),
            TRUE_CAMERA_POSE: played.get(TRUE_CAMERA_POSE, 0),
            # the bridge drops nothing from a clean driver; dropouts are absent samples
            CAMERA_POSE: played.get(TRACKER_POSE, 0),
        }
        _wait_for_drain(recording, expected, settings.drain_timeout_s)
        group.stop(["endo-record"])
        group.stop()
    return GraphRun(
        recording=recording,
        played=played,
        return_codes=dict(group.return_codes),
        log_dir=log_dir,
        seconds=time.monotonic() - start,
        commands=commands,
    )


def _bag_seconds(bag: Path) -> float:
    """Bag time covered by ``bag``, seconds."""
    with BagReader(bag) as reader:
        span = reader.time_range_ns
    return 0.0 if span is None else (span[1] - span[0]) / 1e9
