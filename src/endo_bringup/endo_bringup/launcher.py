"""``endo-launch``: the whole graph on your own topics, each node its own process.

Pip-only (no ``ros2 launch`` needed): the nodes of :data:`endo_bringup.graph.NODES`
started through :class:`~endo_bringup.process_group.ProcessGroup`, with

* ``--calibration photometric.yaml`` and ``--handeye handeye.yaml``: the two
  calibration files (a missing one is warned about at start);
* before anything starts (``--dry-run`` too), each node's configuration
  checked as the node will check it (:func:`check_nodes`): the parameter
  file through rcl, every value against the node's parameter table, the
  calibration files through the nodes' loaders; a fault is one line, exit 2;
* a preset source: ``live`` (your camera driver and tracker publish the
  inputs), ``replay BAG`` (``endo-replay`` with ``/clock``, ``--rate``,
  ``--loop``) or ``sim`` (``endo-sim live``);
* one ROS parameter file given to every node (``--params``, passed as
  ``--ros-args --params-file``; ``--write-params PATH`` writes the shipped
  ``config/endo3d.yaml``), ``--namespace`` and ``--remap FROM:=TO``;
* every line a node writes printed with its name in front (and kept in
  ``--log-dir``); SIGINT and SIGTERM forwarded to every child, which shut down
  cleanly; a node that dies reported with its exit code and its last log
  lines, then the graph stopped (exit 1), or restarted with a growing
  backoff under ``--respawn``;
* the source started only once every node is up, warmed up before it
  subscribed (``endo-sfs`` has loaded or compiled its kernels; with
  ``replay``, ``endo-sfs`` and ``endo-flow`` have run a frame of the bag's
  camera), and a replay plays once every subscription of each played topic
  has matched, so no frame is lost to start-up;
* ``--record OUT.mcap``: ``endo-record`` of every node output and the
  camera_info beside the images (plus the ground truth a replayed bag has).

A replay without ``--loop`` ends the run once it has played and the graph's
outputs have stopped growing. ``--dry-run`` checks, then prints the command lines.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NoReturn, TextIO

import yaml

from endo_bringup.graph import (
    NODE_UP,
    PLAYED_TOPICS,
    PLAYER,
    REPLAY_WAIT_TIMEOUT_S,
    GraphProcess,
    GraphRun,
    graph_nodes,
    node_outputs,
    stage_counts,
    subscriber_counts,
    write_camera_file,
)
from endo_bringup.params_file import write as write_params
from endo_bringup.process_group import ProcessGroup
from endo_io.bag import BagReader
from endo_io.bag.streams import count_messages
from endo_io.cli import refuse_existing, report_error
from endo_io.dds_transport import configure_large_frames
from endo_io.errors import Endo3dError, yaml_error_line
from endo_io.topics import CAMERA_INFO, IMAGE_RAW, TRACKER_POSE, TRUE_CAMERA_POSE, TRUE_DEPTH

PROGRAM = "endo-launch"
#: Names of the source and recorder processes.
SOURCE, RECORDER = "source", "endo-record"
#: The SFS node's line once its kernels are loaded (endo_sfs.node).
KERNELS_READY = re.compile(r"shape-from-shading kernels ready")
#: The nodes that warm up on a frame of the stream's camera (``warm_up_camera_file``).
WARMED_ON_THE_CAMERA = ("endo-sfs", "endo-flow")
#: Respawn backoff: first delay, factor, cap (seconds); a node that ran this
#: long before dying starts again from the first delay.
BACKOFF_FIRST_S, BACKOFF_FACTOR, BACKOFF_MAX_S, BACKOFF_RESET_S = 1.0, 2.0, 30.0, 60.0
#: After a replay ends, the run ends once the recording has not grown for this
#: long (a loaded SFS node may still be solving its last frame).
DRAIN_QUIET_S = 6.0


class LaunchError(Endo3dError):
    """The graph could not be started as asked (a missing file, a bag without images)."""


class DomainInUseError(LaunchError):
    """Another endo3d graph already runs in this ROS domain: the two would mix their data."""


class NodeFailedError(LaunchError):
    """A node exited while the graph was starting, or did not come up in time."""


@dataclass
class LaunchPlan:
    """Everything ``endo-launch`` starts: nodes first, then the source, and the recorder."""

    nodes: list[GraphProcess]
    source: GraphProcess | None
    recorder: GraphProcess | None
    ends: bool  # the source ends by itself (a replay without --loop)
    warnings: list[str] = field(default_factory=list)
    #: replay: the bag's camera, written here before the nodes start (they warm up on it)
    camera_file: Path | None = None

    @property
    def processes(self) -> list[GraphProcess]:
        """Start order: recorder, nodes, source."""
        head = [self.recorder] if self.recorder else []
        tail = [self.source] if self.source else []
        return [*head, *self.nodes, *tail]


def _remap_rule(text: str) -> tuple[str, str]:
    source, sep, target = text.partition(":=")
    if not sep or not source or not target:
        raise argparse.ArgumentTypeError(f"expected FROM:=TO, got {text!r}")
    return source, target


def _node_parameter(text: str) -> tuple[str, str, str]:
    target, sep, value = text.partition(":=")
    node, dot, name = target.partition(".")
    nodes = {row.node_name for row in graph_nodes()}
    if not sep or not dot or not name or node not in nodes:
        raise argparse.ArgumentTypeError(
            f"expected NODE.NAME:=VALUE with NODE one of {', '.join(sorted(nodes))}, got {text!r}"
        )
    return node, name, value


def _namespace(text: str) -> str:
    name = "/" + text.strip("/")
    if not re.fullmatch(r"(/[A-Za-z_][A-Za-z0-9_]*)*|/", name):
        raise argparse.ArgumentTypeError(f"not a ROS namespace: {text!r}")
    return "" if name == "/" else name


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-launch`` argument parser (subcommands ``live``, ``replay``, ``sim``)."""
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_argument_group("graph")
    g.add_argument("--params", type=Path, metavar="FILE",
                   help="ROS parameter file for every node (e.g. a copy of config/endo3d.yaml)")
    g.add_argument("--calibration", type=Path, metavar="photometric.yaml",
                   help="endo-calibrate's file for endo-photometric-correction "
                   "(its calibration_file; overrides the parameter file)")
    g.add_argument("--handeye", type=Path, metavar="handeye.yaml",
                   help="endo-handeye's file for endo-tracker-bridge "
                   "(its handeye_file; overrides the parameter file)")
    g.add_argument("--param", type=_node_parameter, action="append", default=[],
                   metavar="NODE.NAME:=VALUE",
                   help="one parameter of one node, e.g. sfs.solve_scale:=0.5 (NODE: "
                   "photometric_correction, sfs, tracker_bridge, flow; overrides the "
                   "parameter file; repeatable)")
    g.add_argument("--namespace", type=_namespace, default="", metavar="NS",
                   help="put the nodes and every graph topic under NS (/rig1/endoscope/...)")
    g.add_argument("--remap", type=_remap_rule, action="append", default=[], metavar="FROM:=TO",
                   help="rename a graph topic for every process, e.g. "
                   "/endoscope/image_raw:=/camera/image_raw (repeatable)")
    g.add_argument("--record", type=Path, metavar="OUT.mcap",
                   help="record every node output and camera_info into OUT.mcap")
    g.add_argument("--respawn", action="store_true",
                   help="restart a node that dies (backoff 1 s, doubling up to 30 s)")
    g.add_argument("--log-dir", type=Path, default=None, metavar="DIR",
                   help="one log file per process (default: a new temporary directory)")
    g.add_argument("--startup-timeout", type=float, default=180.0, metavar="SECONDS",
                   help="how long the nodes may take to come up (SFS compiles its kernels "
                   "on the very first run; default 180)")
    g.add_argument("--drain-timeout", type=float, default=30.0, metavar="SECONDS",
                   help="replay: after the bag ends, how long to wait for the outputs "
                   "(default 30)")
    g.add_argument("--quiet", action="store_true", help="do not echo the nodes' logs")
    g.add_argument("--allow-shared-domain", action="store_true",
                   help="start even when another endo3d graph already runs in this ROS domain "
                   "(its data and ours then mix)")
    g.add_argument("--dry-run", action="store_true",
                   help="check the nodes' parameters and calibration files as a start does, "
                   "print the command lines, start nothing")
    parser = argparse.ArgumentParser(
        prog=PROGRAM,
        description="Start the endo3d graph (correction → SFS → tracker bridge → flow), "
        "each node its own process, on a live camera, a recording or the simulator.",
    )
    parser.add_argument("--write-params", type=Path, metavar="PATH",
                        help="write the parameter file with every node's defaults and exit "
                             "(an existing PATH only with --overwrite)")
    parser.add_argument("--overwrite", action="store_true",
                        help="let --write-params replace an existing file")
    sub = parser.add_subparsers(dest="preset", metavar="{live,replay,sim}")
    sub.add_parser("live", parents=[common],
                   help="your camera driver and tracker publish the inputs")
    replay = sub.add_parser("replay", parents=[common], help="play a recording into the graph")
    replay.add_argument("bag", type=Path, help=".mcap file or rosbag2 directory")
    replay.add_argument("--rate", type=float, default=1.0, help="playback speed factor (1)")
    replay.add_argument("--loop", action="store_true", help="play again from the start at the end")
    sim = sub.add_parser("sim", parents=[common], help="endo-sim live as camera and tracker")
    sim.add_argument("scene", nargs="?", default="colon", help="endo-sim scene (colon)")
    sim.add_argument("--sim-arg", action="append", default=[], metavar="ARG",
                     help="an argument for endo-sim live, e.g. --sim-arg=--fps=15 (repeatable)")
    return parser  # fmt: skip


