"""Watching the live graph from outside: frames per stage, latency, CPU and memory.

One code path for every figure the live graph is judged by: ``endo-demo``
prints them after its run and ``bench/bench_graph.py`` writes them into
docs/benchmarks.md. Both run the graph of :func:`endo_bringup.graph.graph_processes`
(the one description of the graph) and watch it with:

* :class:`GraphMonitor`: a listener node in this process, on the graph's DDS
  domain, in one of two modes (:data:`LISTEN_MODES`):

  - ``"recording"`` (``endo-demo`` and ``bench/bench_graph.py``): it
    subscribes to the small topics only: the camera_info the replay
    publishes beside each image (same stamp; ~0.4 kB) and ``/diagnostics``.
    The nodes' outputs are timed from the recording the graph's recorder
    writes anyway (:func:`recorded_arrivals`): each message's log time is
    the middleware's receive time at ``endo-record`` (rmw's
    ``received_timestamp``, the system clock; raised to the last one
    written when a message became takeable only after a later one, which
    the recorder counts as ``reordered``). Nothing here receives the
    ~5 MB of float images a frame carries (the ``"topics"`` mode spent
    11–13 CPU-ms per frame on them, beside a graph that needs all of the 2
    cores; docs/benchmarks.md).
  - ``"topics"`` (what it was; ``bench_first_frames``, ``bench_flow_node``):
    it subscribes (serialized, only the header stamp read) to the played
    image topic, the camera_info and every topic the nodes publish, and
    times each arrival here.

  The publish time of frame ``s`` at the replay is the DDS source timestamp
  of the played message with stamp ``s`` that this monitor received: the
  camera_info in ``"recording"`` mode (the image's when the bag has no
  camera_info), the image in ``"topics"`` mode. Latency of an output = its
  arrival (reception at the recorder, or here) minus that publish, same
  stamp, all on the system clock of this one machine (correction: one hop;
  SFS: two; flow's cloud: the whole graph, end to end). The two modes
  differ by the camera_info's publish after or before its image at the
  replay and by the recorder's reception against this listener's (both are
  the middleware's receive time of the same message); both measured once
  side by side (docs/benchmarks.md, bench_graph). The monitor also keeps
  the nodes' last ``/diagnostics`` (received, processed, skipped, dropped,
  lost).
* :class:`ProcessSampler`: CPU time (utime + stime of ``/proc/<pid>/stat``)
  and resident memory (``VmRSS``) of this process's children, sampled every
  ``period_s``; each child is named after the row of the table whose
  executable it runs.

:func:`graph_figures` turns both into :class:`GraphFigures` over the play
window (first to last image published, plus one frame period):

* per stage (a node of the table, its first per-frame output): frames in (on
  its first input, seen here), received (by the node on that input, its
  /diagnostics: fewer than in when DDS overwrote frames the node never saw,
  or the run ended while frames waited), out (on the output, seen here),
  skipped (the node's own count: stale frames passed over for a newer one,
  by design), dropped and lost (its /diagnostics), output rate (out per
  second of the play window), latency p50 / p99;
* end to end: the frame's publish at the replay to the cloud
  (``/endoscope/points``) arriving (at the recorder or here), p50 / p99;
* per process: CPU as a percentage of one core over the window, peak RSS.

:func:`stage_lines` prints them (the demo); the bench formats the same
:class:`GraphFigures` as markdown.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import threading
import time
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from endo_bringup.dds_profile import PROFILE_VARIABLES
from endo_bringup.graph import (
    PLAYED_TOPICS,
    PLAYER,
    RECORDER,
    GraphProcess,
    GraphSettings,
    graph_processes,
)
from endo_io import topics
from endo_io.bag import BagReader
from endo_io.errors import Endo3dError
from endo_io.serialized_stamp import serialized_header_stamp_ns

#: The output that ends the graph: the world cloud, the end-to-end latency's end.
CLOUD_TOPIC = topics.POINTS
#: Topics whose stamps are not the images' (latency against the image is meaningless).
_NOT_IMAGE_STAMPED = frozenset({topics.CAMERA_POSE, topics.MARKER_POSE, topics.MAP})
#: How the monitor times the graph (see the module docstring).
LISTEN_MODES = ("recording", "topics")


class GraphMonitorError(Endo3dError):
    """The monitor cannot give the figures asked for (a mode without the recording it needs)."""


def sent_topic(processes: Sequence[GraphProcess], listen: str) -> str:
    """The played topic whose DDS source times are the frames' publish at the replay.

    ``"recording"``: the camera_info when played (small), else the images;
    ``"topics"``: the images.
    """
    player = next(p for p in processes if p.name == PLAYER)
    if listen == "recording" and topics.CAMERA_INFO in player.publishes:
        return topics.CAMERA_INFO
    return player.publishes[0]


def recorded_arrivals(recording: Path, wanted: Sequence[str]
                      ) -> dict[str, dict[int, tuple[int, int]]]:
    """Per topic of ``wanted``: header stamp -> (publish, log time) ns of the recording.

    endo-record writes the middleware's receive time as both times today;
    the first message of a stamp counts (as the listener's does).

    Args:
        recording: the MCAP the graph's recorder wrote (finalised).
        wanted: topics to read (missing ones give no entry).
    """
    found: dict[str, dict[int, tuple[int, int]]] = defaultdict(dict)
    with BagReader(recording) as reader:
        for message in reader.messages([t for t in wanted if t in reader.topics]):
            stamp = serialized_header_stamp_ns(message.data)
            if stamp is not None:
                found[message.topic].setdefault(
                    stamp, (message.publish_time_ns, message.log_time_ns))
    return dict(found)


def node_name_of(process: GraphProcess) -> str:
    """The ROS node name a row runs.

    Its ``__node`` remap (SFS workers), else its executable without ``endo-``,
    dashes as underscores.
    """
    renamed = process.remaps.get("__node")
    return renamed or process.executable.removeprefix("endo-").replace("-", "_")


# --------------------------------------------------------------------------
# The listener


@dataclass
class _Arrivals:
    """Per topic: stamp -> (source time, reception time), wall-clock ns."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    times: dict[str, dict[int, tuple[int, int]]] = field(
        default_factory=lambda: defaultdict(dict)
    )
    status: dict[str, dict[str, str]] = field(default_factory=dict)

    def add(self, topic: str, data: bytes, info: Mapping[str, Any]) -> None:
        stamp = serialized_header_stamp_ns(data)
        if stamp is None:
            return
        received = int(info.get("received_timestamp") or 0) or time.time_ns()
        source = int(info.get("source_timestamp") or 0) or received
        with self.lock:
            self.times[topic].setdefault(stamp, (source, received))


