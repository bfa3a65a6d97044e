"""The endo3d graph as it exists so far, run on sample bags as separate OS processes.

Two parts, both driving the same command-line tools a user runs:

* :func:`run_offline_calibrations`: ``endo-calibrate`` on the gray-card bag
  (photometric.yaml) and ``endo-handeye`` on the hand–eye bag (handeye.yaml).
* :func:`run_live_graph`: the processes of :func:`graph_processes`, the one
  description of the live graph: a table with, for each process, its
  executable, arguments, ROS parameters and remappings, and the topics it
  subscribes to and publishes. ``endo-record`` records the nodes' outputs and
  the ground truth, ``endo-photometric-correction``, ``endo-sfs`` and
  ``endo-tracker-bridge`` (source ros) and ``endo-flow`` (metric depth,
  world cloud, map and scale) run as nodes, and ``endo-replay``
  plays a phantom bag into them. Every process talks to the others over DDS
  only; :func:`describe_graph` prints the table.

The demo's replay → record round trip is a smaller table of the same rows
(:func:`recorder_process`, :func:`replay_process`), started the same way
(:class:`~endo_bringup.process_group.ProcessGroup`) and waited for with the
same :func:`wait_for_recording`. Scoring the recording is
:mod:`endo_process.evaluation`'s job.
"""

from __future__ import annotations

import contextlib
import re
import subprocess
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from endo_bringup.process_group import ProcessGroup, console_script
from endo_io.bag import BagReader, deserialize
from endo_io.bag.streams import GrowingCounter
from endo_io.camera import CameraModel
from endo_io.topics import (
    CAMERA_INFO,
    CAMERA_POSE,
    DEPTH,
    DEPTH_RELATIVE,
    IMAGE_CORRECTED,
    IMAGE_RAW,
    MAP,
    MARKER_POSE,
    POINTS,
    SCALE,
    TRACKER_POSE,
    TRUE_CAMERA_POSE,
    TRUE_DEPTH,
)
from endo_sim.ground_truth import ground_truth_of

#: The bag's topics that are played into the graph, unchanged: the bridge
#: listens on the tracker driver's /tracker/pose, as a real driver publishes it.
PLAYED_TOPICS = [IMAGE_RAW, CAMERA_INFO, TRACKER_POSE, TRUE_DEPTH, TRUE_CAMERA_POSE]
#: Names of the recorder and player processes (their logs, their exit codes).
RECORDER, PLAYER = "endo-record", "endo-replay"

#: The recorder's niceness in a graph run (the demo's, the benches'). It needs no
#: latency, only to keep up on average (its subscriptions queue what it has not
#: yet taken), so on a loaded machine the CPU goes to the frames' path first; at
#: nice 0 its chunk writes and copies (~10 CPU-ms per frame) competed with SFS and
#: flow (docs/benchmarks.md, "The live graph at video rate: reading"). A run
#: checks that the recording holds every message (wait_for_recording). Under
#: sustained overload a niced recorder falls behind and its queues overflow, so
#: endo-launch's --record, a user's recording of a live session, stays at nice 0.
RECORDER_NICENESS = 10


class GraphError(RuntimeError):
    """A process of the graph failed to start or to finish its part."""


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
# The table of processes


@dataclass(frozen=True)
class GraphProcess:
    """One process of the graph: a row of its table.

    name: the process's name in the run (its log file, its exit code);
    executable: the console script; arguments: its own command-line
    arguments; parameters: ROS parameters (``-p NAME:=VALUE``, values as
    typed); remaps: ROS remappings (``-r FROM:=TO``); subscribes / publishes:
    the topics it reads and writes, after remapping (the first subscribed
    topic is the one whose every message gives one output message).
    per_frame: the published topics that carry one message per message of
    the first input (None: all of them); the others (flow's depth and cloud
    before the scale converged, its periodic map) carry fewer. package and
    node_name: the ROS package of the executable and the ROS node it runs
    (the key of its section in a parameter file; empty for the tools);
    params_file: a ROS parameter file given before the ``-p`` overrides.
    nice: added to the process's niceness when it starts (0: as its parent;
    the recorder's :data:`RECORDER_NICENESS`).
    """

    name: str
    executable: str
    arguments: tuple[str, ...] = ()
    parameters: Mapping[str, str] = field(default_factory=dict)
    remaps: Mapping[str, str] = field(default_factory=dict)
    subscribes: tuple[str, ...] = ()
    publishes: tuple[str, ...] = ()
    per_frame: tuple[str, ...] | None = None
    package: str = ""
    node_name: str = ""
    params_file: str = ""
    nice: int = 0

    @property
    def per_frame_outputs(self) -> tuple[str, ...]:
        """The published topics with one message per message of the first input."""
        return self.publishes if self.per_frame is None else self.per_frame

    def command(self) -> list[str]:
        """The command line: executable, arguments, then the ``--ros-args`` block."""
        argv = [console_script(self.executable), *self.arguments]
        if self.parameters or self.remaps or self.params_file:
            argv.append("--ros-args")
            if self.params_file:
                argv += ["--params-file", self.params_file]
            for name, value in self.parameters.items():
                argv += ["-p", f"{name}:={value}"]
            for source, target in self.remaps.items():
                argv += ["-r", f"{source}:={target}"]
        return argv