def topic_rules(
    topics: Sequence[str], namespace: str, remaps: Sequence[tuple[str, str]]
) -> dict[str, str]:
    """Remapping of each graph topic: the user's rule, else the namespace in front."""
    user = dict(remaps)
    rules = {t: user.get(t, namespace + t) for t in topics}
    rules.update(user)
    return {source: target for source, target in rules.items() if source != target}


def plan_launch(options: argparse.Namespace) -> LaunchPlan:
    """The processes ``options`` ask for (nothing is started).

    Raises:
        LaunchError: the parameter file or the bag does not exist.
    """
    params = ""
    if options.params is not None:
        if not options.params.is_file():
            raise LaunchError(f"no parameter file {options.params}")
        params = str(options.params.resolve())
    base = graph_nodes()
    graph_topics = sorted({t for n in base for t in (*n.subscribes, *n.publishes)})
    rules = topic_rules(graph_topics, options.namespace, options.remap)
    user = dict(options.remap)
    overrides: dict[str, dict[str, str]] = {}
    process_of = {row.node_name: row.name for row in base}
    for node_name, name, value in options.param:
        overrides.setdefault(process_of[node_name], {})[name] = value
    for flag, process, name in ((options.calibration, "endo-photometric-correction",
                                 "calibration_file"),
                                (options.handeye, "endo-tracker-bridge", "handeye_file")):
        if flag is not None:
            if not flag.is_file():
                raise LaunchError(f"no file {flag}")
            overrides.setdefault(process, {})[name] = str(flag.resolve())
    nodes = []
    for node in graph_nodes(overrides, params_file=params, remaps=rules):
        # Each node gets the rules of its own topics (it would ignore the others) and the user's.
        own = set(next(b for b in base if b.name == node.name).subscribes) | set(
            next(b for b in base if b.name == node.name).publishes
        )
        kept = {k: v for k, v in rules.items() if k in own or k in user}
        if options.namespace:
            kept = {"__ns": options.namespace, **kept}
        nodes.append(replace(node, remaps=kept))
    source: GraphProcess | None = None
    camera_file: Path | None = None
    played: list[str] = []
    if options.preset == "replay":
        if not options.bag.exists():
            raise LaunchError(f"no bag {options.bag}")
        with BagReader(options.bag) as reader:
            played = [t for t in PLAYED_TOPICS if t in reader.topics]
        if IMAGE_RAW not in played:
            raise LaunchError(f"{options.bag} has no {IMAGE_RAW}: nothing to play into the graph")
        if CAMERA_INFO in played and options.log_dir is not None:
            # the nodes warm up on a frame of the bag's camera
            camera_file = Path(options.log_dir) / "camera.yaml"
            warm = {"warm_up_camera_file": str(camera_file)}
            nodes = [replace(n, parameters={**warm, **n.parameters})
                     if n.name in WARMED_ON_THE_CAMERA else n for n in nodes]  # fmt: skip
    recorder = None
    if options.record is not None:
        recorded_extra = [rules.get(t, t) for t in (TRUE_DEPTH, TRUE_CAMERA_POSE) if t in played]
        recorded = [*node_outputs(nodes), rules.get(CAMERA_INFO, CAMERA_INFO), *recorded_extra]
        recorder = GraphProcess(RECORDER, "endo-record", arguments=(
            "--topics", *recorded, "-o", str(options.record), "--flush-period", "0.5"),
            subscribes=tuple(recorded))  # fmt: skip
    ends = False
    if options.preset == "replay":
        # Play once every subscription of each played topic has matched (not /clock, not a
        # topic nobody reads), so that no node or recorder misses the first frames.
        readers = [*nodes, *([recorder] if recorder else [])]
        counts = subscriber_counts(readers, [rules.get(t, t) for t in played])
        waited = [f"{t}={counts[rules.get(t, t)]}" for t in played if counts[rules.get(t, t)]]
        arguments = [str(options.bag), "--topics", *played, "--rate", repr(options.rate),
                     "--clock", "--wait-topics", *waited,
                     "--wait-timeout", repr(REPLAY_WAIT_TIMEOUT_S)]  # fmt: skip
        if options.loop:
            arguments.append("--loop")
        for topic in played:
            if rules.get(topic, topic) != topic:
                arguments += ["--remap", f"{topic}:={rules[topic]}"]
        _check_replay_arguments(arguments)
        source = GraphProcess(SOURCE, "endo-replay", arguments=tuple(arguments),
                              publishes=tuple(rules.get(t, t) for t in played))  # fmt: skip
        ends = not options.loop
    elif options.preset == "sim":
        _check_sim_arguments(["live", options.scene, *options.sim_arg])
        inputs = (IMAGE_RAW, CAMERA_INFO, TRACKER_POSE)
        sim_rules = {t: rules[t] for t in inputs if t in rules}
        source = GraphProcess(SOURCE, "endo-sim", arguments=("live", options.scene,
                              *options.sim_arg), remaps=sim_rules,
                              publishes=tuple(rules.get(t, t) for t in inputs))  # fmt: skip
    return LaunchPlan(nodes, source, recorder, ends, check_nodes(nodes), camera_file=camera_file)