class GraphMonitor:
    """A listener node on the graph (see the module docstring).

    Use as a context manager around the run; it spins in a thread of its own.
    Its subscriptions are best effort and 100 deep, so they match every
    publisher and keep up with every message (raw, stamp only).

    Args:
        processes: the graph's table (:func:`endo_bringup.graph.graph_processes`).
        env: the graph's environment: its ``ROS_DOMAIN_ID`` and Fast DDS
            profile variables (large shared-memory frames) apply here too; the
            profile variables are put into this process's environment, where
            Fast DDS reads them.
        listen: ``"recording"`` or ``"topics"`` (:data:`LISTEN_MODES`).

    Raises:
        GraphMonitorError: an unknown ``listen``.
    """

    def __init__(self, processes: Sequence[GraphProcess], env: Mapping[str, str],
                 listen: str = "topics") -> None:
        if listen not in LISTEN_MODES:
            raise GraphMonitorError(f"listen must be one of {LISTEN_MODES}, got {listen!r}")
        self.listen = listen
        self.processes = list(processes)
        self.domain_id = int(env.get("ROS_DOMAIN_ID", "0"))
        # Put back on exit: a later graph (or test) in this process must not
        # inherit a profile file that belonged to this run's temporary folder.
        self._previous_environment = {name: os.environ.get(name) for name in PROFILE_VARIABLES}
        for name in PROFILE_VARIABLES:
            if name in env:
                os.environ[name] = env[name]
        self.arrivals = _Arrivals()
        self._context: Any = None
        self._executor: Any = None
        self._thread: threading.Thread | None = None

    def watched_topics(self) -> list[str]:
        """The topics subscribed besides /diagnostics.

        ``"recording"``: the played topic of :func:`sent_topic` alone;
        ``"topics"``: the player's first topic (the images), its camera_info
        and every topic a node publishes.
        """
        nodes = [p for p in self.processes if p.name not in (PLAYER, RECORDER)]
        played = list(self.played_listeners(self.processes, self.listen))
        if self.listen == "recording":
            return played
        return list(dict.fromkeys([*played, *(t for n in nodes for t in n.publishes)]))

    @staticmethod
    def played_listeners(processes: Sequence[GraphProcess], listen: str = "topics"
                         ) -> dict[str, int]:
        """Played topic -> the monitor's subscriptions to it (the replay waits for them too).

        For :attr:`endo_bringup.graph.GraphSettings.listeners`; ``listen`` as
        the monitor's.
        """
        player = next(p for p in processes if p.name == PLAYER)
        if listen == "recording":
            return {sent_topic(processes, listen): 1}
        return {t: 1 for t in dict.fromkeys(
            [player.publishes[0], *(t for t in player.publishes if t == topics.CAMERA_INFO)])}

    def __enter__(self) -> GraphMonitor:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions

        from endo_io.bag import message_class
        from endo_io.diagnostics import DIAGNOSTICS_TOPIC

        self._context = rclpy.Context()
        rclpy.init(
            args=["graph_monitor"],  # not the caller's command line (rclpy's default)
            context=self._context,
            domain_id=self.domain_id,
            signal_handler_options=SignalHandlerOptions.NO,  # Ctrl-C is the caller's
        )
        node = rclpy.create_node("graph_monitor", context=self._context)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.BEST_EFFORT
        )
        for topic in self.watched_topics():
            # a callback of two arguments gets the message info (the DDS timestamps)
            on_message: Any = functools.partial(self.arrivals.add, topic)
            node.create_subscription(
                message_class(TOPIC_TYPES[topic]), topic, on_message, qos, raw=True
            )
        node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, 100)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()
        return self

    def _spin(self) -> None:
        import contextlib

        # the context is shut down from __exit__ while this spins
        with contextlib.suppress(Exception):
            self._executor.spin()

    def _on_diagnostics(self, msg: Any) -> None:
        with self.arrivals.lock:
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                values["hardware_id"] = status.hardware_id
                self.arrivals.status[status.name] = values

    def __exit__(self, *exc: object) -> None:
        import rclpy

        if self._executor is not None:
            self._executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=self._context)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for name, value in self._previous_environment.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value

    def snapshot(self) -> tuple[dict[str, dict[int, tuple[int, int]]], dict[str, dict[str, str]]]:
        """(topic -> stamp -> (source, reception) ns, status name -> key -> value), copied."""
        with self.arrivals.lock:
            return (
                {t: dict(v) for t, v in self.arrivals.times.items()},
                {n: dict(v) for n, v in self.arrivals.status.items()},
            )