#: The graph's nodes, upstream first: process name, ROS package, ROS node
#: name, the topics each reads (the first one paces its outputs) and writes.
NODES: tuple[GraphProcess, ...] = (
    GraphProcess(
        "endo-photometric-correction",
        "endo-photometric-correction",
        package="endo_calib",
        node_name="photometric_correction",
        subscribes=(IMAGE_RAW,),
        publishes=(IMAGE_CORRECTED,),
    ),
    GraphProcess(
        "endo-sfs",
        "endo-sfs",
        package="endo_sfs",
        node_name="sfs",
        subscribes=(IMAGE_CORRECTED, CAMERA_INFO),
        publishes=(DEPTH_RELATIVE,),
    ),
    GraphProcess(
        "endo-tracker-bridge",
        "endo-tracker-bridge",
        package="endo_tracker_bridge",
        node_name="tracker_bridge",
        subscribes=(TRACKER_POSE,),
        publishes=(CAMERA_POSE, MARKER_POSE),
    ),
    GraphProcess(
        "endo-flow",
        "endo-flow",
        package="endo_flow",
        node_name="flow",
        subscribes=(DEPTH_RELATIVE, IMAGE_CORRECTED, CAMERA_INFO, CAMERA_POSE),
        publishes=(SCALE, DEPTH, POINTS, MAP),
        per_frame=(SCALE,),
    ),
)


def graph_nodes(
    parameters: Mapping[str, Mapping[str, str]] | None = None,
    *,
    params_file: str = "",
    remaps: Mapping[str, str] | None = None,
) -> list[GraphProcess]:
    """The rows of :data:`NODES` with their settings.

    Args:
        parameters: process name -> ROS parameters (``-p NAME:=VALUE``, values
            as typed) of that node.
        params_file: a ROS parameter file every node gets (``--params-file``).
        remaps: ROS remappings every node gets; a remapped topic is also
            renamed in the row's subscribes and publishes.
    """
    given = parameters or {}
    rules = dict(remaps or {})
    return [
        replace(
            node,
            parameters=dict(given.get(node.name, {})),
            params_file=params_file,
            remaps=rules,
            subscribes=tuple(rules.get(t, t) for t in node.subscribes),
            publishes=tuple(rules.get(t, t) for t in node.publishes),
            per_frame=None
            if node.per_frame is None
            else tuple(rules.get(t, t) for t in node.per_frame),
        )
        for node in NODES
    ]


def recorder_lost(log_dir: Path) -> str:
    """The recorder's own ``lost:`` summary line from its log, stripped ("" when it lost nothing).

    endo-record counts what it received but could not write (its write queue
    full, a failed write: :class:`endo_io.record.RecordReport`): a run's
    counts read from the recording would otherwise blame those frames on the
    stage whose output they were.
    """
    try:
        text = (log_dir / f"{RECORDER}.log").read_text(errors="replace")
    except OSError:
        return ""
    lines = [line.strip() for line in text.splitlines() if line.strip().startswith("lost: ")]
    return lines[-1] if lines else ""


