"""One offline run: a recording in, the live graph's outputs out.

:func:`process_bag` is what ``endo-process`` runs. In order:

1. the nodes' parameters (:mod:`endo_process.settings`), the photometric
   and hand–eye calibrations, and the recording's small streams
   (:mod:`endo_process.inputs`);
2. every tracker pose through the bridge's chain
   (:class:`endo_tracker_bridge.chain.CameraPoseChain`: gate, hand–eye,
   ``T_world_tracker``, clock offset), written as ``/endoscope/pose``;
3. every image through the correction and SFS cores
   (:class:`endo_process.parallel.ShadingPool`, one chain, or chains on
   worker processes taking the frames in turn), written as
   ``/endoscope/image_corrected``, ``/endoscope/depth_relative`` and
   ``/endoscope/camera_info``;
4. the camera pose at each image stamp from a
   :class:`endo_io.pose_buffer.PoseBuffer` fed with those poses in stamp
   order, as a live consumer sees them; frames without one are counted;
5. the flow step (:class:`endo_process.flow_stage.FlowStage`, i.e.
   ``FlowPipeline.process``), written as ``/endoscope/depth``,
   ``/endoscope/points`` (the live topic's decimation unless
   ``--cloud-decimation``) and ``/endoscope/scale``, and at the end the voxel
   map's last state as ``/endoscope/map`` (and ``--ply``), fused as the live
   node fuses it (every pixel of every 8th frame by default).

Ground truth in the input is copied through. A stop request (Ctrl-C,
SIGTERM) ends the run after the current frame and the output is finalised.
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import statistics
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from endo_calib.calibration import PhotometricCalibration
from endo_calib.errors import CalibrationError
from endo_flow.errors import MapExportError
from endo_flow.messages import SCALE_TYPE, grey_cloud_cdr, scale_message_cdr
from endo_flow.warm_up import warm_up_pipeline
from endo_io import topics
from endo_io.bag import BagError, BagMessage, BagReader
from endo_io.errors import Endo3dError, PoseLookupError
from endo_io.image import IRRADIANCE_ENCODINGS, encode_irradiance, image_to_array
from endo_io.pose import transforms_to_pose_stamped_cdr
from endo_io.pose_buffer import PoseBuffer
from endo_io.progress import Progress
from endo_io.stamp import NS_PER_S, ns_to_stamp, stamp_to_ns
from endo_io.tf import StampedTransform, static_transforms
from endo_process.accuracy import Accuracy, RecordingScorer
from endo_process.damage import PlacedDamage, most_serious, place_damage
from endo_process.errors import ImageStampBackError, ProcessInputError
from endo_process.flow_stage import FlowStage, offline_flow_options
from endo_process.inputs import (
    CameraInfoPairing,
    InputTopics,
    RecordingStreams,
    first_camera,
    iter_ground_truth,
    iter_images,
    iter_tracker_poses,
    open_recording,
    recording_streams,
)
from endo_process.output import DEFAULT_FLUSH_EVERY, POINTS_TYPE, POSE_TYPE, OutputBag
from endo_process.parallel import DEFAULT_CHUNK_FRAMES, ShadingPool, StageConfig
from endo_process.settings import ProcessSettings, load_settings
from endo_process.shading import RawFrame, ShadedFrame, ShadingStage
from endo_process.worker_start import StartedWorkers
from endo_tracker_bridge.chain import CameraPose, CameraPoseChain
from endo_tracker_bridge.errors import HandEyeFileError
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.sources.ros import sample_from_pose_stamped


@dataclass(frozen=True)
class ProcessOptions:
    """The command line of one run (see ``endo-process --help``)."""

    bag: Path
    output: Path
    calibration: Path
    handeye: Path
    params: Path | None = None
    solve_scale: float | None = None
    topics: InputTopics = field(default_factory=InputTopics)
    camera_info: Path | None = None
    ply: Path | None = None
    cloud_decimation: int | None = None
    jobs: int = 1
    chunk_frames: int = DEFAULT_CHUNK_FRAMES
    compression: str = "zstd"
    chunk_crcs: bool = False
    direct: bool = True
    progress: bool = True
    flush_every: int = DEFAULT_FLUSH_EVERY
    max_frames: int | None = None
    overwrite: bool = False


@dataclass
class ProcessReport:
    """What a run did, for the summary table and the tests.

    Counters are per cause (error class name). ``seconds`` is the wall time
    of the frame loop, ``bag_seconds`` the recording time it covered (by the
    images' log times).
    ``stage_seconds``: wall seconds of the frame loop's steps in this
    process, summed over the frames (:data:`LOOP_STAGES`);
    ``stage_cpu_seconds``: the CPU seconds of the same steps in the loop's
    thread (``time.thread_time``: the CPU this process's other threads spend
    meanwhile, OpenCV's and the queues' feeders, is in ``loop_cpu_seconds``
    only); ``shading_seconds``:
    the correction and SFS steps' own wall seconds, summed, wherever they ran
    (this process or a worker; ``ShadedFrame.timings``). ``loop_cpu_seconds``:
    this process's CPU seconds (all its threads) in the frame loop;
    ``worker_cpu_seconds``: the worker processes' CPU seconds from their
    first frame to their last (``ShadedFrame.worker_cpu_s``), start-up aside.
    ``first_frame_seconds``: wall seconds from the loop's start until the
    first frame was written (with workers, mostly the wait for their
    start-up: loading kernels, warming up); the rest of the loop is the
    steady state (:attr:`steady_real_time_factor`). ``saturated_pixels``:
    pixels of the corrected images above the 16-bit fixed point's range
    (6.5534), written as its top. ``undecodable``: messages skipped because their bytes
    do not decode as their topic's type, per topic (``first_undecodable``:
    the first one's error); ``reasons``: the first one-line message of each
    cause counted in ``dropped``, ``tracker_rejected`` and ``flow_dropped``.
    ``accuracy``: the output against the ground truth the input carries,
    scored as it was written (:class:`endo_process.accuracy.RecordingScorer`;
    empty without truth); None when the run stopped early (a stop, a write
    failure) or the truth came after the outputs of its frames, so that the
    file is to be scored with :func:`endo_process.accuracy.score_recording`.
    ``write_failure``: the output writer's error when a write failed (a full
    disk, a file size limit): the run stopped there, ``written`` counts what
    the file holds and ``lost`` the messages that did not reach it;
    ``--ply`` is still attempted from the map in memory (``ply_vertices``,
    or ``ply_error``: why not).
    ``frames_log_ns``: (first, last) log time of the images read (None:
    none); ``read_all_images``: the image stream was read to its end (no
    ``--max-frames`` or stop before it). ``input_damage``: every damaged
    region of the input the run's readers found, placed against those log
    times (:mod:`endo_process.damage`); ``damage``: the reader's line for
    the most serious region that lost messages among or after the frames
    (or cost none), ``damage_beyond``: for one after the frames processed
    when the run stopped before it (only such regions), else None.
    ``frames_in_flight``: frames read and sent to the correction and SFS
    but never written, because the run stopped (a stop request, a failed
    write) while they were in a worker process: every image read is either
    dropped before the shading (``dropped``), written (with a relative
    depth, ``frames_shaded``, or without, ``dropped`` saying why), or one of
    these. ``recording_start_ns``: the recording's first log time.
    """

    frames_in: int = 0
    frames_total: int = 0
    frames_shaded: int = 0
    frames_with_pose: int = 0
    frames_flow: int = 0
    frames_metric: int = 0
    flow_dropped: Counter[str] = field(default_factory=Counter)
    map_points: int = 0
    saturated_pixels: int = 0
    ply_vertices: int = 0
    dropped: Counter[str] = field(default_factory=Counter)
    without_pose: Counter[str] = field(default_factory=Counter)
    tracker_rejected: Counter[str] = field(default_factory=Counter)
    pose_buffer_events: Counter[str] = field(default_factory=Counter)
    tracker_samples: int = 0
    poses_written: int = 0
    written: Counter[str] = field(default_factory=Counter)
    seconds: float = 0.0
    setup_seconds: float = 0.0
    loop_cpu_seconds: float = 0.0
    first_frame_seconds: float = 0.0
    worker_cpu_seconds: float = 0.0
    bag_seconds: float = 0.0
    solve_ms: list[float] = field(default_factory=list)
    stage_seconds: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))
    stage_cpu_seconds: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))
    shading_seconds: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))
    damage: str | None = None
    damage_beyond: str | None = None
    input_damage: list[PlacedDamage] = field(default_factory=list)
    frames_log_ns: tuple[int, int] | None = None
    read_all_images: bool = False
    frames_in_flight: int = 0
    recording_start_ns: int = 0
    undecodable: Counter[str] = field(default_factory=Counter)
    first_undecodable: str | None = None
    reasons: dict[str, str] = field(default_factory=dict)
    interrupted: bool = False
    output: Path | None = None
    write_failure: str = ""
    lost: int = 0
    ply_error: str = ""
    accuracy: Accuracy | None = None

    def count(self, counter: Counter[str], cause: str, reason: str) -> None:
        """Count one dropped item under ``cause``; keep the first ``reason`` given for it."""
        counter[cause] += 1
        self.reasons.setdefault(cause, reason)

    @property
    def frames_per_second(self) -> float:
        """Frames through the whole pipeline per wall second."""
        return self.frames_in / self.seconds if self.seconds > 0 else 0.0

    @property
    def real_time_factor(self) -> float:
        """Recording seconds processed per wall second (>1: faster than real time)."""
        return self.bag_seconds / self.seconds if self.seconds > 0 else 0.0

    @property
    def steady_real_time_factor(self) -> float:
        """:attr:`real_time_factor` of the frames after the first (the pipeline filled)."""
        steady = self.seconds - self.first_frame_seconds
        if self.frames_in < 2 or steady <= 0:
            return 0.0
        return self.bag_seconds * (self.frames_in - 1) / self.frames_in / steady

    @property
    def median_solve_ms(self) -> float:
        """Median SFS solve time per frame."""
        return statistics.median(self.solve_ms) if self.solve_ms else 0.0


#: The steps of the frame loop timed in :attr:`ProcessReport.stage_seconds`:
#: reading and decoding an image and pairing its camera ("read"); the
#: correction and SFS, or with worker processes the wait for them and the
#: frames' way there and back ("shading"); the pose lookup, with the poses
#: it reads and queues ("poses"); ground truth copied through ("truth");
#: camera_info, corrected image and relative depth written ("write"); the
#: flow step ("flow") and its outputs written ("flow_write"); flushing the
#: output ("flush").
LOOP_STAGES = ("read", "shading", "poses", "truth", "write", "flow", "flow_write", "flush")


class _StageClock:
    """Wall and thread-CPU seconds of the frame loop's steps, into a report's two tables."""

    def __init__(self, report: ProcessReport) -> None:
        self.wall = report.stage_seconds
        self.cpu = report.stage_cpu_seconds

    @staticmethod
    def now() -> tuple[float, float]:
        """(wall, this thread's CPU) seconds now."""
        return time.perf_counter(), time.thread_time()

    def add(self, name: str, since: tuple[float, float]) -> tuple[float, float]:
        """Count the time from ``since`` to now to step ``name``; now."""
        now = self.now()
        self.wall[name] += now[0] - since[0]
        self.cpu[name] += now[1] - since[1]
        return now


def _load_calibrations(
    options: ProcessOptions,
) -> tuple[PhotometricCalibration, HandEyeCalibration]:
    try:
        photometric = PhotometricCalibration.load(options.calibration)
    except CalibrationError as error:
        raise ProcessInputError(f"--calibration: {error}") from None
    try:
        handeye = HandEyeCalibration.load(options.handeye)
    except (HandEyeFileError, OSError) as error:
        raise ProcessInputError(f"--handeye: {error}") from None
    return photometric, handeye


def iter_camera_poses(
    messages: Iterator[PoseStamped],
    settings: ProcessSettings,
    handeye: HandEyeCalibration,
    report: ProcessReport,
) -> Iterator[CameraPose]:
    """The recorded marker poses through the bridge's chain, lazily, as the ``ros`` source does."""
    chain = CameraPoseChain(handeye, settings.T_world_tracker, settings.speed_limits)
    unit = settings.tracker_unit
    bridge = settings.bridge
    for msg in messages:
        report.tracker_samples += 1
        try:
            sample = sample_from_pose_stamped(
                msg, unit, str(bridge["ros_frame_id"]), str(bridge["tool_id"]),
                float(bridge["rotation_tolerance"]),
            )  # fmt: skip
            pose = chain.accept(sample)
        except Endo3dError as error:
            report.count(report.tracker_rejected, type(error).__name__, str(error))
            continue
        yield pose


#: Poses converted at once when the feed drains the stream (at most this many held ahead).
_POSE_BLOCK = 256


class _PoseFeed:
    """Camera poses, read lazily in arrival order, into a PoseBuffer up to just past each query.

    Each pose taken from the stream is queued for the output as
    ``/endoscope/pose`` (camera time) and ``/tracker/marker_pose`` (tracker
    time), and goes into the buffer as the flow node takes it: the transform
    that ``pose_to_matrix`` reads back from the ``/endoscope/pose`` message,
    into a buffer made as the flow node makes it (capacity 6000, its
    ``pose_max_gap_s``). The poses a frame needs are read first and then
    converted together (:func:`endo_io.pose.transforms_to_pose_stamped_cdr`:
    the same bytes and transforms as one ``matrix_to_pose`` per pose, at a
    fraction of the cost), then inserted one by one. A pose the buffer
    refuses (out of order, a far-future stamp) or that resets it (a clock
    jump) is counted by cause, as the node's diagnostics count it. Only the
    poses read ahead of the current frame are held in memory.
    """

    def __init__(
        self,
        poses: Iterator[CameraPose],
        output: OutputBag,
        frames: tuple[str, str],
        max_gap_ns: int,
        report: ProcessReport,
    ) -> None:
        self._poses = poses
        self._output = output
        self._pose_frame, self._tracker_frame = frames
        self._report = report
        self.buffer = PoseBuffer(capacity=6000, max_gap_ns=max_gap_ns)

    def _read(self, until_ns: int | None) -> list[CameraPose]:
        """Poses from the stream up to the first stamped after ``until_ns`` (a block when None)."""
        block: list[CameraPose] = []
        for pose in self._poses:
            block.append(pose)
            if (until_ns is not None and pose.stamp_ns > until_ns) or len(block) >= _POSE_BLOCK:
                break
        return block

    def _take(self, block: list[CameraPose]) -> None:
        """Queue ``block`` for the output and insert it into the buffer, in order."""
        world, read_back = transforms_to_pose_stamped_cdr(
            np.stack([pose.T_world_camera for pose in block]),
            [pose.stamp_ns for pose in block], self._pose_frame,
        )  # fmt: skip
        marker, _ = transforms_to_pose_stamped_cdr(
            np.stack([pose.sample.T_tracker_marker for pose in block]),
            [pose.sample.stamp_ns for pose in block], self._tracker_frame,
        )  # fmt: skip
        for k, pose in enumerate(block):
            self._output.hold_cdr(topics.CAMERA_POSE, POSE_TYPE, world[k], pose.stamp_ns)
            self._output.hold_cdr(topics.MARKER_POSE, POSE_TYPE, marker[k], pose.sample.stamp_ns)
            try:
                self.buffer.insert(pose.stamp_ns, read_back[k])
            except Endo3dError as error:  # ClockJumpError: the tracker's stamps went back
                self._report.count(self._report.pose_buffer_events, type(error).__name__,
                                   str(error))  # fmt: skip

    def at(self, stamp_ns: int) -> np.ndarray:
        """T_world_camera at ``stamp_ns``; raises PoseLookupError when there is none."""
        # Only the last pose read can be newer than stamp_ns, as when taken one by one.
        while self.buffer.newest_ns is None or self.buffer.newest_ns <= stamp_ns:
            block = self._read(stamp_ns)
            if not block:
                break
            self._take(block)
        return self.buffer.query(stamp_ns)

    def drain(self) -> None:
        """Queue every pose left in the stream for the output (the end of a complete run)."""
        while block := self._read(None):
            self._take(block)


def _raw_frames(
    pairing: CameraInfoPairing,
    images: Iterator[tuple[int, Image]],
    infos: dict[int, CameraInfo | None],
    report: ProcessReport,
    stop: threading.Event,
    max_frames: int | None,
) -> Iterator[RawFrame]:
    """Decoded images paired with their camera; unusable ones are counted and skipped.

    ``infos`` receives each yielded frame's camera_info (by frame index) for
    the output; the frame loop takes it back out. ``images`` are (log time
    ns, image); the report gets the log times of the images read
    (``frames_log_ns``) and whether they were read to the end.
    """
    index = 0
    newest_ns: int | None = None  # the newest image stamp read
    clock = _StageClock(report)
    start = clock.now()
    for log_ns, msg in images:
        if stop.is_set() or (max_frames is not None and report.frames_in >= max_frames):
            return
        report.frames_in += 1
        first_ns = log_ns if report.frames_log_ns is None else report.frames_log_ns[0]
        report.frames_log_ns = (first_ns, log_ns)
        stamp_ns = stamp_to_ns(msg.header.stamp)
        went_back = newest_ns is not None and stamp_ns < newest_ns
        newest_ns = stamp_ns if newest_ns is None else max(newest_ns, stamp_ns)
        try:
            paired = pairing.at(stamp_ns)
            if paired is None and went_back:
                assert newest_ns is not None
                # the camera_info stream has moved on past this stamp: not a missing camera_info
                error = ImageStampBackError(
                    f"image stamp went back {(newest_ns - stamp_ns) / NS_PER_S:.3f} s, from "
                    f"{newest_ns} to {stamp_ns} ns (a clock jump, or frames out of order)"
                )
                report.count(report.dropped, type(error).__name__, str(error))
                continue
            if paired is None:
                report.count(report.dropped, "NoCameraInfoError",
                             f"no camera_info at or before the image stamped {stamp_ns} ns")
                continue
            raw = image_to_array(msg)
        except Endo3dError as error:
            report.count(report.dropped, type(error).__name__, str(error))
            continue
        camera, infos[index] = paired
        clock.add("read", start)
        yield RawFrame(index, stamp_ns, msg.header.frame_id, raw, msg.encoding, camera)
        start = clock.now()
        index += 1
    clock.add("read", start)
    report.read_all_images = True


def _write_frame(
    output: OutputBag, info: CameraInfo | None, shaded: ShadedFrame, report: ProcessReport
) -> None:
    """Camera_info, corrected image and relative depth of one frame.

    The camera_info is the recorded one, restamped to the image when the
    driver stamped it on its own clock (the live graph publishes one beside
    every image, at the image's stamp), or built from ``--camera-info``.
    """
    stamp = shaded.stamp_ns
    if info is None:
        info = shaded.camera.to_camera_info(stamp)
        info.header.frame_id = shaded.frame_id or shaded.camera.frame_id
    elif stamp_to_ns(info.header.stamp) != stamp:
        info = copy.deepcopy(info)
        info.header.stamp = ns_to_stamp(stamp)
    output.write(topics.CAMERA_INFO, info, stamp)
    if shaded.irradiance is not None:
        # the fixed point's decoded values encode back to the same counts (tested)
        pixels = encode_irradiance(shaded.irradiance, shaded.encoding).pixels \
            if shaded.encoding in IRRADIANCE_ENCODINGS else shaded.irradiance
        output.write_image(topics.IMAGE_CORRECTED, pixels, shaded.encoding, stamp,
                           shaded.frame_id)  # fmt: skip
        report.saturated_pixels += shaded.saturated
    if shaded.depth_relative is not None:
        output.write_image(topics.DEPTH_RELATIVE, shaded.depth_relative, "32FC1", stamp,
                           shaded.frame_id)  # fmt: skip
        report.frames_shaded += 1
    if shaded.dropped is not None:
        report.count(report.dropped, *shaded.dropped)
    if shaded.solve_ms > 0.0:
        report.solve_ms.append(shaded.solve_ms)
    for name, seconds in shaded.timings.items():
        report.shading_seconds[name] += seconds


def _flow_frame(
    output: OutputBag,
    flow: FlowStage,
    shaded: ShadedFrame,
    T_world_camera: np.ndarray | None,
    world_frame: str,
    report: ProcessReport,
) -> None:
    """The flow step of one frame and its messages; a frame the pipeline refuses is counted."""
    if shaded.irradiance is None or shaded.depth_relative is None or shaded.irradiance.ndim != 2:
        return
    stamp = shaded.stamp_ns
    clock = _StageClock(report)
    start = clock.now()
    try:
        result = flow.process(shaded, T_world_camera)
    except Endo3dError as error:
        report.count(report.flow_dropped, type(error).__name__, str(error))
        return
    finally:
        now = clock.add("flow", start)
    report.frames_flow += 1
    if result.depth is not None:
        output.write_image(topics.DEPTH, result.depth, "32FC1", stamp, shaded.frame_id)
        report.frames_metric += 1
    if len(result.points):
        output.write_cdr(topics.POINTS, POINTS_TYPE, grey_cloud_cdr(
            result.points, result.intensity, stamp, world_frame), stamp)  # fmt: skip
    output.write_cdr(topics.SCALE, SCALE_TYPE, scale_message_cdr(
        result.scale, stamp, shaded.frame_id), stamp)  # fmt: skip
    clock.add("flow_write", now)


def _write_map(
    output: OutputBag,
    flow: FlowStage,
    options: ProcessOptions,
    stamp_ns: int,
    world_frame: str,
    report: ProcessReport,
) -> None:
    """The voxel map's last state on /endoscope/map (--ply: :func:`_export_ply`, after)."""
    cloud = flow.map_cloud(stamp_ns, world_frame)
    if cloud is None:
        return
    output.write(topics.MAP, cloud, stamp_ns)
    report.map_points = cloud.width * cloud.height


def _export_ply(flow: FlowStage, options: ProcessOptions, report: ProcessReport) -> None:
    """--ply, once the output is finalised: a PLY that cannot be written costs only itself.

    After the output's writing failed (a full disk) the map is still in
    memory, fused up to the last frame processed: the PLY is written too
    (``--ply`` may name another disk); if that fails as well,
    ``report.ply_error`` says why.
    """
    voxel_map = flow.pipeline.voxel_map
    if options.ply is None:
        return
    if voxel_map is None:
        report.ply_error = "the flow node's map is off (map_enabled)"
    elif len(voxel_map) and (report.write_failure or report.map_points):
        try:
            report.ply_vertices = voxel_map.export_ply(options.ply)
        except (MapExportError, OSError) as error:  # write_ply removes a partial file
            # the output and the summary are whole: this costs only the PLY (it was exit 2
            # with no summary, after the whole run)
            report.ply_error = str(error)
    else:
        report.ply_error = "the map was empty"


def _place_damage(
    report: ProcessReport, streams: RecordingStreams, image_topic: str, reach_ns: int
) -> None:
    """Where the input's damage lies against the frames read: ``input_damage``, ``damage*``.

    ``reach_ns``: how far past the last image's log time its pose lookup reads
    (:func:`endo_process.damage.place_damage`).
    """
    placed = place_damage(streams.damaged_regions(), image_topic, report.frames_log_ns,
                          report.read_all_images, reach_ns=reach_ns)  # fmt: skip
    report.input_damage = placed
    serious = most_serious(placed)
    if serious is None:
        return
    more = f"; {len(placed) - 1} more damaged region(s)" if len(placed) > 1 else ""
    if serious.where == "after":  # --max-frames or a stop came before it: not met
        report.damage_beyond = f"{serious.region}{more}"
    else:
        report.damage = f"{serious.region}{more}"


def one_chain_parameters(sfs_parameters: dict[str, Any]) -> dict[str, Any]:
    """The SFS parameters of ``--jobs 1``'s chain: ``threads`` 0 taken as 2.

    The node's default 0 gives one thread at solve_scale 0.5, to leave a
    live graph's other nodes the second core; the one chain of ``--jobs 1``
    has the process to itself, and two threads solve a phantom frame at 0.5
    in 12.9 ms against one thread's 16.7 (docs/process.md, "Speed: two cores"). A
    count the parameters set is kept.
    """
    if sfs_parameters.get("threads"):
        return sfs_parameters
    return dict(sfs_parameters, threads=2)


def process_bag(
    options: ProcessOptions,
    stop: threading.Event | None = None,
    workers: StartedWorkers | None = None,
) -> ProcessReport:
    """Run the offline graph over ``options.bag`` into ``options.output``.

    Args:
        options: the run's inputs, outputs and settings.
        stop: set it (from a signal handler) to end the run after the
            current frame; the output is finalised either way.
        workers: with ``options.jobs`` > 1, the shading workers, started
            before this process loaded its modules
            (:func:`endo_process.worker_start.start_workers`); the run
            takes them over. None: the run starts its own. The caller
            closes them (a no-op once taken) if the run fails before.

    Returns:
        The run's report (``damage`` set when the bag was cut short,
        ``interrupted`` when ``stop`` ended it).

    Raises:
        ProcessInputError: (and subclasses) an input is unusable; nothing
            was written.
        BagError: the bag cannot be opened, or the output exists already.
    """
    stop = stop or threading.Event()
    setup_start = time.perf_counter()
    settings = load_settings(options.params, solve_scale=options.solve_scale)
    photometric, handeye = _load_calibrations(options)
    inputs = open_recording(options.bag, options.topics, options.camera_info)
    config = StageConfig(options.calibration, settings.channel, settings.sfs,
                         settings.mask_extrapolated, settings.output_encoding)  # fmt: skip
    stage = None
    if options.jobs == 1:  # the calibration loaded above, not a second time
        stage = ShadingStage(photometric, settings.channel, one_chain_parameters(settings.sfs),
                             mask_extrapolated=settings.mask_extrapolated,
                             output_encoding=settings.output_encoding)  # fmt: skip
    camera = None
    with contextlib.suppress(Endo3dError):  # a bad camera_info is the frame loop's to report
        camera = first_camera(inputs)
    # Workers start first, and get their first frames at once (pool.map sends
    # them): loading their kernels and building their solve grids on real
    # frames while this process sets up and warms up the flow step.
    pool = ShadingPool(config, options.jobs, options.chunk_frames, stage, camera=camera,
                       workers=workers)  # fmt: skip
    streams: RecordingStreams | None = None
    try:  # the workers are running: stop them if the set-up fails
        report = ProcessReport(frames_total=inputs.frame_count, output=options.output,
                               recording_start_ns=inputs.time_range_ns[0])  # fmt: skip
        streams = recording_streams(inputs)
        infos: dict[int, CameraInfo | None] = {}
        frames = _raw_frames(
            CameraInfoPairing(inputs, streams), iter_images(streams), infos, report, stop,
            options.max_frames,
        )  # fmt: skip
        shaded_frames = enumerate(pool.map(frames), start=1)
        with BagReader(options.bag) as reader:
            copied = {name: reader.topics[name] for name in inputs.ground_truth}
        if options.overwrite:  # only now: every input has been checked
            options.output.unlink(missing_ok=True)
        # The output scored as it is written, not read back (with ground truth only).
        scorer = RecordingScorer() if copied else None
        output = OutputBag(options.output, options.compression, copied,
                           threaded=pool.worker_count == 0, crcs=options.chunk_crcs,
                           direct=options.direct,
                           tap=None if scorer is None else scorer.add)  # fmt: skip
        world_frame = str(settings.flow["world_frame"])
        poses = iter_camera_poses(iter_tracker_poses(streams), settings, handeye, report)
        first_pose = next(poses, None)
        if first_pose is not None:
            poses = itertools.chain([first_pose], poses)
        static_ns = min(inputs.time_range_ns[0],
                        first_pose.stamp_ns if first_pose is not None else inputs.time_range_ns[0])
        output.hold_tf(
            topics.TF_STATIC,
            static_transforms(
                T_world_tracker=settings.T_world_tracker,
                T_marker_camera=handeye.T_marker_camera,
                stamp_ns=static_ns,
            ),
            static_ns,
        )  # fmt: skip
        feed = _PoseFeed(
            poses,
            output,
            (str(settings.bridge["world_frame"]), str(settings.bridge["tracker_frame"])),
            round(float(settings.flow["pose_max_gap_s"]) * NS_PER_S),
            report,
        )
        flow = FlowStage(offline_flow_options(settings.flow, options.cloud_decimation),
                         int(settings.flow["map_min_count"]))
        if camera is not None and pool.worker_count > 0:
            # Overlapped with the workers' first frames; with one job it would only add.
            warm_up_pipeline(flow.pipeline.options, camera)
        truth: Iterator[BagMessage] = iter_ground_truth(streams)
        truth_pending: list[BagMessage] = []
        total = inputs.frame_count if options.max_frames is None else min(
            inputs.frame_count, options.max_frames
        )
        first_stamp: int | None = None
        last_stamp: int | None = None
        progress = Progress(total, enabled=options.progress, description="endo-process")
    except BaseException:
        pool.close()
        if streams is not None:
            streams.close()
        raise
    report.setup_seconds = time.perf_counter() - setup_start
    loop_start, loop_cpu_start = time.perf_counter(), time.process_time()
    worker_cpu: dict[int, float] = {}
    try:
        clock = _StageClock(report)
        clock.wall["read"] = clock.cpu["read"] = 0.0  # pool.map's first frames: the set-up's
        while True:
            # "shading" is the wait for the next shaded frame less the reading it includes.
            read_before = clock.wall["read"], clock.cpu["read"]
            step = clock.now()
            item = next(shaded_frames, None)
            clock.add("shading", step)
            clock.wall["shading"] -= clock.wall["read"] - read_before[0]
            clock.cpu["shading"] -= clock.cpu["read"] - read_before[1]
            if item is None:
                break
            count, shaded = item
            if shaded.worker_cpu_s > 0.0:
                worker_cpu[pool.worker_of(shaded.index)] = shaded.worker_cpu_s
            # The poses up to this frame first: the output stays in log-time order.
            T_world_camera: np.ndarray | None = None
            # The cause's name only: an exception kept past its except block holds
            # its traceback, whose frames hold this loop's frame data until a full
            # garbage collection (the cycle that made the live flow node's memory
            # creep, docs/reliability.md).
            missing_pose: str | None = None
            step = clock.now()
            try:
                T_world_camera = feed.at(shaded.stamp_ns)
            except PoseLookupError as error:
                missing_pose = type(error).__name__
            step = clock.add("poses", step)
            output.copy_until(truth, truth_pending, shaded.stamp_ns)
            step = clock.add("truth", step)
            _write_frame(output, infos.pop(shaded.index), shaded, report)
            if missing_pose is not None:
                report.without_pose[missing_pose] += 1
            if T_world_camera is not None:
                report.frames_with_pose += 1
                edge = StampedTransform.from_matrix(
                    T_world_camera, shaded.stamp_ns, world_frame,
                    shaded.frame_id or topics.OPTICAL_FRAME,
                )  # fmt: skip
                output.hold_tf(topics.TF, [edge], shaded.stamp_ns)
            clock.add("write", step)
            _flow_frame(output, flow, shaded, T_world_camera, world_frame, report)
            if first_stamp is None:
                first_stamp = shaded.stamp_ns
                report.first_frame_seconds = time.perf_counter() - loop_start
            last_stamp = shaded.stamp_ns
            if count % options.flush_every == 0:
                step = clock.now()
                output.flush()
                clock.add("flush", step)
            progress.update(report.frames_in)
            if stop.is_set():
                report.interrupted = True
                break
    except KeyboardInterrupt:
        report.interrupted = True
    except BagError:
        if not output.failure:  # not the output's writer: an input
            raise
        report.write_failure = output.failure  # a full disk: stop here, keep what is on disk
    finally:
        # Sent to the shading and not written: in a worker when the run stopped.
        report.frames_in_flight = len(infos)
        report.seconds = time.perf_counter() - loop_start
        report.loop_cpu_seconds = time.process_time() - loop_cpu_start
        report.worker_cpu_seconds = sum(worker_cpu.values())
        pool.stop()  # the workers exit (a few tenths of a second) while the output is finished
        try:
            progress.close()
            # A partial run (stopped, or --max-frames short of the end) ends at its last frame.
            partial = stop.is_set() or report.interrupted or (
                options.max_frames is not None and report.frames_in < inputs.frame_count
            )
            end = last_stamp if partial and last_stamp is not None else np.iinfo(np.int64).max
            try:
                if not report.write_failure:  # the writer refuses every write after one failed
                    if not partial:
                        feed.drain()
                    output.copy_until(truth, truth_pending, end)
                    if last_stamp is not None:
                        _write_map(output, flow, options, last_stamp, world_frame, report)
                output.close(end if partial else None)
            except BagError:
                if not output.failure:
                    raise
                report.write_failure = output.failure
                with contextlib.suppress(BagError):
                    output.close()  # the file only: it reads to its last complete chunk
            streams.close()
        finally:
            pool.close()
    _export_ply(flow, options, report)
    report.interrupted = report.interrupted or stop.is_set()
    if not report.interrupted and not report.write_failure:
        if scorer is None:
            report.accuracy = Accuracy()
        elif scorer.complete:
            report.accuracy = scorer.result()
    if scorer is not None:
        scorer.close()
    report.written = output.on_disk if report.write_failure else Counter(output.counts)
    report.lost = output.lost
    report.poses_written = report.written[topics.CAMERA_POSE]
    # a frame's pose: tracker samples up to the buffer's gap after its stamp, shifted by
    # the hand-eye clock offset (the tracker's clock against the camera's)
    pose_reach_ns = (round(float(settings.flow["pose_max_gap_s"]) * NS_PER_S)
                     + abs(handeye.time_offset_ns))  # fmt: skip
    _place_damage(report, streams, inputs.topics.image, pose_reach_ns)
    report.undecodable = inputs.undecodable
    report.first_undecodable = inputs.first_undecodable
    if first_stamp is not None and last_stamp is not None:
        # The recording time covered: the log times of the images read (the recorder's
        # clock: a re-recorded looping replay's stamps go back at each loop, so the
        # stamps' span said 0.04x for a run at ~0.8x); the stamps' when the log times
        # do not move (a writer that logged every message at one time).
        span_ns = 0
        if report.frames_log_ns is not None:
            span_ns = report.frames_log_ns[1] - report.frames_log_ns[0]
        if span_ns <= 0:
            span_ns = last_stamp - first_stamp
        frame_period = 0 if report.frames_in < 2 else span_ns / max(report.frames_in - 1, 1)
        report.bag_seconds = (span_ns + frame_period) / NS_PER_S
    return report