#: Message type of each topic the monitor may watch (a subscription needs it
#: before the publisher exists, so it cannot come from discovery).
TOPIC_TYPES: dict[str, str] = {
    topics.IMAGE_RAW: "sensor_msgs/msg/Image",
    topics.CAMERA_INFO: "sensor_msgs/msg/CameraInfo",
    topics.IMAGE_CORRECTED: "sensor_msgs/msg/Image",
    topics.DEPTH_RELATIVE: "sensor_msgs/msg/Image",
    topics.DEPTH: "sensor_msgs/msg/Image",
    topics.NORMALS: "sensor_msgs/msg/Image",
    topics.POINTS: "sensor_msgs/msg/PointCloud2",
    topics.MAP: "sensor_msgs/msg/PointCloud2",
    topics.SCALE: "geometry_msgs/msg/Vector3Stamped",
    topics.CAMERA_POSE: "geometry_msgs/msg/PoseStamped",
    topics.MARKER_POSE: "geometry_msgs/msg/PoseStamped",
}


# --------------------------------------------------------------------------
# CPU and memory of the children


@dataclass
class _Sample:
    t: float
    cpu_s: float
    rss_mb: float


def _children(parent: int) -> list[int]:
    """Pids of the direct children of ``parent``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == parent:  # fields[0] is the state, [1] the parent pid
            found.append(int(entry.name))
    return found


def _cpu_and_rss(pid: int) -> tuple[float, float] | None:
    """(CPU seconds user + system, VmRSS MB) of ``pid``; None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    cpu_s = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14, 15)
    rss = next((line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:")), "0")
    return cpu_s, int(rss) / 1024


class ProcessSampler:
    """CPU time and RSS of this process's children every ``period_s``, in a thread.

    Args:
        processes: the table; a child is named after the row whose executable
            appears in its command line.
        period_s: sampling period, seconds.
    """

    def __init__(self, processes: Sequence[GraphProcess], period_s: float = 0.5) -> None:
        self.executables = {Path(p.command()[0]).name: p.name for p in processes}
        # several rows may run one executable (SFS workers): their command lines tell
        self.commands = [(p.command(), p.name) for p in processes]
        self.period_s = period_s
        self.samples: dict[str, list[_Sample]] = defaultdict(list)
        #: This process (the monitor's and the sampler's threads: the watching's cost).
        self.own: list[_Sample] = []
        self._names: dict[int, str | None] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> ProcessSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _name(self, pid: int) -> str | None:
        if self._names.get(pid) is None:  # None: not yet, or not a row (read again)
            try:
                raw = Path(f"/proc/{pid}/cmdline").read_bytes().rstrip(b"\0").split(b"\0")
            except OSError:
                return None
            self._names[pid] = self.row_of([a.decode(errors="replace") for a in raw])
        return self._names[pid]

    def row_of(self, argv: Sequence[str]) -> str | None:
        """The row a command line runs (None: none).

        The row whose command line ends ``argv`` (the interpreter before it),
        else the row whose executable ``argv`` names.
        """
        argv = list(argv)
        exact = [name for command, name in self.commands if argv[-len(command):] == command]
        names = [*exact, *(self.executables.get(Path(a).name) for a in argv)]
        return next((n for n in names if n is not None), None)

    def _run(self) -> None:
        parent = os.getpid()
        rows = {*self.executables.values(), *(name for _, name in self.commands)}
        known: dict[int, str] = {}
        while not self._stop.is_set():
            now = time.time()
            usage = _cpu_and_rss(parent)
            if usage is not None:
                self.own.append(_Sample(now, *usage))
            # /proc is scanned for the children only until every row has been seen: the
            # scan reads every process's stat (~2.5 ms of CPU per 100 processes, each
            # period, on the cores the graph runs on)
            if not rows <= set(self.samples):
                for pid in _children(parent):
                    name = self._name(pid)
                    if name is not None:
                        known[pid] = name
            for pid, name in list(known.items()):
                usage = _cpu_and_rss(pid)
                if usage is None:
                    del known[pid]  # it ended
                else:
                    self.samples[name].append(_Sample(now, *usage))
            self._stop.wait(self.period_s)


# --------------------------------------------------------------------------
# The figures


@dataclass(frozen=True)
class StageFigures:
    """One stage over the play window (see the module docstring)."""

    stage: str
    input_topic: str
    output_topic: str
    frames_in: int
    received: int | None
    frames_out: int
    skipped: int | None
    dropped: int | None
    lost: int | None
    rate_hz: float
    latency_ms: tuple[float, float]  # p50, p99 (NaN: none)


@dataclass(frozen=True)
class ProcessFigures:
    """One process: CPU (% of one core) over the play window, peak RSS (MB).

    cpu_s: CPU seconds from the start of the play window to the process's
    last sample (its work on the frames, the drain after the replay included).
    """

    name: str
    cpu_percent: float
    rss_mb: float
    cpu_s: float = float("nan")


@dataclass(frozen=True)
class GraphFigures:
    """Everything measured on one run (see the module docstring).

    window_s: the play window; frames_played: images published by the
    replay; end_to_end_ms: (p50, p99) image publish → cloud arrival, and
    end_to_end_frames how many clouds it is over; load: 1-minute load
    average at the end; timing: where the outputs' arrivals were taken
    (``"recording"``: at the recorder, ``"topics"``: at the monitor);
    listener_cpu_s: CPU seconds of this process (the monitor and the sampler,
    not the graph) over the same span as a process's ``cpu_s``.
    """

    window_s: float
    frames_played: int
    stages: list[StageFigures]
    end_to_end_ms: tuple[float, float]
    end_to_end_frames: int
    processes: list[ProcessFigures]
    load: float
    timing: str = "topics"
    listener_cpu_s: float = float("nan")

    def document(self) -> dict[str, Any]:
        """The figures as plain JSON-able data (pairs as lists; NaN stays NaN)."""
        return dict(json.loads(json.dumps(dataclasses.asdict(self))))

    def cpu_ms_per_frame(self, name: str) -> float:
        """CPU ms process ``name`` spent per frame it let out (per frame played: not a stage)."""
        process = next((p for p in self.processes if p.name == name), None)
        if process is None:
            return float("nan")
        stage = next((s for s in self.stages if s.stage == name), None)
        frames = self.frames_played if stage is None else stage.frames_out
        return 1e3 * process.cpu_s / frames if frames else float("nan")

    def stage(self, name: str) -> StageFigures:
        """The figures of stage ``name`` (a process name of the table)."""
        return next(s for s in self.stages if s.stage == name)

    @property
    def every_frame_kept(self) -> bool:
        """Every stage's per-frame output carried every frame played, and nothing was skipped.

        (A frame flow dropped for want of a pose still gives its scale: the
        outputs decide, not the drop counters.)
        """
        return all(not s.skipped and s.frames_out >= self.frames_played for s in self.stages)


def _percentiles(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    array = np.asarray(values)
    return float(np.percentile(array, 50)), float(np.percentile(array, 99))


def _latencies_ms(sent: Mapping[int, tuple[int, int]],
                  arrived: Mapping[int, tuple[int, int]]) -> list[float]:
    return [
        (reception - sent[stamp][0]) / 1e6
        for stamp, (_, reception) in arrived.items()
        if stamp in sent
    ]


def _diagnostic_counts(status: Mapping[str, Mapping[str, str]], node: str, first_input: str
                       ) -> dict[str, int] | None:
    """The node's counters summed over its statuses (None: no status from it).

    ``received`` is what reached its first input; skipped, dropped and lost
    are over all its inputs.
    """
    mine = [v for v in status.values() if v.get("hardware_id", "").lstrip("/") == node]
    if not mine:
        return None
    counts = {key: sum(int(v.get(key, 0)) for v in mine) for key in ("skipped", "dropped", "lost")}
    counts["received"] = sum(int(v.get(f"received.{first_input}", 0)) for v in mine)
    return counts


def graph_figures(
    processes: Sequence[GraphProcess],
    monitor: GraphMonitor,
    sampler: ProcessSampler | None,
    played: Mapping[str, int] | None = None,
    recording: Path | None = None,
    timing: str | None = None,
) -> GraphFigures:
    """The figures of a finished run (see the module docstring).

    played: messages the player published per topic (``GraphRun.played``).
    The monitor may match the player's new publisher after its first
    frames (the player starts once the graph's nodes subscribe), so the
    images played, the first stage's input and the play window come from
    it: window = frames played × their median interval, ending one interval
    after the last frame published.
    recording: the graph's finished recording (``GraphRun.recording``),
    needed when timing from it.
    timing: ``"recording"`` (arrivals at the recorder) or ``"topics"``
    (arrivals at the monitor); default the monitor's mode. A monitor in
    ``"topics"`` mode can give both from one run (it also receives the
    camera_info).

    Raises:
        GraphMonitorError: ``"recording"`` timing without a recording, or
            an unknown ``timing``.
    """
    timing = monitor.listen if timing is None else timing
    if timing not in LISTEN_MODES:
        raise GraphMonitorError(f"timing must be one of {LISTEN_MODES}, got {timing!r}")
    arrivals, status = monitor.snapshot()
    player = next(p for p in processes if p.name == PLAYER)
    image_topic = player.publishes[0]
    images = arrivals.get(sent_topic(processes, timing), {})
    if timing == "recording":
        if recording is None:
            raise GraphMonitorError("timing from the recording needs the run's recording")
        recorder = next((p for p in processes if p.name == RECORDER), None)
        kept = [] if recorder is None else [t for t in recorder.subscribes if t != image_topic]
        arrivals = recorded_arrivals(recording, kept)
    frames_played = len(images) if played is None else int(played.get(image_topic, len(images)))
    sent = sorted(source for source, _ in images.values())
    period = float(np.median(np.diff(sent))) if len(sent) > 1 else 1.0
    end = (sent[-1] if sent else 0) + period
    start = end - frames_played * period
    window_s = (end - start) / 1e9
    stages = []
    for process in processes:
        if process.name in (PLAYER, RECORDER):
            continue
        output = process.per_frame_outputs[0]
        first = process.subscribes[0]
        counts = _diagnostic_counts(status, node_name_of(process), first)
        got = arrivals.get(output, {})
        latency = (
            (float("nan"), float("nan")) if output in _NOT_IMAGE_STAMPED
            else _percentiles(_latencies_ms(images, got))
        )
        stages.append(StageFigures(
            stage=process.name, input_topic=first, output_topic=output,
            frames_in=(frames_played if first == image_topic
                       else int(played[first]) if played is not None and first in played
                       else len(arrivals.get(first, {}))),
            received=None if counts is None else counts["received"], frames_out=len(got),
            skipped=None if counts is None else counts["skipped"],
            dropped=None if counts is None else counts["dropped"],
            lost=None if counts is None else counts["lost"],
            rate_hz=len(got) / window_s if window_s > 0 else 0.0, latency_ms=latency,
        ))  # fmt: skip
    clouds = _latencies_ms(images, arrivals.get(CLOUD_TOPIC, {}))
    figures_of_processes = []
    listener_cpu_s = float("nan")
    if sampler is not None and sampler.own:
        before = [s for s in sampler.own if s.t <= start / 1e9]
        listener_cpu_s = sampler.own[-1].cpu_s - (before[-1] if before else sampler.own[0]).cpu_s
    if sampler is not None:
        for name, samples in sampler.samples.items():
            inside = [s for s in samples if start / 1e9 <= s.t <= end / 1e9 + sampler.period_s]
            cpu = (
                100.0 * (inside[-1].cpu_s - inside[0].cpu_s) / (inside[-1].t - inside[0].t)
                if len(inside) > 1 and inside[-1].t > inside[0].t else float("nan")
            )
            before = [s for s in samples if s.t <= start / 1e9]
            at_start = before[-1] if before else samples[0]
            figures_of_processes.append(ProcessFigures(
                name, cpu, max(s.rss_mb for s in samples), samples[-1].cpu_s - at_start.cpu_s
            ))
    return GraphFigures(
        window_s=window_s, frames_played=frames_played, stages=stages,
        end_to_end_ms=_percentiles(clouds), end_to_end_frames=len(clouds),
        processes=figures_of_processes, load=os.getloadavg()[0], timing=timing,
        listener_cpu_s=listener_cpu_s,
    )  # fmt: skip


def _count(value: int | None) -> str:
    return "?" if value is None else str(value)


def stage_lines(figures: GraphFigures) -> list[str]:
    """The figures as plain text lines (what ``endo-demo`` prints)."""
    lines = [
        f"{'stage':<28} {'output':<26} {'in':>5} {'rcvd':>5} {'out':>5} {'skipped':>7} "
        f"{'dropped':>7} {'lost':>4} {'rate/s':>6}  latency p50/p99 ms"
    ]
    for s in figures.stages:
        lines.append(
            f"{s.stage:<28} {s.output_topic:<26} {s.frames_in:>5} {_count(s.received):>5} "
            f"{s.frames_out:>5} "
            f"{_count(s.skipped):>7} {_count(s.dropped):>7} {_count(s.lost):>4} "
            f"{s.rate_hz:>6.1f}  {s.latency_ms[0]:.0f}/{s.latency_ms[1]:.0f}"
        )
    p50, p99 = figures.end_to_end_ms
    where = "at the recorder" if figures.timing == "recording" else "here"
    lines.append(
        f"end to end (frame published by the replay -> {CLOUD_TOPIC} {where}): p50 {p50:.0f} ms, "
        f"p99 {p99:.0f} ms over {figures.end_to_end_frames} clouds of {figures.frames_played} "
        f"frames in {figures.window_s:.1f} s"
    )
    if figures.processes:
        lines.append(
            "CPU (% of one core) / peak RSS: "
            + ", ".join(f"{p.name} {p.cpu_percent:.0f} % / {p.rss_mb:.0f} MB"
                        for p in figures.processes)
            + f"; load average {figures.load:.1f} on {os.cpu_count()} cores"
        )
    return lines


def planned_graph(
    bag: Path, photometric: Path, handeye: Path, out_dir: Path, settings: GraphSettings
) -> list[GraphProcess]:
    """The table :func:`~endo_bringup.graph.run_live_graph` runs with the same arguments.

    A monitor subscribes before the graph starts, so it needs the table first.
    """
    with BagReader(bag) as reader:
        played = [t for t in PLAYED_TOPICS if t in reader.topics]
    return graph_processes(bag, played, photometric, handeye, out_dir / "graph.mcap", settings)
