"""``endo-demo``: the endo3d graph as it exists so far, on the sample bags, over DDS.

Three parts, every one through the command-line tools a user runs, each tool
in its own OS process, talking to the others over loopback DDS only:

1. Round trip (the spine): a bag is played by ``endo-replay`` and recorded
   by ``endo-record``, and the recording is compared with the input message
   for message. The bag is ``bags/phantom_*.mcap`` if there is one, else the
   first ``bags/*.mcap``, else a small synthetic bag written here (two
   seconds of 160x120 rgb8 endoscope frames with camera info, a tracked tool
   pose and a light level).
2. Offline calibrations: ``endo-calibrate`` on ``bags/graycard.mcap`` and
   ``endo-handeye`` on ``bags/handeye.mcap``, scored against the ground-truth
   files beside the bags.
3. Live graph (:mod:`endo_bringup.graph`): ``endo-photometric-correction``,
   ``endo-sfs``, ``endo-tracker-bridge`` and ``endo-flow`` with those
   calibrations, ``endo-record`` of their outputs, the camera_info and the
   ground truth, and ``endo-replay`` of ``bags/phantom_colon.mcap`` into
   them; the recording is scored by :func:`endo_process.accuracy.score_recording`
   (the figures ``endo-process`` prints: relative, metric and oracle-scaled
   depth, cloud RMS, scale against the oracle, camera pose error) and judged
   by :mod:`endo_bringup.acceptance` (every frame kept, the accuracy bars).

Parts 2 and 3 need the three sample bags with their ground truth; without
them (or with ``--round-trip-only``) only part 1 runs. Outputs go to a new
temporary directory, or to ``--output-dir`` (``make demo``: ``out/``, git-ignored),
where the files of a previous demo run (:data:`DEMO_OUTPUTS`) are replaced.

Exit status 0 (``endo-demo: OK``) when every played message came back with
the same bytes, every stage of the graph kept every frame at the playback
rate and the live recording meets the accuracy bars; 1 otherwise, with what
fell short printed plainly; 2 on bad input (a
missing ``--bag``), with one line on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import signal
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import yaml
from std_msgs.msg import Float32

from endo_bringup.dds_profile import with_large_frame_profile
from endo_bringup.graph import (
    PLAYER,
    RECORDER,
    GraphError,
    GraphRun,
    GraphSettings,
    OfflineStep,
    bag_seconds,
    ground_truth_of,
    node_outputs,
    play_and_record,
    recorder_lost,
    recorder_process,
    replay_process,
    run_live_graph,
    run_offline_calibrations,
    stage_counts,
)
from endo_bringup.graph_monitor import (
    GraphFigures,
    GraphMonitor,
    ProcessSampler,
    graph_figures,
    planned_graph,
    stage_lines,
)
from endo_bringup.process_group import ProcessGroup
from endo_io import topics as topic_names
from endo_io.bag import BagReader, BagWriter, message_class, msgtype_of, serialize
from endo_io.bag.serde import dds_aligned
from endo_io.bag.streams import count_messages
from endo_io.camera import CameraModel
from endo_io.cli import exit_on_error
from endo_io.errors import Endo3dError
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose
from endo_sim.errors import GroundTruthError

if TYPE_CHECKING:
    from endo_bringup.live_vs_offline import OfflineRun
    from endo_process.accuracy import Accuracy
    from endo_process.evaluation import PoseComparison
    from endo_sfs.evaluation import DepthError

#: DDS domain of the demo when the environment gives none (as in the Makefile).
DEMO_DOMAIN_ID = "41"
SYNTHETIC_START_NS = 1_763_800_000_000_000_000
REPO_ROOT = Path(__file__).resolve().parents[3]
#: The files a demo run writes into its output directory (a rerun replaces them;
#: nothing else there is touched).
DEMO_OUTPUTS = (
    "round_trip.mcap", "graph.mcap", "offline.mcap", "report.png", "summary.json",
    "offline_summary.json", "endo3d.yaml", "photometric.yaml", "handeye.yaml",
)  # fmt: skip


# --------------------------------------------------------------------------
# The input bag


def find_bag(search_dirs: list[Path]) -> Path | None:
    """``phantom_*.mcap`` in the first directory that has one, else the first ``*.mcap``."""
    for pattern in ("phantom_*.mcap", "*.mcap"):
        for directory in search_dirs:
            found = sorted(directory.glob(pattern))
            if found:
                return found[0]
    return None


def write_synthetic_bag(path: Path, seconds: float = 2.0) -> None:
    """A small endoscope-like recording.

    160x120 rgb8 frames at 30 Hz (a lit, vignetted tissue-like texture drifting
    across the view), the matching CameraInfo, a tool PoseStamped at 60 Hz on a
    helix, and a std_msgs/Float32 light level at 10 Hz. Payloads are stored as
    ``ros2 bag record`` stores them (padded to 4 bytes, as DDS delivers them).
    """
    width, height = 160, 120
    camera = CameraModel.pinhole(width, height, fx=140.0, fy=140.0, cx=79.5, cy=59.5)
    rng = np.random.default_rng(3)
    noise = rng.random((height * 2, width * 2)).astype(np.float32)
    blurred = cv2.blur(noise, (9, 9))  # smoother, tissue-like
    texture = (blurred - blurred.min()) / (blurred.max() - blurred.min())
    y, x = np.mgrid[0:height, 0:width]
    vignette = np.clip(1.0 - ((x - 79.5) ** 2 + (y - 59.5) ** 2) / 90.0**2, 0.0, 1.0)
    tint = np.array([1.0, 0.55, 0.45], np.float32)
    events: list[tuple[int, str, object]] = []
    for i in range(round(30 * seconds)):
        t = SYNTHETIC_START_NS + round(i * 1e9 / 30)
        patch = texture[i : i + height, 2 * i % width : 2 * i % width + width]
        shade = (0.35 + 0.65 * patch) * vignette
        pixels = (255 * np.clip(shade[..., None] * tint, 0, 1)).astype(np.uint8)
        events.append(
            (t, topic_names.IMAGE_RAW, array_to_image(pixels, "rgb8", t, camera.frame_id))
        )
        events.append((t + 1_000_000, topic_names.CAMERA_INFO, camera.to_camera_info(t)))
    for i in range(round(60 * seconds)):
        t = SYNTHETIC_START_NS + round(i * 1e9 / 60) + 2_000_000
        angle = 0.1 * i
        transform = np.eye(4)
        transform[:3, :3] = [
            [np.cos(angle), -np.sin(angle), 0],
            [np.sin(angle), np.cos(angle), 0],
            [0, 0, 1],
        ]
        transform[:3, 3] = [0.01 * np.cos(angle), 0.01 * np.sin(angle), 0.0005 * i]
        events.append((t, "/tool/pose", matrix_to_pose(transform, t, "tracker")))
    for i in range(round(10 * seconds)):
        t = SYNTHETIC_START_NS + i * 100_000_000 + 3_000_000
        events.append((t, "/light/level", Float32(data=0.6 + 0.02 * np.sin(i))))
    added: set[str] = set()
    with BagWriter(path) as writer:
        for t, topic, msg in sorted(events, key=lambda e: e[0]):
            if topic not in added:
                writer.add_topic(topic, msgtype_of(msg))
                added.add(topic)
            writer.write(topic, serialize(msg), t)


# --------------------------------------------------------------------------
# Comparison


@dataclass
class TopicComparison:
    """One topic of the round trip."""

    msgtype: str
    sent: int = 0
    received: int = 0
    identical: int = 0
    padding_only: int = 0
    sent_bytes: int = 0

    @property
    def equal(self) -> bool:
        """Every message came back, in order, with the same bytes (up to DDS padding)."""
        return self.sent == self.received == self.identical + self.padding_only


@dataclass
class RoundTrip:
    """Result of comparing a recording with the bag that was played."""

    topics: dict[str, TopicComparison] = field(default_factory=dict)
    extra_topics: list[str] = field(default_factory=list)

    @property
    def equal(self) -> bool:
        """True when every topic is equal and nothing else was recorded."""
        return not self.extra_topics and all(t.equal for t in self.topics.values())


def compare_bags(sent_path: Path, received_path: Path, topics: list[str]) -> RoundTrip:
    """Compare, per topic and in order, the messages of ``topics`` in two bags.

    A message is identical when its bytes are; ``padding_only`` counts those
    that differ only by the zero padding DDS adds up to a 4-byte boundary
    (bags written by rclpy serialisation rather than recorded lack it).
    """
    sent: dict[str, list[bytes]] = defaultdict(list)
    received: dict[str, list[bytes]] = defaultdict(list)
    result = RoundTrip()
    with BagReader(sent_path) as reader:
        for name in topics:
            result.topics[name] = TopicComparison(reader.topics[name].msgtype)
        for message in reader.messages(topics=topics):
            sent[message.topic].append(message.data)
    with BagReader(received_path) as reader:
        result.extra_topics = sorted(set(reader.topics) - set(topics))
        for message in reader.messages(topics=topics):
            received[message.topic].append(message.data)
    for name, comparison in result.topics.items():
        comparison.sent, comparison.received = len(sent[name]), len(received[name])
        comparison.sent_bytes = sum(map(len, sent[name]))
        for a, b in zip(sent[name], received[name], strict=False):
            if a == b:
                comparison.identical += 1
            elif dds_aligned(a) == dds_aligned(b):
                comparison.padding_only += 1
    return result


# --------------------------------------------------------------------------
# Running the two processes


def playable_topics(bag: Path) -> tuple[list[str], list[str]]:
    """(topics whose type is installed, topics that cannot be published here)."""
    playable, skipped = [], []
    with BagReader(bag) as reader:
        for name, info in sorted(reader.topics.items()):
            try:
                message_class(info.msgtype)
            except Endo3dError:
                skipped.append(name)
                continue
            playable.append(name)
    return playable, skipped


def run_round_trip(
    bag: Path, output: Path, rate: float, env: dict[str, str]
) -> tuple[int | None, int | None, str]:
    """Record ``bag`` played over DDS into ``output``.

    The recorder and the player are :func:`~endo_bringup.graph.recorder_process`
    and :func:`~endo_bringup.graph.replay_process`, run in a
    :class:`~endo_bringup.process_group.ProcessGroup` like the live graph; their
    logs go to ``<output dir>/logs/round_trip``. Returns (endo-replay exit
    status, endo-record exit status, both logs); a status is None for a
    process that had to be killed.
    """
    topics, _ = playable_topics(bag)
    with BagReader(bag) as reader:
        expected = {t: reader.topics[t].message_count for t in topics}
    with ProcessGroup(env, output.parent / "logs" / "round_trip") as group:
        recorder = recorder_process(topics, output)
        group.start(recorder.name, recorder.command(), nice=recorder.nice)
        play_and_record(
            group,
            replay_process(bag, topics, rate),
            output,
            expected,
            play_timeout_s=60.0 + bag_seconds(bag) / rate,
            drain_timeout_s=15.0,
        )
    codes = group.return_codes
    return codes[PLAYER], codes[RECORDER], group.log(PLAYER) + group.log(RECORDER)


# --------------------------------------------------------------------------
# The graph on the sample bags

#: The sample bags the graph part needs, with their ground truth beside them.
GRAYCARD_BAG, HANDEYE_BAG, PHANTOM_BAG = "graycard.mcap", "handeye.mcap", "phantom_colon.mcap"
SAMPLE_BAGS = (GRAYCARD_BAG, HANDEYE_BAG, PHANTOM_BAG)
#: Playback speed of the phantom bag into the graph: 30 fps × 0.25 = 7.5 frames/s, the
#: fastest rate at which the whole graph kept every frame in every pass of
#: bench/bench_graph.py --sweep-only on the slowest 2-core host measured
#: (docs/benchmarks.md, endo-demo's playback rate; 2026-12-03 18:02, a host 2-3x
#: slower for the solver than session 15's, load 1.3-4.0: 0.25x two of two passes,
#: 0.35x none, 0.5x none; on session 15's host 0.5x kept every frame four of four,
#: and the demo played at 0.5x in session 15-16). SFS at full resolution is the limit.
#: A run on a loaded machine skips frames; the demo prints what each stage kept and
#: skipped (endo_bringup.graph_monitor, the bench's code) and says NOT OK.
GRAPH_RATE = 0.25
#: The SFS node's solve_scale in the demo graph (full resolution).
GRAPH_SOLVE_SCALE = 1.0


@dataclass
class CalibrationScores:
    """The offline calibrations against the simulator's truth.

    response_residual_dn: endo-calibrate's fit residual RMS (raw values);
    inverse_response_max_error: max |g − g_true| over raw values 5–250, fraction
    of full scale; handeye_*: T_marker_camera error (mm, deg), clock offset
    error (ms), the fit's residuals and views.
    """

    response_residual_dn: float
    inverse_response_max_error: float
    handeye_translation_mm: float
    handeye_rotation_deg: float
    time_offset_error_ms: float
    handeye_residuals: dict[str, float]
    handeye_views: tuple[int, int]


@dataclass
class GraphReport:
    """Everything the graph part did and measured.

    counts: messages per recorded topic; accuracy: the recording scored
    against the ground truth (:func:`endo_process.accuracy.score_recording`);
    depth_errors: stamp (ns) -> median-scaled error of each relative depth
    frame that has a ground truth, and poses: the bridge's /endoscope/pose
    against /ground_truth/camera_pose (both from ``accuracy``); figures:
    frames, skips, rates, latency, CPU and RSS of the run as
    bench/bench_graph.py measures them (:mod:`endo_bringup.graph_monitor`).
    """

    calibrate: OfflineStep
    handeye: OfflineStep
    scores: CalibrationScores | None
    run: GraphRun | None
    counts: dict[str, int] = field(default_factory=dict)
    depth_errors: dict[int, DepthError] = field(default_factory=dict)
    poses: PoseComparison | None = None
    accuracy: Accuracy | None = None
    offline: OfflineRun | None = None
    figures: GraphFigures | None = None
    dds_note: str = ""
    error: str = ""

    def shortfalls(self) -> list[str]:
        """What kept a completed run from OK: frames a stage dropped, accuracy bars missed."""
        from endo_bringup.acceptance import accuracy_shortfalls, frame_shortfalls

        if self.run is None:
            return []
        per_frame = {t for p in self.run.processes for t in p.per_frame_outputs}
        skipped = {} if self.figures is None else {s.stage: s.skipped for s in self.figures.stages}
        problems = frame_shortfalls(stage_counts(self.run, self.counts), per_frame, skipped)
        lost = recorder_lost(self.run.log_dir)
        if lost:  # the frames above missing from the recording, not from the stage
            problems.append(f"the recorder {lost}")
        if self.accuracy is not None:
            problems += accuracy_shortfalls(self.accuracy)
        if not self.depth_errors and self._skipped_frames():
            problems.append(
                "no depth frame has a ground truth with the same stamp (the stages skipped "
                "stale frames: slower than the playback)"
            )
        return problems

    def _skipped_frames(self) -> bool:
        """Whether a stage skipped frames for newer ones (so truth frames may be missing)."""
        return self.figures is not None and any(s.skipped for s in self.figures.stages)

    def failures(self) -> list[str]:
        """Why this run counts as failed (empty when it did not)."""
        problems = [
            f"{step.argv[0].rsplit('/', 1)[-1]} exited {step.return_code}"
            for step in (self.calibrate, self.handeye)
            if step.return_code != 0
        ]
        if self.error:
            problems.append(self.error)
        if self.run is not None:
            problems += [
                f"{name} exited {'(killed)' if code is None else code}"
                for name, code in self.run.return_codes.items()
                if code != 0
            ]
            problems += [
                f"no message on {topic}"
                for topic in node_outputs(self.run.processes)
                if self.counts.get(topic, 0) == 0
            ]
            if not self.depth_errors and not self._skipped_frames():
                problems.append("no depth frame has a ground truth with the same stamp")
            if self.poses is None or self.poses.compared == 0:
                problems.append("no camera pose could be compared with the ground truth")
        return problems


def score_calibrations(
    photometric: Path, handeye: Path, graycard_bag: Path, handeye_bag: Path
) -> CalibrationScores:
    """Compare photometric.yaml and handeye.yaml with the ground truth beside the bags."""
    # The graph's packages are imported only when the graph part runs, so the
    # round trip works whatever state they are in.
    from endo_calib.calibration import PhotometricCalibration
    from endo_process import evaluation
    from endo_tracker_bridge.handeye_file import HandEyeCalibration

    calibration = PhotometricCalibration.load(photometric)
    fit = yaml.safe_load(photometric.read_text())["fit"]["channels"]
    true_response = np.load(graycard_bag.with_name(graycard_bag.stem + ".inverse_response.npy"))
    hand_eye = HandEyeCalibration.load(handeye)
    tracker = ground_truth_of(handeye_bag)["tracker"]
    translation_mm, rotation_deg = evaluation.handeye_error(
        hand_eye.T_marker_camera,
        np.asarray(tracker["T_marker_camera"], dtype=np.float64),  # type: ignore[index]
    )
    return CalibrationScores(
        response_residual_dn=float(max(c["residual_rms_dn"] for c in fit.values())),
        inverse_response_max_error=evaluation.inverse_response_error(
            np.asarray(calibration.inverse_response).reshape(len(true_response), -1)[:, 0],
            true_response,
        ),
        handeye_translation_mm=translation_mm,
        handeye_rotation_deg=rotation_deg,
        time_offset_error_ms=hand_eye.time_offset_ns * 1e-6 - float(tracker["latency_s"]) * 1e3,  # type: ignore[index]
        handeye_residuals=dict(hand_eye.residuals),
        handeye_views=(hand_eye.views_used, hand_eye.views_total),
    )


def graph_settings_for(bag: Path, rate: float, solve_scale: float) -> GraphSettings:
    """Settings of the live graph for a simulated bag.

    The SFS roughness is the simulator's Oren–Nayar σ (a user would take it
    from tissue measurements). T_world_tracker is the simulator's
    tracker-to-world registration, so that /endoscope/pose lands in the
    frame of /ground_truth/camera_pose; a real setup gets it from a
    registration step (not part of endo3d yet).
    """
    truth = ground_truth_of(bag)
    T_tracker_world = np.asarray(truth["tracker"]["T_tracker_world"], dtype=np.float64)  # type: ignore[index]
    return GraphSettings(
        rate=rate,
        model="near_light",
        roughness=float(truth["photometry"]["roughness_rad"]),  # type: ignore[index]
        solve_scale=solve_scale,
        T_world_tracker=np.linalg.inv(T_tracker_world),
    )


def run_graph_stage(
    bags_dir: Path,
    out_dir: Path,
    env: dict[str, str],
    rate: float = GRAPH_RATE,
    solve_scale: float = GRAPH_SOLVE_SCALE,
    *,
    node_parameters: Mapping[str, Mapping[str, str]] | None = None,
) -> GraphReport:
    """Offline calibrations, then the live graph on the phantom bag, then the scores.

    bags_dir holds graycard.mcap, handeye.mcap and phantom_colon.mcap with
    their ground truth; everything is written under ``out_dir``. Every child
    process has ended when this returns. node_parameters: extra ROS
    parameters per process name (:attr:`GraphSettings.node_parameters`).
    """
    # endo_process scores endo-process's output the same way; it depends on
    # endo_bringup, so it is imported here, when the graph part runs.
    from endo_process.accuracy import score_recording

    graycard, handeye_bag, phantom = (bags_dir / name for name in SAMPLE_BAGS)
    calibrate, handeye = run_offline_calibrations(graycard, handeye_bag, out_dir, env)
    report = GraphReport(calibrate=calibrate, handeye=handeye, scores=None, run=None)
    if calibrate.return_code != 0 or handeye.return_code != 0:
        return report
    report.scores = score_calibrations(calibrate.result, handeye.result, graycard, handeye_bag)
    graph_env, report.dds_note = with_large_frame_profile(env, out_dir)
    settings = dataclasses.replace(graph_settings_for(phantom, rate, solve_scale),
                                   node_parameters=dict(node_parameters or {}))
    processes = planned_graph(phantom, calibrate.result, handeye.result, out_dir, settings)
    # the replay starts once the monitor's subscription matched too; the monitor times
    # the outputs from the recording (it receives none of the images itself)
    settings = dataclasses.replace(
        settings, listeners=GraphMonitor.played_listeners(processes, "recording"))
    try:
        with GraphMonitor(processes, graph_env, "recording") as monitor, \
                ProcessSampler(processes) as sampler:
            report.run = run_live_graph(
                phantom, calibrate.result, handeye.result, out_dir, graph_env, settings
            )
        report.figures = graph_figures(report.run.processes, monitor, sampler,
                                       report.run.played, report.run.recording)
    except (GraphError, GroundTruthError) as error:
        report.error = str(error)
        return report
    recording = report.run.recording
    report.counts = dict(count_messages(recording))
    report.accuracy = score_recording(recording)
    report.depth_errors = report.accuracy.relative
    report.poses = report.accuracy.poses
    return report


def print_graph_report(report: GraphReport, rate: float) -> None:
    """The graph part's summary: what ran, frames per stage, errors against the truth."""
    for step in (report.calibrate, report.handeye):
        name = step.argv[0].rsplit("/", 1)[-1]
        status = "ok" if step.return_code == 0 else f"FAILED (exit {step.return_code})"
        print(f"  {name:<16} {status} in {step.seconds:.1f} s -> {step.result}")
        if step.return_code != 0:
            print("    " + step.output.strip().replace("\n", "\n    "))
    if report.dds_note:
        print(f"  {report.dds_note}")
    run = report.run
    if run is None and report.error:
        print(f"  live graph: FAILED: {report.error}")
    if run is not None:
        print(
            f"  live graph: {PHANTOM_BAG} at {rate:g}x, {run.seconds:.1f} s; one log per process "
            f"(command line first) in {run.log_dir}"
        )
        per_frame = {t for p in run.processes for t in p.per_frame_outputs}
        # "in-out", not "dropped": the monitor's table below has the nodes' own
        # "dropped" (bad input) beside "skipped" (stale frames), which make up in-out.
        print(f"    {'stage':<28} {'output topic':<30} {'in':>5} {'out':>5} {'in-out':>7}  exit")
        for row in stage_counts(run, report.counts):
            code = "?" if row.return_code is None else row.return_code
            # depth and cloud start once the scale converged, the map is periodic
            missing = row.count_in - row.count_out if row.topic in per_frame else "-"
            print(
                f"    {row.stage:<28} {row.topic:<30} {row.count_in:>5} {row.count_out:>5} "
                f"{missing:>7}  {code}"
            )
    if report.figures is not None:
        print("    as bench/bench_graph.py measures it (endo_bringup.graph_monitor):")
        for line in stage_lines(report.figures):
            print(f"      {line}")
    rows: list[tuple[str, str]] = []
    scores = report.scores
    if scores is not None:
        r = scores.handeye_residuals
        rows += [
            ("photometric fit residual", f"{scores.response_residual_dn:.3f} DN RMS"),
            (
                "inverse response vs truth",
                f"max error {100 * scores.inverse_response_max_error:.2f} % of full scale "
                "(raw values 5-250)",
            ),
            (
                "hand-eye fit residuals",
                f"{r.get('translation_rms_mm', float('nan')):.3f} mm, "
                f"{r.get('rotation_rms_deg', float('nan')):.3f} deg RMS "
                f"({scores.handeye_views[0]}/{scores.handeye_views[1]} views)",
            ),
            (
                "hand-eye vs truth",
                f"{scores.handeye_translation_mm:.3f} mm, {scores.handeye_rotation_deg:.3f} deg; "
                f"clock offset {scores.time_offset_error_ms:+.3f} ms",
            ),
        ]
    if report.accuracy is not None:
        from endo_process.summary import accuracy_rows

        rows += accuracy_rows(report.accuracy)
    poses = report.poses
    if rows:
        width = max(40, *(len(label) for label, _ in rows))
        print(f"    {'measured':<{width}} value")
        for label, value in rows:
            print(f"    {label:<{width}} {value}")
    if report.depth_errors:
        print(
            "    relative depth: each frame scaled by median(true) / median(estimate); oracle: "
            "one scale for the whole sequence, exp(median of ln(true / estimate)) over every "
            "pixel; the scale is judged from 1 s after the camera's first 2 mm; metric depth "
            "and the cloud: "
            "endo-flow's own scale from the tracker poses, no scaling by the truth."
        )
    if poses is not None and poses.compared:
        print(
            "    camera pose: /endoscope/pose interpolated (endo_io.pose.interpolate_transforms) "
            f"at each /ground_truth/camera_pose stamp; {poses.missing} stamp(s) fall outside the "
            "tracker stream or in a dropout."
        )
    if run is not None:
        shortfalls = report.shortfalls()
        if shortfalls:
            print("  fell short of OK:")
            for problem in shortfalls:
                print(f"    - {problem}")
        else:
            print("  every stage kept every frame and the accuracy bars hold")
        print(f"  recording: {run.recording}")
        print(
            f"  look at it: open {run.recording} in Foxglove (layout config/foxglove/endo3d.json),"
            f" or play it with `endo-replay {run.recording} --loop` beside `endo-foxglove` or "
            "RViz2 on the same ROS_DOMAIN_ID"
        )
        if topic_names.TF not in report.counts:
            # pip-only the bridge cannot publish /tf (no tf2_msgs wheel, docs/viewers.md)
            print(
                "    it holds no /tf (no tf2_msgs here): the 3D view shows the world cloud, map "
                "and pose but cannot place the camera's images; endo-process outputs "
                "(offline.mcap) carry /tf"
            )