def _check_replay_arguments(arguments: Sequence[str]) -> None:
    """Check the source's arguments with endo-replay's own parser and checks, before any start."""
    from endo_io.replay_node import build_parser as replay_parser
    from endo_io.replay_node import check_options

    try:
        check_options(_parse_quietly(replay_parser(), arguments, "endo-replay"))
    except ValueError as error:
        raise LaunchError(f"endo-replay: {error}") from None


def _check_sim_arguments(arguments: Sequence[str]) -> None:
    """Parse ``endo-sim live``'s arguments with its own parser, before any start."""
    from endo_sim.cli import build_parser as sim_parser

    _parse_quietly(sim_parser(), arguments, "endo-sim")


def _parse_quietly(
    parser: argparse.ArgumentParser, arguments: Sequence[str], program: str
) -> argparse.Namespace:
    """``parser.parse_args``, its error as a :class:`LaunchError` (one line, no usage)."""

    def fail(message: str) -> NoReturn:
        raise LaunchError(f"{program}: {message}")

    parser.error = fail  # type: ignore[method-assign]
    for action in parser._actions:  # the subcommands' parsers too
        for child in getattr(action, "choices", None) or ():
            if isinstance(action.choices, dict):
                action.choices[child].error = fail
    return parser.parse_args(list(arguments))