def recorder_process(
    topics: Sequence[str], output: Path, nice: int = RECORDER_NICENESS,
    compression: str = "lz4", writer_nice: int = 0,
) -> GraphProcess:
    """``endo-record`` of ``topics`` into ``output``, flushed every 0.2 s (readable meanwhile).

    Chunks in lz4, not zstd: the recorder compresses ~5 MB of float images per
    frame, and zstd (level 3, mcap's) cost 2.0 ms of CPU per MB against lz4's
    0.5 ms, for files 1.16x bigger (a graph recording, docs/benchmarks.md).
    It runs at ``nice`` (:data:`RECORDER_NICENESS` by default); ``compression``
    is endo-record's ``--compression``, ``writer_nice`` its ``--writer-nice``
    (the writing thread's niceness on top of the process's).
    """
    return GraphProcess(
        RECORDER,
        "endo-record",
        arguments=("--topics", *topics, "-o", str(output), "--flush-period", "0.2",
                   "--compression", compression, "--writer-nice", str(writer_nice)),
        subscribes=tuple(topics),
        nice=nice,
    )


def replay_process(
    bag: Path, topics: Sequence[str], rate: float, subscribers: Mapping[str, int] | None = None
) -> GraphProcess:
    """``endo-replay`` of ``topics`` of ``bag`` at ``rate``.

    It plays once every topic has a subscriber, or, given ``subscribers``
    (topic -> count), once each of those topics has that many: every
    subscription of the graph matched, so that no one misses the first
    frames to discovery.
    """
    arguments = (str(bag), "--topics", *topics, "--rate", repr(float(rate)))
    waited = {t: n for t, n in (subscribers or {}).items() if n > 0}
    wait = (
        ("--wait-topics", *(f"{t}={n}" for t, n in waited.items()), "--wait-timeout",
         repr(REPLAY_WAIT_TIMEOUT_S))
        if waited else ("--wait-for-subscribers", "1")
    )  # fmt: skip
    return GraphProcess(PLAYER, "endo-replay", arguments=(*arguments, *wait),
                        publishes=tuple(topics))  # fmt: skip


def subscriber_counts(
    processes: Sequence[GraphProcess], topics: Sequence[str],
    listeners: Mapping[str, int] | None = None,
) -> dict[str, int]:
    """Topic -> subscriptions it has in the table (plus ``listeners``: outside it)."""
    extra = listeners or {}
    return {
        t: sum(t in p.subscribes for p in processes) + int(extra.get(t, 0)) for t in topics
    }


def write_camera_file(bag: Path, path: Path) -> Path | None:
    """The bag's first camera_info as a camera_calibration YAML at ``path`` (None: it has none).

    The nodes' ``warm_up_camera_file``: they warm up on a frame of that camera.
    """
    with BagReader(bag) as reader:
        if CAMERA_INFO not in reader.topics:
            return None
        first = next(reader.messages(topics=[CAMERA_INFO]), None)
    if first is None:
        return None
    CameraModel.from_camera_info(deserialize(first)).save_yaml(path)
    return path


@dataclass
class GraphSettings:
    """How the live graph is run.

    rate: playback speed factor of the phantom bag. model, roughness,
    solve_scale: the SFS node's parameters. T_world_tracker: (4, 4) tracker
    frame → world frame (metres), the bridge's registration parameter.
    startup_timeout_s: how long the nodes may take to come up (when the
    kernel cache is empty the SFS node first compiles its numba kernels:
    about 2.5 min of CPU, more while the other processes start; ``make venv``
    compiles them first);
    drain_timeout_s: how long to wait for the outputs after the replay ends.
    node_parameters: extra ROS parameters per process name, added to that
    row's (a benchmark's configuration, e.g. ``{"endo-sfs": {"warm_start": "false"}}``).
    listeners: played topic -> subscriptions outside the table the replay
    waits for too (a :class:`~endo_bringup.graph_monitor.GraphMonitor`).
    sfs_workers: ``endo-sfs`` processes sharing the frames (its
    ``worker_count``; :func:`sfs_worker_rows`). 1 by default: on 2 cores
    two one-thread workers let more depths out but doubled the latency
    (docs/benchmarks.md, session graphrate); more workers are for more cores.
    recorder_nice: the recorder's niceness (:data:`RECORDER_NICENESS`).
    recorder_compression: the recorder's chunk compression (lz4 | zstd | none).
    recorder_writer_nice: the niceness of the recorder's writing thread on top
    of ``recorder_nice`` (endo-record's ``--writer-nice``).
    """

    rate: float = 0.25
    model: str = "near_light"
    roughness: float = 0.0
    solve_scale: float = 0.5
    T_world_tracker: np.ndarray = field(default_factory=lambda: np.eye(4))
    startup_timeout_s: float = 90.0
    drain_timeout_s: float = 20.0
    node_parameters: Mapping[str, Mapping[str, str]] = field(default_factory=dict)
    listeners: Mapping[str, int] = field(default_factory=dict)
    sfs_workers: int = 1
    recorder_nice: int = RECORDER_NICENESS
    recorder_compression: str = "lz4"
    recorder_writer_nice: int = 0