def run_offline_stage(
    report: GraphReport,
    bag: Path,
    out_dir: Path,
    env: dict[str, str],
    options: argparse.Namespace,
) -> tuple[list[str], list[str]]:
    """endo-process on the bag the live graph played; prints live vs offline.

    Returns (failures: endo-process did not finish, shortfalls: the bars its
    output misses, each prefixed "offline:"). Keeps the run in ``report.offline``.
    """
    from endo_bringup.acceptance import accuracy_shortfalls
    from endo_bringup.live_vs_offline import print_side_by_side, run_endo_process

    print(f"endo-demo: [4/4] endo-process on {bag} (no DDS), the same cores offline")
    offline = run_endo_process(
        bag, report.calibrate.result, report.handeye.result, out_dir, env, options.solve_scale
    )
    report.offline = offline
    print_side_by_side(offline, report.accuracy, report.counts.get(topic_names.SCALE, 0))
    if offline.step.return_code != 0 or offline.accuracy is None:
        return [f"endo-process exited {offline.step.return_code}"], []
    shortfalls = [f"offline: {problem}" for problem in accuracy_shortfalls(offline.accuracy)]
    for problem in shortfalls:
        print(f"    - {problem}")
    return [], shortfalls


def write_demo_summary(
    path: Path, report: GraphReport, problems: list[str], options: argparse.Namespace
) -> None:
    """out/summary.json: settings, stage counts, calibration, live and offline figures."""
    from endo_bringup.live_vs_offline import write_summary

    run = report.run
    stages = (
        [] if run is None else [dataclasses.asdict(row) for row in stage_counts(run, report.counts)]
    )
    write_summary(
        path,
        ok=not problems,
        problems=problems,
        settings={"playback_rate": options.graph_rate, "solve_scale": options.solve_scale},
        stages=stages,
        calibration=None if report.scores is None else dataclasses.asdict(report.scores),
        live=report.accuracy,
        offline=report.offline,
        timing=None if report.figures is None else report.figures.document(),
    )