#: What a node lacks without its calibration: parameter, endo-launch flag, effect.
_CALIBRATIONS = {"endo-photometric-correction": ("calibration_file", "--calibration",
                                                 "drops every frame"),
                 "endo-tracker-bridge": ("handeye_file", "--handeye",
                                         "publishes the marker pose as the camera pose")}


def _check_calibration_files(node: GraphProcess, values: Mapping[str, Any]) -> None:
    """Load the calibration a node will load at start, with the node's own loader.

    Raises:
        Endo3dError: the file does not load (or does not suit the node's
            parameters), with the node's message.
    """
    if node.name == "endo-photometric-correction" and values["calibration_file"]:
        from endo_calib.calibration import PhotometricCalibration
        from endo_calib.node import check_channel

        path = str(values["calibration_file"])
        check_channel(PhotometricCalibration.load(path), str(values["channel"]), path)
    elif node.name == "endo-tracker-bridge":
        from endo_tracker_bridge.handeye_file import HandEyeCalibration
        from endo_tracker_bridge.node import world_tracker_from_parameter

        if values["handeye_file"]:
            HandEyeCalibration.load(str(values["handeye_file"]))
        world_tracker_from_parameter(values["T_world_tracker"])


def check_nodes(nodes: Sequence[GraphProcess]) -> list[str]:
    """Check each node's start-up configuration as its start will, before anything starts.

    Per node: its ROS arguments through rcl (``--params-file`` that does not
    parse, a malformed ``-p``), every value it will start with against its
    parameter table (type, range, choices, a misspelt name:
    :func:`endo_io.parameters.check_start_values`) and the calibration files
    it will load, with its own loader. ``--dry-run`` runs the same checks.

    Returns:
        Warnings: a node without its calibration (it runs, but is of little use).

    Raises:
        LaunchError: one line naming the node and the cause.
    """
    from endo_bringup.params_file import node_parameters
    from endo_io.parameters import check_start_values, file_overrides, sections_for_no_node
    from endo_io.process import check_ros_arguments

    document: Any = None
    warnings = []
    for node in nodes:
        try:
            check_ros_arguments(node.command())
            if node.params_file and document is None:
                document = yaml.safe_load(Path(node.params_file).read_text()) or {}
            given = file_overrides(document, node.node_name, node.remaps.get("__ns", ""))
            # `-p NAME:=VALUE`: rcl reads VALUE as YAML
            given.update({name: yaml.safe_load(value) if value else value
                          for name, value in node.parameters.items()})  # fmt: skip
            values = check_start_values(node_parameters(node), given, node.node_name)
            _check_calibration_files(node, values)
        except (Endo3dError, OSError, yaml.YAMLError) as error:
            reason = yaml_error_line(error) if isinstance(error, yaml.YAMLError) else str(error)
            raise LaunchError(f"{node.name}: {reason}") from None
        if node.name in _CALIBRATIONS:
            name, flag, effect = _CALIBRATIONS[node.name]
            if not values[name]:
                warnings.append(f"no {name} for {node.name}: it {effect} (pass {flag} FILE, "
                                f"or set {name} in --params)")  # fmt: skip
    files = {node.params_file for node in nodes if node.params_file}
    fqns = [f"{node.remaps.get('__ns', '').rstrip('/')}/{node.node_name}" for node in nodes]
    for path in sorted(files):  # rcl ignores a section for no node without a word
        try:
            ignored = sections_for_no_node(document, fqns)
        except Endo3dError as error:
            raise LaunchError(f"--params {path}: {error}") from None
        warnings += [f"--params {path}: section {key} applies to none of the graph's nodes "
                     f"({', '.join(sorted(fqns))}): ignored" for key in ignored]  # fmt: skip
    return warnings