#: The SFS row's process name (worker 0's when there are several).
SFS_PROCESS = "endo-sfs"


def sfs_worker_rows(nodes: Sequence[GraphProcess], workers: int) -> list[GraphProcess]:
    """``nodes`` with the SFS row as ``workers`` processes sharing the frames.

    Worker ``i`` is the row with ``worker_count`` / ``worker_index``
    parameters (docs/sfs.md, "Workers"), its ROS node renamed ``sfs_<i>``
    (``-r __node:=``) and its process named ``endo-sfs`` (worker 0: the
    stage's figures) or ``endo-sfs-<i>``. All publish the one depth topic,
    every frame once, merged by stamp downstream. ``workers`` 1: ``nodes``
    unchanged.

    Raises:
        GraphError: ``workers`` below 1.
    """
    if workers < 1:
        raise GraphError(f"sfs workers must be at least 1, got {workers}")
    if workers == 1:
        return list(nodes)
    rows: list[GraphProcess] = []
    for node in nodes:
        if node.name != SFS_PROCESS:
            rows.append(node)
            continue
        rows += [
            replace(
                node,
                name=SFS_PROCESS if i == 0 else f"{SFS_PROCESS}-{i}",
                parameters={**node.parameters, "worker_count": str(workers),
                            "worker_index": str(i)},
                remaps={**node.remaps, "__node": f"{node.node_name}_{i}"},
            )
            for i in range(workers)
        ]  # fmt: skip
    return rows


def _float_list(values: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.ravel(values)) + "]"


def graph_processes(
    bag: Path,
    played: Sequence[str],
    photometric: Path,
    handeye: Path,
    recording: Path,
    settings: GraphSettings,
) -> list[GraphProcess]:
    """The live graph, in start order: recorder, the four nodes, the player.

    The recorder keeps every node output, the camera_info played beside the
    images (so that viewers can place them) and the ground truth.

    Args:
        bag: the bag played into the graph.
        played: its topics that are played (those of PLAYED_TOPICS it has).
        photometric, handeye: the calibration files the nodes load.
        recording: where the recorder writes the nodes' outputs and the truth.
        settings: the nodes' parameters and the playback rate.
    """
    # the nodes warm up on a frame of the bag's camera (run_live_graph writes the file)
    camera = {"warm_up_camera_file": str(camera_file_path(recording))} if (
        CAMERA_INFO in played) else {}
    rows: dict[str, Mapping[str, str]] = {
        "endo-photometric-correction": {"calibration_file": str(photometric)},
        "endo-sfs": {
            "model": settings.model,
            "roughness": repr(float(settings.roughness)),
            "solve_scale": repr(float(settings.solve_scale)),
            **camera,
        },
        "endo-tracker-bridge": {
            "source": "ros",
            "handeye_file": str(handeye),
            "T_world_tracker": _float_list(settings.T_world_tracker),
        },
        "endo-flow": camera,
    }
    nodes = sfs_worker_rows(graph_nodes({
        name: {**rows.get(name, {}), **settings.node_parameters.get(name, {})}
        for name in {*rows, *settings.node_parameters}
    }), settings.sfs_workers)
    recorded = [*node_outputs(nodes), CAMERA_INFO, TRUE_DEPTH, TRUE_CAMERA_POSE]
    recorder = recorder_process(recorded, recording, settings.recorder_nice,
                                settings.recorder_compression, settings.recorder_writer_nice)
    subscribers = subscriber_counts([recorder, *nodes], played, settings.listeners)
    return [recorder, *nodes, replay_process(bag, played, settings.rate, subscribers)]


def camera_file_path(recording: Path) -> Path:
    """Where a graph run keeps its bag's camera (beside the recording)."""
    return recording.with_name("camera.yaml")