def sample_bags_dir(search_dirs: list[Path]) -> Path | None:
    """The first directory holding the three sample bags and the ground truth they need."""
    for directory in search_dirs:
        needed = [directory / name for name in SAMPLE_BAGS]
        needed += [bag.with_name(bag.stem + ".ground_truth.yaml") for bag in needed]
        needed.append(directory / GRAYCARD_BAG.replace(".mcap", ".inverse_response.npy"))
        if all(path.exists() for path in needed):
            return directory
    return None


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-demo`` command line."""
    parser = argparse.ArgumentParser(
        prog="endo-demo",
        description="Round trip replay/record, offline calibrations, and the live endo3d graph "
        "on the sample bags, every tool in its own process over DDS.",
    )
    parser.add_argument("--bag", type=Path, default=None, help="bag of the round trip")
    parser.add_argument(
        "--output-dir", type=Path, default=None, help="where to write (default: a new temp dir)"
    )
    parser.add_argument(
        "--rate", type=float, default=1.0, help="round-trip playback speed (default 1)"
    )
    parser.add_argument(
        "--graph-rate",
        type=float,
        default=GRAPH_RATE,
        help=f"playback speed of the phantom bag into the graph (default {GRAPH_RATE:g}: "
        f"{30 * GRAPH_RATE:g} frames/s, the fastest at which the slowest 2-core host measured "
        "kept every frame at full resolution; on a loaded one stages skip stale frames, and "
        "the demo says how many: bench/bench_graph.py --sweep-only measures the rate for a "
        "machine)",
    )
    parser.add_argument(
        "--solve-scale",
        type=float,
        default=GRAPH_SOLVE_SCALE,
        help=f"the SFS node's solve_scale (default {GRAPH_SOLVE_SCALE:g})",
    )
    parser.add_argument(
        "--round-trip-only", action="store_true", help="skip the calibrations and the graph"
    )
    parser.add_argument(
        "--no-offline",
        action="store_true",
        help="skip endo-process on the phantom bag (the live vs offline comparison, report.png)",
    )
    return parser


#: The SFS node's solve_scale range (its parameter's).
SOLVE_SCALE_RANGE = (0.1, 1.0)


def check_options(options: argparse.Namespace) -> None:
    """Refuse values no run can use, before anything starts.

    Raises:
        Endo3dError: a playback rate that is not > 0 (a finite number), or a
            solve scale outside the SFS node's range.
    """
    for flag, value in (("--rate", options.rate), ("--graph-rate", options.graph_rate)):
        if not (math.isfinite(value) and value > 0.0):
            raise Endo3dError(f"{flag} must be a playback speed > 0, got {value:g}")
    low, high = SOLVE_SCALE_RANGE
    if not low <= options.solve_scale <= high:
        raise Endo3dError(f"--solve-scale must be in [{low:g}, {high:g}], got "
                          f"{options.solve_scale:g}")


def run_round_trip_stage(bag: Path | None, out_dir: Path, rate: float, env: dict[str, str]) -> bool:
    """Part 1: replay ``bag`` (or the default one), record it, compare; print the table."""
    bag = bag or find_bag(list(dict.fromkeys([Path.cwd() / "bags", REPO_ROOT / "bags"])))
    if bag is None:
        bag = out_dir / "synthetic_input.mcap"
        write_synthetic_bag(bag)
        print(f"endo-demo: no bag in bags/, wrote a synthetic one: {bag}")
    output = out_dir / "round_trip.mcap"
    if output.exists():
        print(f"endo-demo: error: {output} exists", file=sys.stderr)
        return False
    topics, skipped = playable_topics(bag)
    if not topics:
        raise Endo3dError(f"{bag}: no topic to play here (an empty bag, one cut before its "
                          f"first chunk, or only types not installed: `endo-bag info` says)")
    print(
        f"endo-demo: [1/4] round trip: playing {bag} at {rate:g}x over DDS "
        f"(domain {env['ROS_DOMAIN_ID']}, discovery {env['ROS_AUTOMATIC_DISCOVERY_RANGE']}), "
        f"recording into {output}"
    )
    for name in skipped:
        print(f"  {name}: type not installed here, not played")
    started = time.monotonic()
    replay_rc, record_rc, logs = run_round_trip(bag, output, rate, env)
    elapsed = time.monotonic() - started
    if replay_rc != 0 or record_rc != 0 or not output.exists():
        print(logs)
        print(
            f"endo-demo: round trip FAILED (endo-replay exit {replay_rc}, "
            f"endo-record exit {record_rc})"
        )
        return False
    result = compare_bags(bag, output, topics)
    print(f"  {'topic':<28} {'type':<32} {'sent':>6} {'recorded':>9} {'bytes':>11}  result")
    for name, t in result.topics.items():
        if t.identical == t.sent == t.received:
            verdict = "identical"
        elif t.equal:
            verdict = f"equal up to DDS 4-byte padding ({t.padding_only} padded in transit)"
        else:
            verdict = "DIFFERENT"
        counts = f"{t.sent:>6} {t.received:>9} {t.sent_bytes:>11}"
        print(f"  {name:<28} {t.msgtype:<32} {counts}  {verdict}")
    for name in result.extra_topics:
        print(f"  {name}: recorded but not played (DIFFERENT)")
    total = sum(t.sent for t in result.topics.values())
    print(f"  {total} messages in {elapsed:.1f} s")
    if not result.equal:
        print("endo-demo: round trip FAILED: the recording differs from the bag")
        return False
    print("  round trip OK: the recording equals the bag, message for message")
    return True


@exit_on_error("endo-demo")
def main(argv: list[str] | None = None) -> int:
    """Run the demo; returns the exit status (1: a check failed, 2: bad input)."""
    options = build_parser().parse_args(argv)
    check_options(options)
    # SIGTERM ends the demo like Ctrl-C: unwinding stops every child process.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", DEMO_DOMAIN_ID)
    out_dir = options.output_dir or Path(tempfile.mkdtemp(prefix="endo_demo_"))
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in DEMO_OUTPUTS:
        (out_dir / name).unlink(missing_ok=True)
    started = time.monotonic()
    round_trip_ok = run_round_trip_stage(options.bag, out_dir, options.rate, env)
    failures = [] if round_trip_ok else ["round trip"]
    shortfalls: list[str] = []
    bags_dir = sample_bags_dir(list(dict.fromkeys([Path.cwd() / "bags", REPO_ROOT / "bags"])))
    if options.round_trip_only:
        pass
    elif bags_dir is None:
        print("endo-demo: [2/4-4/4] skipped: bags/ lacks graycard, handeye and phantom_colon bags")
    else:
        print(
            f"endo-demo: [2/4] offline calibrations on {bags_dir / GRAYCARD_BAG} and "
            f"{bags_dir / HANDEYE_BAG}; [3/4] live graph on {bags_dir / PHANTOM_BAG}"
        )
        report = run_graph_stage(bags_dir, out_dir, env, options.graph_rate, options.solve_scale)
        print_graph_report(report, options.graph_rate)
        failures += report.failures()
        shortfalls = report.shortfalls()
        if report.run is not None and not options.no_offline:
            offline_failures, offline_shortfalls = run_offline_stage(
                report, bags_dir / PHANTOM_BAG, out_dir, env, options
            )
            failures += offline_failures
            shortfalls += offline_shortfalls
            write_demo_summary(out_dir / "summary.json", report, failures + shortfalls, options)
            print(f"  summary: {out_dir / 'summary.json'}")
    print(f"endo-demo: outputs in {out_dir} ({time.monotonic() - started:.0f} s in all)")
    if failures:
        print("endo-demo: FAILED: " + "; ".join(failures + shortfalls))
        return 1
    if shortfalls:
        print("endo-demo: NOT OK: the graph ran to the end, but " + "; ".join(shortfalls))
        return 1
    print("endo-demo: OK")
    return 0


if __name__ == "__main__":
    sys.exit(main())