@dataclass
class _Echo:
    """Prints children's lines with their names in front, one line at a time."""

    stream: TextIO
    quiet: bool
    width: int
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, name: str, line: str) -> None:
        if self.quiet:
            return
        with self.lock:
            self.stream.write(f"[{name:<{self.width}}] {line}\n")
            self.stream.flush()

    def say(self, text: str) -> None:
        """A line of the launcher's own."""
        with self.lock:
            self.stream.write(f"{PROGRAM}: {text}\n")
            self.stream.flush()


@dataclass
class _Respawn:
    """Backoff state of one node."""

    delay_s: float = BACKOFF_FIRST_S
    started: float = 0.0
    due: float | None = None
    count: int = 0


class Launch:
    """A running graph: starts it, watches it, stops it.

    Args:
        plan: what to start.
        group: where the children run.
        echo: how lines are printed.
        respawn: restart nodes that die instead of stopping the graph.
    """

    def __init__(self, plan: LaunchPlan, group: ProcessGroup, echo: _Echo, *,
                 respawn: bool) -> None:  # fmt: skip
        self.plan = plan
        self.group = group
        self.echo = echo
        self.respawn = respawn
        self.stop_requested = threading.Event()
        self.state = {node.name: _Respawn() for node in plan.nodes}

    def start(self, process: GraphProcess) -> None:
        """Start one process of the plan, its output echoed."""
        self.group.start(process.name, process.command(), echo=self.echo, new_session=True,
                         nice=process.nice)
        if process.name in self.state:
            self.state[process.name].started = time.monotonic()

    def report_death(self, name: str) -> int | None:
        """Say that ``name`` exited, with its code and its last lines; the code."""
        code = self.group.processes[name].poll()
        lines = "\n".join("    " + x for x in self.group.tail(name, 10))
        self.echo.say(f"{name} exited with code {code}; its last lines:\n{lines}")
        return code

    def wait_until_up(self, timeout_s: float) -> None:
        """Wait until every node is spinning and SFS has its kernels.

        Raises:
            NodeFailedError: a node exited, or the timeout passed.
        """
        deadline = time.monotonic() + timeout_s
        while not self.stop_requested.is_set():
            waiting = []
            for node in self.plan.nodes:
                log = self.group.log(node.name)
                if not NODE_UP.search(log) or (
                    node.executable == "endo-sfs" and not KERNELS_READY.search(log)
                ):
                    waiting.append(node.name)
                if not self.group.running(node.name):
                    self.report_death(node.name)
                    raise NodeFailedError(f"{node.name} exited while starting")
            if not waiting:
                return
            if time.monotonic() > deadline:
                raise NodeFailedError(f"not up after {timeout_s:g} s: {', '.join(waiting)}")
            time.sleep(0.1)

    def watch(self, drain_timeout_s: float) -> int:
        """Watch the children until a stop request, the end of the source, or a failure.

        Returns:
            The launcher's exit code: 0, or 1 when a node or the source failed.
        """
        source_end: float | None = None
        last_size = -1
        while not self.stop_requested.wait(0.2):
            now = time.monotonic()
            for node in self.plan.nodes:
                state = self.state[node.name]
                if state.due is not None:
                    if now >= state.due:
                        state.due = None
                        state.count += 1
                        self.echo.say(f"restarting {node.name} (restart {state.count})")
                        self.start(node)
                    continue
                if self.group.running(node.name):
                    continue
                self.report_death(node.name)
                if not self.respawn:
                    self.echo.say("stopping the graph (--respawn restarts a node that dies)")
                    return 1
                if now - state.started > BACKOFF_RESET_S:
                    state.delay_s = BACKOFF_FIRST_S
                state.due = now + state.delay_s
                self.echo.say(f"restarting {node.name} in {state.delay_s:g} s")
                state.delay_s = min(state.delay_s * BACKOFF_FACTOR, BACKOFF_MAX_S)
            for extra in (self.plan.source, self.plan.recorder):
                if extra is None or self.group.running(extra.name):
                    continue
                code = self.group.processes[extra.name].poll()
                if extra is self.plan.source and self.plan.ends and code == 0:
                    if source_end is None:
                        self.echo.say("the recording has been played; waiting for the outputs")
                        source_end = now
                    continue
                self.report_death(extra.name)
                return 1
            if source_end is not None:
                # The run ends once the outputs stop growing (or after the drain timeout).
                size = self._recording_size()
                if size != last_size:
                    last_size, quiet_since = size, now
                if now - source_end > drain_timeout_s or (
                    now - quiet_since > DRAIN_QUIET_S and now - source_end > DRAIN_QUIET_S
                ):
                    return 0
        return 0

    def _recording_size(self) -> int:
        recorder = self.plan.recorder
        if recorder is None:
            return 0
        path = Path(recorder.arguments[recorder.arguments.index("-o") + 1])
        return path.stat().st_size if path.exists() else 0