def describe_graph(processes: Sequence[GraphProcess]) -> str:
    """The table as text: process, subscribes, publishes, one row each."""
    rows = [("process", "subscribes", "publishes")]
    rows += [(p.name, ", ".join(p.subscribes), ", ".join(p.publishes)) for p in processes]
    widths = [max(len(row[i]) for row in rows) for i in range(2)]
    return "\n".join(f"{a:<{widths[0]}}  {b:<{widths[1]}}  {c}".rstrip() for a, b, c in rows)


def _process(processes: Sequence[GraphProcess], name: str) -> GraphProcess:
    return next(p for p in processes if p.name == name)


def _nodes(processes: Sequence[GraphProcess]) -> list[GraphProcess]:
    return [p for p in processes if p.name not in (RECORDER, PLAYER)]


def node_outputs(processes: Sequence[GraphProcess]) -> list[str]:
    """The topics the graph's nodes publish (neither the player's nor the recorder's), once each."""
    return list(dict.fromkeys(topic for node in _nodes(processes) for topic in node.publishes))


def expected_counts(processes: Sequence[GraphProcess], played: Mapping[str, int]) -> Counter[str]:
    """Messages each topic carries when no node drops one.

    played: bag topic -> messages played, in the order the player was given
    them. The player's topics carry what it plays; each node's per-frame
    outputs carry as many messages as its first input (nodes are in
    upstream-first order); its other outputs are not counted here.
    """
    counts: Counter[str] = Counter()
    for topic, count in zip(_process(processes, PLAYER).publishes, played.values(), strict=True):
        counts[topic] = count
    for node in _nodes(processes):
        for topic in node.per_frame_outputs:
            counts[topic] = counts[node.subscribes[0]]
    return counts


# --------------------------------------------------------------------------
# Running it


@dataclass
class GraphRun:
    """What a live-graph run left behind.

    recording: the MCAP of the recorder's topics; played: messages in the
    bag per played (bag) topic; return_codes: exit status of each process
    (None: killed); log_dir: one log per process; seconds: wall time of the
    run; processes: the table that was run.
    """

    recording: Path
    played: dict[str, int]
    return_codes: dict[str, int | None]
    log_dir: Path
    seconds: float
    processes: list[GraphProcess]


@dataclass(frozen=True)
class StageCount:
    """One output topic of a stage: messages in (its input) and out (recorded)."""

    stage: str
    topic: str
    count_in: int
    count_out: int
    return_code: int | None


def stage_counts(run: GraphRun, recorded: Mapping[str, int]) -> list[StageCount]:
    """Per recorded output topic of each process, what went in and what came out.

    recorded: messages per topic in the recording. The player's "in" is what
    the bag holds; a node's "in" is what reached its first input (recorded
    when the recorder keeps that topic, else what the player sent on it).
    """
    player = _process(run.processes, PLAYER)
    sent = dict(zip(player.publishes, run.played.values(), strict=True))
    kept = set(_process(run.processes, RECORDER).subscribes)
    rows = []
    for process in run.processes:
        if process.name == RECORDER:
            continue
        code = run.return_codes.get(process.name)
        for topic in process.publishes:
            if topic not in kept:
                continue
            if process is player:
                count_in = sent[topic]
            else:
                first = process.subscribes[0]
                count_in = recorded.get(first, 0) if first in kept else sent.get(first, 0)
            rows.append(StageCount(process.name, topic, count_in, recorded.get(topic, 0), code))
    return rows


_SUBSCRIBED = re.compile(r"subscribed to (\S+) \[")
#: Every node logs its DDS settings once its executor exists, after its
#: constructor returned (:func:`endo_io.process.run_node`): its warm-up is done
#: and its publishers and subscriptions exist.
NODE_UP = re.compile(r"DDS: domain \d+")
#: How long the replay waits for its subscribers to match (the nodes are up by then).
REPLAY_WAIT_TIMEOUT_S = 30.0


def _wait_for_recorder(group: ProcessGroup, topics: list[str], timeout_s: float) -> None:
    """Wait until the recorder logs a subscription to each of ``topics``.

    The recorder subscribes to a topic when a publisher of it appears, so
    this also means that every node is up (the SFS node creates its
    publisher after loading its kernels).
    """
    deadline = time.monotonic() + timeout_s
    while True:
        subscribed = set(_SUBSCRIBED.findall(group.log(RECORDER)))
        missing = [t for t in topics if t not in subscribed]
        if not missing:
            return
        for name in group.processes:
            if not group.running(name):
                raise GraphError(f"{name} exited early:\n{group.log(name)}")
        if time.monotonic() > deadline:
            raise GraphError(f"no publisher of {', '.join(missing)} after {timeout_s:g} s")
        time.sleep(0.1)


