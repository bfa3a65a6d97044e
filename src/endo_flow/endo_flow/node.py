"""``flow`` node: corrected image + relative depth + camera pose -> metric depth, cloud, map.

A thin adapter around :class:`endo_flow.pipeline.FlowPipeline` (the per-frame
step the offline processor calls too).

Subscriptions:

* ``/endoscope/depth_relative`` (32FC1), the frame input (newest frame): its
  arrival drives the node;
* ``/endoscope/image_corrected`` (linear irradiance, 16UC1 fixed point or
  32FC1: :func:`endo_io.image.image_to_irradiance`) and
  ``/endoscope/camera_info``, taken by stamp when a depth arrives
  (:meth:`endo_io.diagnostics.InputHealth.subscribe_passive`: they wait in
  DDS, :data:`endo_io.qos.BY_STAMP_QOS`, and cost no executor wake-up each),
  paired with the depth by header stamp with
  :class:`endo_io.stamp_matching.StampMatcher` (exact stamps by default), so a
  frame never mixes two images;
* ``/endoscope/pose`` (``T_world_camera`` on the camera clock, from the tracker
  bridge) into a :class:`endo_io.pose_buffer.PoseBuffer`, taken the same way
  (:data:`endo_io.qos.PASSIVE_POSE_QOS`, 2 s of a 250 Hz tracker): when a
  depth arrives, at each pose that arrives while a frame waits for its pose
  (:meth:`endo_io.diagnostics.PassiveInput.wake_on_arrival`: the frame goes
  as soon as the pose after its stamp is in, with no polling timer) and at
  least every :data:`endo_io.qos.PASSIVE_POSE_TAKE_PERIOD_S` (0.1 s), so no
  pose is overwritten in DDS while no depth comes (start-up, SFS stalled or
  slow). Likewise the image and camera_info wake the node at their arrival
  while a depth waits for them (it came first). Before each /diagnostics
  status the node also takes the waiting images and camera_infos, so the
  status's ages and counts of those inputs are theirs, not the depth's: with
  the depth stopped, only the depth is stale.

The poses and camera_infos are read from their CDR bytes without rclpy's
message objects (:func:`endo_io.pose.pose_stamped_from_cdr`,
:func:`endo_io.camera.camera_info_from_cdr`: the camera model is rebuilt
only when the bytes after the stamp change), the images as views of the
received bytes (:func:`endo_io.image.image_from_cdr`).

A complete frame waits (at most ``pose_wait_s``, checked at each pose that
arrives and at least every 0.1 s, and behind at most ``max_pending`` earlier
frames) until a pose after its stamp has arrived, then
takes the interpolated pose at its stamp. A frame whose pose cannot come
(a tracker dropout longer than ``pose_max_gap_s``, a wait that ran out) is
counted under the lookup error's name and processed without a pose: tracking
continues and its depth is published with the held scale, but it gives no
triangulation, no world points and no map update. It is never paired with a
stale pose.

Publications (reliable, QoS overridable):

* ``/endoscope/points``: the frame's world cloud, PointCloud2 (x, y, z, rgb
  grey from the image) in ``world_frame``, every ``cloud_decimation``-th
  pixel per axis (4: a 16th of the pixels); published first (the graph's
  latency is timed to it);
* ``/endoscope/depth``: metric depth, 32FC1 metres, NaN invalid (REP 118), the
  image's header, so ``/endoscope/camera_info`` describes it; nothing before
  the scale has converged once;
* ``/endoscope/map``: the fused voxel map, PointCloud2 in ``world_frame``,
  transient-local. While frames come it goes right after a frame (the
  longest wait for the next), at most every ``map_period_s`` and at most
  ``map_bandwidth_mb_s`` megabytes per second
  (:class:`endo_flow.map_schedule.MapPublishSchedule`), thinned evenly to
  about ``map_stream_max_points`` voxels; once they stop, the whole map goes
  (and then a changed one every ``map_period_s``). The map fuses every
  ``map_decimation``-th pixel (1: full resolution) of every ``map_every``-th
  frame with world points, from the same back-projection as the topic's
  cloud (:func:`endo_flow.cloud.world_clouds`);
* ``/endoscope/scale``: ``geometry_msgs/Vector3Stamped`` with x = s (metres
  per unit of depth_relative), y = the standard deviation of ln s, z = the
  state (:class:`endo_flow.scale.ScaleState`: 0 initializing, 1 tracking,
  2 holding, 3 recovering); header = the frame's (why this type:
  :mod:`endo_flow.messages`);
* ``/diagnostics``: frames and poses received, frames processed, dropped per
  cause and lost in transport (stamp gaps), clock jumps, and the scale, its
  state and the track counts (:class:`endo_io.diagnostics.InputHealth`).

Services (std_srvs/Trigger): ``~/reset_map`` empties the map; ``~/export_map``
writes it to ``ply_path`` as binary PLY (:func:`endo_flow.voxel_map.write_ply`).

Before its publishers and subscriptions exist, the node runs the pipeline's
first-frame work on synthetic frames of the ``warm_up_camera_file`` camera
(:func:`endo_flow.warm_up.warm_up_pipeline`), so its first real frames are
not slow; ``--help`` skips that.

Bad input (one log line, counted, that frame dropped, the node keeps running):
an image that is not 16UC1/32FC1, a depth that is not 32FC1, a depth_relative
or image of another size than camera_info, a NaN pose (rejected by the pose
buffer), a textureless frame, undecodable CDR. Time that jumps (a looping bag,
a restarted camera: :mod:`endo_io.clock_jump`, on the frames' stamps, and the
pose buffer's own on the poses') resets the tracks, the scale filter and the
map with one log line, counted as ``clock_jumps``, and tracking resumes; one
frame stamped far in the future is dropped (``FutureStampError``).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

from endo_flow.errors import FlowError, FlowInputError
from endo_flow.map_schedule import MapPublishSchedule
from endo_flow.messages import grey_cloud_cdr, scale_message
from endo_flow.pipeline import (
    SCALE_OBSERVATIONS,
    FlowFrame,
    FlowOptions,
    FlowOutput,
    FlowPipeline,
)
from endo_flow.scale import ScaleFilterOptions
from endo_flow.shape_correction import SHAPE_CORRECTION_MODES, ShapeCorrectionOptions
from endo_flow.tracking import TrackingOptions
from endo_flow.warm_up import warm_up_pipeline
from endo_io import topics
from endo_io.camera import CameraInfoCache, CameraInfoView, CameraModel, camera_info_from_cdr
from endo_io.clock_jump import ClockJumpDetector
from endo_io.diagnostics import HEALTH_PARAMETERS, InputHealth
from endo_io.errors import (
    ClockJumpError,
    Endo3dError,
    ParameterValidationError,
    PoseBeforeStreamError,
    PoseLookupError,
    PoseNotYetError,
)
from endo_io.image import (
    IRRADIANCE_ENCODINGS,
    ImageMessage,
    array_to_image_cdr,
    image_from_cdr,
    image_to_array,
    image_to_irradiance,
)
from endo_io.parameters import NodeParameters, ParameterSpec
from endo_io.pointcloud import records_to_pointcloud2_cdr
from endo_io.pose import PoseView, pose_stamped_from_cdr, pose_to_matrix
from endo_io.pose_buffer import PoseBuffer
from endo_io.process import describing_only, run_node
from endo_io.qos import (
    BY_STAMP_QOS,
    MAP_QOS,
    NEWEST_FRAME_QOS,
    PASSIVE_POSE_QOS,
    PASSIVE_POSE_TAKE_PERIOD_S,
    create_reliable_publisher,
)
from endo_io.stamp import NS_PER_S, stamp_to_ns
from endo_io.stamp_matching import StampMatcher

#: The frames have stopped after this long without one (seconds), or after
#: :data:`STOPPED_AFTER_INTERVALS` of their usual interval when they come slower: the
#: rest of a deferred map frame is then fused at once (the node otherwise fuses it a
#: band per frame) and the whole map goes.
MAP_FINISH_AFTER_S = 0.5
#: Usual frame intervals without a frame that mean the frames stopped (review,
#: session 13: at under 2 Hz every gap sent the whole map, and the live view flickered
#: between thinned and whole).
STOPPED_AFTER_INTERVALS = 3.0
#: Weight of the newest interval in the usual one (an exponential average).
INTERVAL_WEIGHT = 0.25
#: Intervals longer than this count as this long in the usual one (seconds): frames
#: slower than 1 every 2 s are taken as stopping between them.
LONGEST_INTERVAL_S = 2.0

#: The camera warmed up on when ``warm_up_camera_file`` is empty (small: only
#: the map's kernels matter then).
WARM_UP_DEFAULT_CAMERA = CameraModel.pinhole(160, 120, 140.0, 140.0, 79.5, 59.5)

PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("world_frame", topics.WORLD_FRAME,
                  "frame id of the world cloud and the map (the tracker's world)",
                  read_only=True),
    ParameterSpec("stamp_tolerance", 0.0,
                  "largest stamp difference of image, depth_relative and camera_info in one "
                  "frame, seconds (0: exact)", range=(0.0, 1.0), read_only=True),
    ParameterSpec("queue_size", 10,
                  "unmatched messages of each stream kept while waiting for partners",
                  range=(1, 1000), read_only=True),
    ParameterSpec("pose_wait_s", 0.2,
                  "longest time a frame waits for a pose after its stamp, seconds",
                  range=(0.0, 5.0)),
    ParameterSpec("max_pending", 5, "frames that may wait for poses at once; older ones go "
                  "on without a pose", range=(1, 100)),
    ParameterSpec("pose_max_gap_s", 0.1,
                  "longest interval between two poses that is interpolated, seconds",
                  range=(0.0, 2.0), read_only=True),
    ParameterSpec("max_tracks", 200, "Lucas–Kanade tracks kept alive", range=(8, 2000),
                  read_only=True),
    ParameterSpec("tracking_downsample", 2,
                  "integer factor from the image to the tracking resolution", range=(1, 8),
                  read_only=True),
    ParameterSpec("pyramid_levels", 2, "Lucas–Kanade pyramid levels above the base",
                  range=(0, 6), read_only=True),
    ParameterSpec("reseed_every", 10, "seed new features at least every this many frames "
                  "(0: only when tracks run low)", range=(0, 1000), read_only=True),
    ParameterSpec("min_parallax_deg", 4.0, "least parallax of a triangulated track, degrees",
                  range=(0.1, 60.0), read_only=True),
    ParameterSpec("min_baseline_m", 2.0e-3,
                  "least camera-centre baseline of a triangulated track, metres",
                  range=(0.0, 0.1), read_only=True),
    ParameterSpec("scale_observation", "triangulation",
                  "how a frame observes the scale: its triangulated tracks' depth ratios, or "
                  "the scale-only reprojection fit of SFS's points over the keyframe window",
                  choices=SCALE_OBSERVATIONS, read_only=True),
    ParameterSpec("pose_smoothing_s", 0.3,
                  "half-width of the pose smoothing of keyframes, seconds (0: raw poses)",
                  range=(0.0, 2.0), read_only=True),
    ParameterSpec("scale_process_noise", 0.003,
                  "random-walk density of ln s per square-root second", range=(0.0, 1.0),
                  read_only=True),
    ParameterSpec("shape_correction", "none",
                  "smooth correction field of the SFS depth from the metric points",
                  choices=SHAPE_CORRECTION_MODES, read_only=True),
    ParameterSpec("cloud_decimation", 4,
                  "/endoscope/points takes every n-th pixel per axis (the map has its own, "
                  "map_decimation)", range=(1, 32)),
    ParameterSpec("map_enabled", True, "fuse the world clouds into the voxel map",
                  read_only=True),
    ParameterSpec("map_decimation", 1,
                  "the map fuses every n-th pixel per axis of the metric depth (1: full "
                  "resolution)", range=(1, 32)),
    ParameterSpec("map_every", 8,
                  "the map fuses every n-th frame with world points (the live map's CPU "
                  "knob: it keeps the resolution; 8: docs/flow.md)", range=(1, 100)),
    ParameterSpec("map_voxel_size_m", 1e-3, "voxel edge of the map, metres",
                  range=(1e-5, 0.1), read_only=True),
    ParameterSpec("map_max_voxels", 2_000_000,
                  "map capacity (memory bound); the voxels seen longest ago go first",
                  range=(1000, 100_000_000), read_only=True),
    ParameterSpec("map_period_s", 2.0, "shortest publishing period of the map, seconds",
                  range=(0.1, 3600.0), read_only=True),
    ParameterSpec("map_bandwidth_mb_s", 2.0,
                  "while frames come, the map is published after a frame at most at this "
                  "many megabytes per second: after a map of B MB the next waits B / this "
                  "seconds (at least map_period_s); once frames stop, every map_period_s; "
                  "0: no budget, at most every map_period_s (docs/flow.md)",
                  range=(0.0, 10_000.0), read_only=True),
    ParameterSpec("map_stream_max_points", 125_000,
                  "while frames come, the map message holds about this many voxels at most, "
                  "an even thinning that keeps the same voxels from one message to the next "
                  "(4 MB at 125000); once frames stop, the whole map; ~/export_map and "
                  "endo-process always write the whole map; 0: the whole map always "
                  "(docs/flow.md)",
                  range=(0, 100_000_000), read_only=True),
    ParameterSpec("map_min_count", 1, "voxels fused from fewer points are not published or "
                  "exported", range=(1, 1000)),
    ParameterSpec("ply_path", "endo3d_map.ply", "file ~/export_map writes"),
    ParameterSpec("warm_up_camera_file", "",
                  "camera_calibration YAML of the camera whose frames will come: before it "
                  "subscribes, the node tracks synthetic frames of that size and fuses a "
                  "synthetic cloud (OpenCV buffers, the map's kernels), so that its first "
                  "frames cost what later ones do; empty: the map's kernels only",
                  read_only=True),
    *HEALTH_PARAMETERS,
)


def pipeline_options(values: dict[str, Any]) -> FlowOptions:
    """The pipeline settings the parameter values describe."""
    base = FlowOptions()
    tracking = replace(TrackingOptions(), max_tracks=values["max_tracks"],
                       downsample=values["tracking_downsample"],
                       pyramid_levels=values["pyramid_levels"],
                       reseed_every=values["reseed_every"])
    gates = replace(base.gates, min_parallax_rad=float(np.radians(values["min_parallax_deg"])),
                    min_baseline_m=values["min_baseline_m"])
    return replace(
        base, tracking=tracking, gates=gates,
        scale=replace(ScaleFilterOptions(), process_noise=values["scale_process_noise"]),
        shape=ShapeCorrectionOptions(mode=values["shape_correction"]),
        pose_smoothing_s=values["pose_smoothing_s"],
        scale_observation=values["scale_observation"],
        cloud_decimation=values["cloud_decimation"], map_enabled=values["map_enabled"],
        map_decimation=values["map_decimation"], map_every=values["map_every"],
        voxel_size_m=values["map_voxel_size_m"], max_voxels=values["map_max_voxels"],
    )


@dataclass
class _Pending:
    """A complete frame waiting for its pose."""

    stamp_ns: int
    image: ImageMessage
    depth: ImageMessage
    info: CameraInfo | CameraInfoView
    deadline: float


class FlowNode(Node):
    """The ``flow`` node (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("flow", **kwargs)
        self.parameters = NodeParameters(self, PARAMETERS)
        values = self.parameters.values()
        self.parameters.on_change(self._apply)
        options = pipeline_options(values)
        if not describing_only():  # --help lists parameters and must not warm up
            self._warm_up(options, values["warm_up_camera_file"])
        self.pipeline = FlowPipeline(options)
        tolerance_ns = round(values["stamp_tolerance"] * NS_PER_S)
        self._images: StampMatcher[ImageMessage, CameraInfo | CameraInfoView] = StampMatcher(
            values["queue_size"], tolerance_ns)
        self._frames: StampMatcher[tuple[ImageMessage, CameraInfo | CameraInfoView],
                                   ImageMessage] = StampMatcher(values["queue_size"], tolerance_ns)
        self.poses = PoseBuffer(capacity=6000,
                                max_gap_ns=round(values["pose_max_gap_s"] * NS_PER_S))
        self._pending: deque[_Pending] = deque()
        self._cameras = CameraInfoCache()
        self.health = InputHealth(self, "frames", settings=self.parameters)
        self.pose_health = InputHealth(self, "poses", settings=self.parameters)
        self._frame_time = ClockJumpDetector()
        self.depth_pub = create_reliable_publisher(self, Image, topics.DEPTH)
        self.points_pub = create_reliable_publisher(self, PointCloud2, topics.POINTS, depth=2)
        self.scale_pub = create_reliable_publisher(self, Vector3Stamped, topics.SCALE)
        self.map_pub = self.create_publisher(PointCloud2, topics.MAP, MAP_QOS)
        # "processed" counts frames (_process), not the inputs' messages. The depth
        # drives a frame: only the newest is processed, stale ones are skipped. The
        # image, camera_info and poses wait in DDS and are taken when a depth comes
        # (no executor wake-up for each: rclpy rebuilds its whole wait set at each),
        # except while a frame waits for them (wake_on_arrival).
        # image_from_cdr: the pixels stay a view of the received bytes (no copy)
        self.health.subscribe(Image, topics.DEPTH_RELATIVE, self._on_depth, NEWEST_FRAME_QOS,
                              processed=False, gaps=True, newest=True, decode=image_from_cdr)
        self._image_input = self.health.subscribe_passive(
            Image, topics.IMAGE_CORRECTED, lambda msg, _: self._on_image(msg), BY_STAMP_QOS,
            decode=image_from_cdr)
        self._info_input = self.health.subscribe_passive(
            CameraInfo, topics.CAMERA_INFO, lambda msg, _: self._on_info(msg), BY_STAMP_QOS,
            decode=camera_info_from_cdr)
        self._pose_input = self.pose_health.subscribe_passive(
            PoseStamped, topics.CAMERA_POSE, self._on_pose, PASSIVE_POSE_QOS, processed=True,
            decode=pose_stamped_from_cdr, on_arrival=self._take_poses)
        self.pose_health.on_refresh(self._take_poses)
        # the image and camera_info counted and aged as theirs, even while no depth comes
        self.health.on_refresh(self._take_frame_inputs)
        self.health.watch_matching(self._images, topics.IMAGE_CORRECTED, topics.CAMERA_INFO)
        self.health.watch_matching(self._frames, "image + camera_info", topics.DEPTH_RELATIVE)
        # until when a depth that came before its image or camera_info retakes them
        self._inputs_due = 0.0
        self.create_service(Trigger, "~/reset_map", self._reset_map)
        self.create_service(Trigger, "~/export_map", self._export_map)
        # poses taken even while no depth comes (their DDS history holds 2 s at 250 Hz),
        # and the deadlines of waiting frames checked while no pose comes
        self.create_timer(PASSIVE_POSE_TAKE_PERIOD_S, self._tick)
        self.create_timer(values["map_period_s"], self._on_map_timer)
        # the map's revision last published: whatever changed it since (a band, process()
        # fusing the rest of a deferred frame, a reset) makes it go again; the warm-up's
        # fused-then-emptied map is not a change anyone needs to see
        voxel_map = self.pipeline.voxel_map
        self._published_revision = 0 if voxel_map is None else voxel_map.revision
        self._published_whole = True  # whether the last map sent held every voxel
        self._map_schedule = MapPublishSchedule(values["map_period_s"],
                                                values["map_bandwidth_mb_s"])
        self._last_frame_s = time.monotonic()
        self._frame_interval_s = 0.0  # the usual interval between frames (smoothed)
        self._last_frame_ns = 0  # the stamp of the last frame published (map errors name it)
        self.get_logger().info(
            f"flow: {topics.IMAGE_CORRECTED} + {topics.DEPTH_RELATIVE} + {topics.CAMERA_INFO} "
            f"+ {topics.CAMERA_POSE} -> {topics.DEPTH}, {topics.POINTS}, {topics.MAP}, "
            f"{topics.SCALE}; shape_correction={values['shape_correction']}"
        )

    def _warm_up(self, options: FlowOptions, path: str) -> None:
        """Run the pipeline's first-frame work on synthetic frames (see :mod:`endo_flow.warm_up`).

        Raises:
            ParameterValidationError: ``path`` does not load as a camera.
        """
        camera = WARM_UP_DEFAULT_CAMERA
        if path:
            try:
                camera = CameraModel.load_yaml(path)
            except (OSError, Endo3dError) as error:
                raise ParameterValidationError(
                    f"parameter warm_up_camera_file: {path} is not a camera_calibration YAML: "
                    f"{error}"
                ) from None
        seconds = warm_up_pipeline(options, camera)
        grey_cloud_cdr(np.zeros((1, 3), np.float32), np.zeros(1, np.uint8), 0,
                       self.parameters["world_frame"])
        self.get_logger().info(
            f"warmed up on a {camera.width}x{camera.height} frame"
            f"{f' of {path}' if path else ''} in {seconds:.2f} s"
        )

    # ------------------------------------------------------------------ parameters

    def _apply(self, changes: Mapping[str, Any], values: Mapping[str, Any]) -> None:
        cloud = {name: changes[name] for name in ("cloud_decimation", "map_decimation",
                                                  "map_every") if name in changes}
        if cloud:
            # these only change the clouds; the pipeline keeps its state
            self.pipeline.set_cloud_options(**cloud)

    # ------------------------------------------------------------------ inputs

    def _take_frame_inputs(self) -> None:
        """Take the images and camera_infos waiting in DDS into the stamp matchers."""
        self._image_input.take()
        self._info_input.take()

    def _take_poses(self) -> None:
        """Take the poses waiting in DDS into the pose buffer, then process what can go."""
        self._pose_input.take()
        self._drain()

    def _tick(self) -> None:
        """The periodic take: poses (and what can go), and the end of a wait for inputs.

        When the frames have stopped (a bag's end, a paused camera) for
        :data:`MAP_FINISH_AFTER_S`, the rest of a deferred map frame is fused,
        so the map and its export hold what endo-process's would.
        """
        if self._inputs_due and time.monotonic() >= self._inputs_due:
            self._wait_for_inputs(False)
        self._take_poses()
        if self.pipeline.map_pending and self._frames_stopped(time.monotonic()):
            self._fuse_map(1)

    def _wait_for_inputs(self, wait: bool) -> None:
        """Whether the image and camera_info wake the node at their arrival (a depth waits)."""
        self._inputs_due = time.monotonic() + self.parameters["pose_wait_s"] if wait else 0.0
        self._image_input.wake_on_arrival(wait)
        self._info_input.wake_on_arrival(wait)

    def _on_image(self, msg: ImageMessage) -> None:
        self._offer_pair(self._images.add_first(stamp_to_ns(msg.header.stamp), msg))

    def _on_info(self, msg: CameraInfo) -> None:
        self._offer_pair(self._images.add_second(stamp_to_ns(msg.header.stamp), msg))

    def _on_depth(self, msg: ImageMessage) -> None:
        self._take_frame_inputs()
        self._take_poses()
        pair = self._frames.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._enqueue(pair.stamp_ns, pair.first[0], msg, pair.first[1])
        else:  # its image or camera_info is not here yet: woken by them, as long as a pose
            self._wait_for_inputs(True)  # would be waited for

    def _offer_pair(self, pair: Any) -> None:
        if pair is None:
            return
        triple = self._frames.add_first(pair.stamp_ns, (pair.first, pair.second))
        if triple is not None:
            if self._inputs_due and not self._frames.pending()[1]:
                self._wait_for_inputs(False)  # no depth waits for its inputs any more
            self._enqueue(triple.stamp_ns, pair.first, triple.second, pair.second)

    def _on_pose(self, msg: PoseStamped | PoseView, arrival_ns: int) -> None:
        T, stamp = pose_to_matrix(msg)
        self.poses.insert(stamp, T, arrival_ns=arrival_ns)

    def _enqueue(self, stamp_ns: int, image: ImageMessage, depth: ImageMessage,
                 info: CameraInfo | CameraInfoView) -> None:
        wait = self.parameters["pose_wait_s"]
        self._pending.append(_Pending(stamp_ns, image, depth, info, time.monotonic() + wait))
        self._drain()

    def _drain(self) -> None:
        """Process waiting frames in order while their pose is known or cannot come.

        While a frame is left waiting, each pose that arrives wakes the node.
        """
        self._drain_ready()
        self._pose_input.wake_on_arrival(bool(self._pending))

    def _drain_ready(self) -> None:
        now = time.monotonic()
        while self._pending:
            head = self._pending[0]
            pose: np.ndarray | None = None
            missing: PoseLookupError | None = None
            try:
                pose = self.poses.query(head.stamp_ns)
            except PoseNotYetError as error:
                too_many = len(self._pending) > self.parameters["max_pending"]
                if now < head.deadline and not too_many:
                    return  # the pose may still come; later frames wait behind this one
                missing = error.with_traceback(None)
            except PoseLookupError as error:
                # Without its traceback: kept in a local, the traceback would make a cycle
                # through this frame, which holds the frame's images (2.4 MB) until a full
                # garbage collection, minutes later (flow's RSS sawtooth in the soak).
                missing = error.with_traceback(None)
            self._pending.popleft()
            if missing is not None:
                self.health.drop(type(missing).__name__,
                                 f"frame {head.stamp_ns} ns has no pose, processed without: "
                                 f"{missing}",
                                 expected=isinstance(missing, PoseBeforeStreamError))
            self._process(head, pose)

    # ------------------------------------------------------------------ processing

    def _camera_model(self, info: CameraInfo | CameraInfoView) -> CameraModel:
        return self._cameras.model_of(info)[0]  # rebuilt only for another camera

    def _process(self, pending: _Pending, pose: np.ndarray | None) -> None:
        if self._frame_time.is_late(pending.stamp_ns):
            # paired after a newer frame was processed (its image or camera_info came
            # late): stale, skipped like a depth passed over for a newer one
            self.health.skip(topics.DEPTH_RELATIVE)
            return
        try:
            out = self._step(pending, pose)
        except ClockJumpError as error:  # the pipeline reset itself; this frame is dropped
            self.health.clock_jump(str(error))
            self._map_was_reset()
            return
        except Endo3dError as error:
            self.health.drop(type(error).__name__, str(error))
            return
        except Exception as error:  # a bug on one frame must not stop the node
            self.health.drop(type(error).__name__, f"unexpected: {error}")
            return
        self.health.ok()
        self._publish(pending, out)
        now = time.monotonic()
        if self._last_frame_ns:  # not the first frame: how long since the last one
            # a long stop (a bag's end, a pause) is not a frame rate: at most LONGEST_INTERVAL_S
            interval = min(now - self._last_frame_s, LONGEST_INTERVAL_S)
            self._frame_interval_s = interval if not self._frame_interval_s else (
                INTERVAL_WEIGHT * interval + (1.0 - INTERVAL_WEIGHT) * self._frame_interval_s)
        self._last_frame_s = now
        self._last_frame_ns = pending.stamp_ns
        # After the frame's outputs, the longest wait for the next frame: either the map,
        # when its budget allows (this frame's slot then holds no band), or a band of rows
        # of the map's full-resolution cloud and insert (map_every frames share each fused
        # frame's work; a band left out is fused with the next fused frame).
        if self._map_changed and self._map_schedule.due(now):
            self._publish_map(now, whole=False)
        else:
            self._fuse_map(self.pipeline.options.map_every)

    def _fuse_map(self, parts: int) -> None:
        """The next 1/parts of a deferred map frame; a failure is counted, never raised."""
        try:
            self.pipeline.fuse_deferred_map(parts=parts)
        except Exception as error:  # the frame is out; a map failure must not stop the node
            self.health.drop(type(error).__name__,
                             f"map fusion after frame {self._last_frame_ns} ns: {error}")

    def _step(self, pending: _Pending, pose: np.ndarray | None) -> FlowOutput:
        if pending.image.encoding not in IRRADIANCE_ENCODINGS:
            raise FlowInputError(
                f"image_corrected must be 16UC1 or 32FC1, got {pending.image.encoding!r}")
        if pending.depth.encoding != "32FC1":
            raise FlowInputError(f"depth_relative must be 32FC1, got {pending.depth.encoding!r}")
        camera = self._camera_model(pending.info)
        frame = FlowFrame(pending.stamp_ns, image_to_irradiance(pending.image),
                          image_to_array(pending.depth), camera, pose)
        jump = self._frame_time.check(pending.stamp_ns, time.monotonic_ns())
        if jump is not None:
            self.pipeline.reset()
            self._map_was_reset()
            self.health.clock_jump(
                f"{jump.describe('frame time')}; tracks, scale filter and map reset"
            )
        return self.pipeline.process(frame, defer_map=True)

    def _publish(self, pending: _Pending, out: FlowOutput) -> None:
        header = pending.image.header
        if out.depth is not None:
            # the cloud first: the graph's end-to-end latency is timed to its arrival
            if len(out.points):
                self.points_pub.publish(grey_cloud_cdr(out.points, out.intensity,
                                                       pending.stamp_ns,
                                                       self.parameters["world_frame"]))
            # CDR bytes built directly: one copy of the pixels, not the message's and rclpy's
            self.depth_pub.publish(array_to_image_cdr(out.depth, "32FC1",
                                                      stamp_to_ns(header.stamp),
                                                      header.frame_id))
        self.scale_pub.publish(scale_message(out.scale, pending.stamp_ns, header.frame_id))
        d = out.diagnostics
        for key, value in (("scale", f"{out.scale.value:.6g}"),
                           ("scale_log_std", f"{out.scale.log_std:.3g}"),
                           ("scale_state", out.scale.state.name),
                           ("tracks", d.tracks), ("triangulated", d.triangulated),
                           ("scale_gated", self.pipeline.scale_filter.gated),
                           ("scale_steps", self.pipeline.scale_filter.steps),
                           ("shape_correction_active", d.shape_correction),
                           ("map_voxels", len(self.pipeline.voxel_map or ())),
                           ("camera_changes", self.pipeline.camera_changes)):
            self.health.set_value(key, value)
        if d.gated:
            self.get_logger().warning(
                f"scale observation {d.observation:.4g} gated (filter at {out.scale.value:.4g})",
                throttle_duration_sec=1.0)

    # ------------------------------------------------------------------ map

    def _on_map_timer(self) -> None:
        """Frames stopped: a changed (or thinned) map goes whole every ``map_period_s``.

        While frames come, the map goes after a frame instead (:meth:`_process`).
        """
        now = time.monotonic()
        if (self._map_changed or not self._published_whole) and self._frames_stopped(now):
            self._publish_map(now, whole=True)

    def _frames_stopped(self, now: float) -> bool:
        """Whether the frames stopped: no frame for 0.5 s, or for 3 of their usual intervals."""
        wait = max(MAP_FINISH_AFTER_S, STOPPED_AFTER_INTERVALS * self._frame_interval_s)
        return now - self._last_frame_s > wait

    def _publish_map(self, now: float, *, whole: bool) -> None:
        """Publish the map (``now``: the monotonic clock, for the budget).

        ``whole``: every voxel; otherwise a map larger than
        ``map_stream_max_points`` goes thinned to about that many
        (:meth:`endo_flow.voxel_map.VoxelMap.published_records`): the cost of a
        publish, in the node's thread and in every subscriber, grows with the
        message (docs/flow.md, "The live map's size").
        """
        voxel_map = self.pipeline.voxel_map
        if voxel_map is None:
            return
        cap = self.parameters["map_stream_max_points"]
        fraction = 1.0 if whole or cap == 0 or len(voxel_map) <= cap else cap / len(voxel_map)
        records, finite = voxel_map.published_records(self.parameters["map_min_count"],
                                                      fraction=fraction)
        stamp = self.get_clock().now().nanoseconds
        message = records_to_pointcloud2_cdr(
            records, stamp, self.parameters["world_frame"], is_dense=finite)
        self.map_pub.publish(message)
        # the budget is the stream's: a whole map sent while frames stopped does not
        # hold back the next thinned one when they come again
        self._map_schedule.published(now, 0 if whole else len(message))
        self._published_revision = voxel_map.revision
        self._published_whole = fraction == 1.0

    @property
    def _map_changed(self) -> bool:
        """Whether the map changed since it was last published."""
        voxel_map = self.pipeline.voxel_map
        return voxel_map is not None and voxel_map.revision != self._published_revision

    def _map_was_reset(self) -> None:
        """An emptied map goes after the next frame, whatever the budget of the last one."""
        self._map_schedule.reset()

    def _reset_map(self, _request: Trigger.Request, response: Trigger.Response
                   ) -> Trigger.Response:
        if self.pipeline.voxel_map is None:
            response.success, response.message = False, "the map is disabled (map_enabled)"
            return response
        dropped = self.pipeline.reset_map()
        self._map_was_reset()
        response.success, response.message = True, f"map reset ({dropped} voxels dropped)"
        self.get_logger().info(response.message)
        return response

    def _export_map(self, _request: Trigger.Request, response: Trigger.Response
                    ) -> Trigger.Response:
        voxel_map = self.pipeline.voxel_map
        path = Path(self.parameters["ply_path"]).expanduser()
        if voxel_map is None:
            response.success, response.message = False, "the map is disabled (map_enabled)"
            return response
        self._fuse_map(1)  # the rows of a deferred frame still waiting
        try:
            count = voxel_map.export_ply(path, self.parameters["map_min_count"])
        except FlowError as error:
            response.success, response.message = False, str(error)
            return response
        response.success, response.message = True, f"wrote {count} points to {path.resolve()}"
        self.get_logger().info(response.message)
        return response


def main(args: list[str] | None = None) -> int:
    """Console entry point ``endo-flow``."""
    return run_node(FlowNode, args, restart_on_lost_port=True)