def _child_environment(log_dir: Path) -> dict[str, str]:
    env = dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONUNBUFFERED="1")
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    configure_large_frames(env)  # once here, so that every child names the same profile
    return env


def _refuse_a_shared_domain(plan: LaunchPlan) -> None:
    """Raise when this ROS domain already has our nodes or publishers on our topics.

    Raises:
        DomainInUseError: one line naming what was found and the domain.
    """
    from endo_bringup.domain_probe import graph_conflicts

    ours = [p for p in (*plan.nodes, plan.source) if p is not None]
    topics = sorted({t for p in ours for t in p.publishes})
    names = []
    for node in plan.nodes:
        namespace = node.remaps.get("__ns", "")
        names.append(f"{namespace}/{node.node_name}")
    found = graph_conflicts(topics, names)
    if found:
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        raise DomainInUseError(
            f"ROS domain {domain} already has an endo3d graph: {', '.join(found)}; stop it, "
            "choose another ROS_DOMAIN_ID or --namespace, or pass --allow-shared-domain"
        )


def output_counts(plan: LaunchPlan, played: dict[str, int], recording: Path
                  ) -> tuple[list[str], list[str]]:  # fmt: skip
    """Per node output, messages out against what came in, from the recording.

    The counting is the demo's (:func:`endo_bringup.graph.stage_counts`).

    Args:
        plan: a replay's plan with a recorder.
        played: bag topic -> messages played, in the order of the source's ``--topics``.
        recording: the finalised recording.

    Returns:
        (one line per output, one line per node output that got nothing at all
        although its input got messages).
    """
    assert plan.source is not None and plan.recorder is not None
    run = GraphRun(recording, played, {}, Path(), 0.0,
                   [plan.recorder, *plan.nodes, replace(plan.source, name=PLAYER)])  # fmt: skip
    lines, missing = [], []
    for row in stage_counts(run, count_messages(recording)):
        if row.stage == PLAYER:
            continue
        lines.append(f"{row.stage} {row.topic}: {row.count_out} from {row.count_in} in")
        if row.count_out == 0 and row.count_in > 0:
            missing.append(f"{row.stage} published nothing on {row.topic} "
                           f"({row.count_in} messages in)")  # fmt: skip
    return lines, missing