def wait_for_nodes(group: ProcessGroup, names: Sequence[str], timeout_s: float) -> None:
    """Wait until each of ``names`` has logged :data:`NODE_UP` (warmed up, subscribed).

    Raises:
        GraphError: one exited first, or ``timeout_s`` passed.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        waiting = [name for name in names if not NODE_UP.search(group.log(name))]
        if not waiting:
            return
        for name in waiting:
            if not group.running(name):
                raise GraphError(f"{name} exited early:\n{group.log(name)}")
        if time.monotonic() > deadline:
            raise GraphError(f"{', '.join(waiting)} not up after {timeout_s:g} s")
        time.sleep(0.1)


def wait_for_recording(
    recording: Path, expected: Mapping[str, int], timeout_s: float, quiet_s: float = 1.5
) -> Counter[str]:
    """Wait until a recording being written holds ``expected`` messages per topic.

    Gives up after ``timeout_s``, or once the recording has not grown for
    ``quiet_s`` (a node dropped messages; they will not come). Returns the
    messages per topic in its complete chunks at that point.

    The file is counted by a :class:`~endo_io.bag.streams.GrowingCounter`:
    each poll reads only the records written since the last one, and no
    chunk's data (a whole read, ``count_messages``, decompressed a 60 s
    graph recording in 4.8 CPU-s at every poll, on the cores the graph
    still drains on).
    """
    deadline = time.monotonic() + timeout_s
    counter = GrowingCounter(recording)
    counts = counter.count()
    last_change = time.monotonic()
    while time.monotonic() < deadline:
        if all(counts[t] >= n for t, n in expected.items()):
            break
        time.sleep(0.5)
        now = counter.count()
        if now != counts:
            counts, last_change = now, time.monotonic()
        elif time.monotonic() - last_change >= quiet_s:
            break
    return counts


def bag_seconds(bag: Path) -> float:
    """Bag time covered by ``bag``, seconds."""
    with BagReader(bag) as reader:
        span = reader.time_range_ns
    return 0.0 if span is None else (span[1] - span[0]) / 1e9


def play_and_record(
    group: ProcessGroup,
    player: GraphProcess,
    recording: Path,
    expected: Mapping[str, int],
    *,
    play_timeout_s: float,
    drain_timeout_s: float,
) -> None:
    """Start the player, wait for it to end and for the recording to hold ``expected``.

    The recorder (:data:`RECORDER`, already started in ``group``) is then
    stopped with SIGINT, which finalises the recording. A player still running
    after ``play_timeout_s`` is stopped and reported by its exit status.
    """
    replay = group.start(player.name, player.command(), nice=player.nice)
    with contextlib.suppress(subprocess.TimeoutExpired):
        replay.wait(play_timeout_s)
    group.stop([player.name])
    # Delivered is not yet written: wait until the flushed, still open
    # recording holds everything, then let SIGINT finalise it.
    wait_for_recording(recording, expected, drain_timeout_s)
    group.stop([RECORDER], timeout_s=30.0)


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
    processes = graph_processes(bag, list(played), photometric, handeye, recording, settings)
    nodes = _nodes(processes)
    child_env = dict(env, RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONUNBUFFERED="1")
    start = time.monotonic()
    with ProcessGroup(child_env, log_dir) as group:
        if CAMERA_INFO in played:
            write_camera_file(bag, camera_file_path(recording))
        for process in (_process(processes, RECORDER), *nodes):
            group.start(process.name, process.command(), nice=process.nice)
        _wait_for_recorder(group, node_outputs(processes), settings.startup_timeout_s)
        wait_for_nodes(group, [node.name for node in nodes], settings.startup_timeout_s)
        play_and_record(
            group,
            _process(processes, PLAYER),
            recording,
            expected_counts(processes, played),
            play_timeout_s=settings.startup_timeout_s + bag_seconds(bag) / settings.rate + 15.0,
            drain_timeout_s=settings.drain_timeout_s,
        )
        group.stop()
    return GraphRun(
        recording=recording,
        played=played,
        return_codes=dict(group.return_codes),
        log_dir=log_dir,
        seconds=time.monotonic() - start,
        processes=processes,
    )