def run(options: argparse.Namespace) -> int:
    """Start the plan of ``options``, watch it, stop it; the exit code."""
    if options.log_dir is None and not options.dry_run:
        import tempfile

        options.log_dir = Path(tempfile.mkdtemp(prefix="endo-launch-"))
    plan = plan_launch(options)
    if options.dry_run:
        for warning in plan.warnings:  # what a start would say, on stderr
            print(f"endo-launch: warning: {warning}", file=sys.stderr)
        for process in plan.processes:
            print(" ".join(process.command()))
        return 0
    if options.record is not None and options.record.exists():
        raise LaunchError(f"{options.record} exists; endo-record does not overwrite")
    if not options.allow_shared_domain:
        _refuse_a_shared_domain(plan)
    if plan.camera_file is not None:
        Path(options.log_dir).mkdir(parents=True, exist_ok=True)
        write_camera_file(options.bag, plan.camera_file)
    width = max(len(p.name) for p in plan.processes)
    echo = _Echo(sys.stdout, options.quiet, width)
    echo.say(f"logs in {options.log_dir}")
    for warning in plan.warnings:
        echo.say("warning: " + warning)
    group = ProcessGroup(_child_environment(options.log_dir), options.log_dir, grace_s=15.0)
    launch = Launch(plan, group, echo, respawn=options.respawn)

    def on_signal(signum: int, _frame: object) -> None:
        echo.say(f"{signal.Signals(signum).name}: stopping the graph")
        launch.stop_requested.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    code = 0
    try:
        with group:
            if plan.recorder is not None:
                launch.start(plan.recorder)
            for node in plan.nodes:
                launch.start(node)
            launch.wait_until_up(options.startup_timeout)
            if launch.stop_requested.is_set():
                return 0
            echo.say("every node is up" + (f"; starting {plan.source.executable}"
                                           if plan.source else ""))  # fmt: skip
            if plan.source is not None:
                launch.start(plan.source)
            code = launch.watch(options.drain_timeout)
            # Source first (no new input), nodes next, the recorder last (it finalises).
            order = [p.name for p in (plan.source, *plan.nodes) if p is not None]
            group.stop(order)
            if plan.recorder is not None:
                group.stop([plan.recorder.name], timeout_s=30.0)
                if group.return_codes.get(plan.recorder.name) not in (0,):
                    echo.say(f"{plan.recorder.name} did not finish cleanly")
                    code = code or 1
                else:
                    echo.say(f"recorded {options.record}")
                    if plan.ends:
                        code = _report_outputs(plan, options, echo) or code
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return code


def _report_outputs(plan: LaunchPlan, options: argparse.Namespace, echo: _Echo) -> int:
    """Print each node output's count against frames played; 1 when one output got nothing."""
    assert plan.source is not None
    arguments = plan.source.arguments
    bag_topics = arguments[arguments.index("--topics") + 1:arguments.index("--rate")]
    with BagReader(options.bag) as reader:
        played = {t: reader.topics[t].message_count for t in bag_topics}
    lines, missing = output_counts(plan, played, options.record)
    echo.say(f"outputs ({played[IMAGE_RAW]} frames played):")
    for line in lines:
        echo.say("  " + line)
    for line in missing:
        echo.say("warning: " + line)
    if missing:
        echo.say("the graph gave no output on some topics: exit 1 (see the logs)")
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``endo-launch``."""
    parser = build_parser()
    options = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if options.write_params is not None:
        try:  # it may be the user's edited file (or, misnamed, another calibration)
            refuse_existing(options.write_params, overwrite=options.overwrite)
        except Endo3dError as error:
            return report_error(PROGRAM, error)
        print(write_params(options.write_params))
        return 0
    if options.preset is None:
        parser.print_usage(sys.stderr)
        print(f"{PROGRAM}: choose a preset: live, replay BAG or sim", file=sys.stderr)
        return 2
    try:
        return run(options)
    except NodeFailedError as error:
        print(f"{PROGRAM}: {error}", file=sys.stderr)
        return 1
    except Endo3dError as error:
        return report_error(PROGRAM, error)


if __name__ == "__main__":
    sys.exit(main())
