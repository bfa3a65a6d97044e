"""``endo-tracker-bridge``: one tracker in, the endoscope camera pose out.

Parameter ``source`` picks the input (``ros``, ``igtl``, ``ndi``, ``csv``);
``source=ros`` listens on ``/tracker/pose`` by default, where tracker
drivers and the sample bags publish. Each accepted marker pose is published
twice (names from :mod:`endo_io.topics`):

* ``/tracker/marker_pose``: the validated T_tracker_marker, frame
  ``tracker``, metres, stamped with the tracker's own stamp (what
  ``endo-handeye`` can read back);
* ``/endoscope/pose``: T_world_camera = T_world_tracker · T_tracker_marker ·
  T_marker_camera, frame ``world``, stamped at the tracker stamp minus the
  calibrated time offset (camera clock).

With ``publish_tf`` (default on) and where ``tf2_msgs`` is importable (a full
ROS install), the same transforms go out as tf2 does (:mod:`endo_io.tf_broadcast`,
the frame tree of :mod:`endo_io.tf`): ``/tf`` world → ``camera_frame`` at
each camera pose's stamp, ``/tf_static`` (transient local) world → tracker
and ``camera_frame`` → marker, sent at start and after each change of the
transform, the hand–eye file or a frame name. Pip-only, one info line says
where the transforms are served instead.

An input topic equal to one of these outputs is refused at start-up (one
line, exit code 2) and as a run-time change: the bridge would read its own
poses. Every parameter can be changed at run time and the change takes
effect (a new source, hand–eye file, transform, limits or frame); a value
that cannot work is refused with the reason and changes nothing.

Rejected samples (NaN, non-unit quaternion, tool missing, a repeated
stamp, speed jump, bad message) are dropped and counted by cause on
``/diagnostics``; the node keeps running, and network/serial sources
reconnect by themselves. Time that jumps (a looped recording, a restarted
driver: any step back, :mod:`endo_io.clock_jump`) resets the tool's history with one log
line, counted as ``clock_jumps``, and the stream goes on; one sample stamped
far in the future is dropped (``FutureStampError``) and locks nothing out.
The status is WARN while the tracker input is silent (``input_stale_s``) or,
for a network or serial source, not connected; the source's state
(``connected``, ``connections``, ...) is refreshed every period.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.subscription import Subscription

from endo_io import topics
from endo_io.diagnostics import HEALTH_PARAMETERS, InputHealth
from endo_io.errors import ParameterValidationError
from endo_io.parameters import NodeParameters, ParameterSpec
from endo_io.pose import matrix_to_pose
from endo_io.process import run_node
from endo_io.qos import POSE_STREAM_QOS, create_reliable_publisher
from endo_io.tf import FrameNames, StampedTransform, camera_transform, static_transforms
from endo_io.tf_broadcast import TfBroadcaster
from endo_tracker_bridge.chain import CameraPoseChain
from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.errors import TrackerSourceError
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.sample import TrackerSample
from endo_tracker_bridge.sources.background import BackgroundSource
from endo_tracker_bridge.sources.ndi import TRACKER_TYPES
from endo_tracker_bridge.sources.ros import sample_from_pose_stamped
from endo_tracker_bridge.validation import (
    DEFAULT_ROTATION_TOLERANCE,
    SpeedLimits,
    check_rotation_matrix,
)

SOURCES = ("ros", "igtl", "ndi", "csv")
UNITS = tuple(unit.value for unit in LengthUnit)
IGTL_STAMPS = ("message", "receive")
IDENTITY_ROWS = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]

#: Every parameter of the node. All of them can be changed at run time, and
#: each change takes effect: see :meth:`TrackerBridgeNode._apply_parameters`.
PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("source", "ros", "tracker input", choices=SOURCES),
    ParameterSpec(
        "handeye_file", "",
        "handeye.yaml from endo-handeye; empty: identity hand-eye, no time offset",
    ),
    ParameterSpec(
        "T_world_tracker", IDENTITY_ROWS,
        "16 row-major numbers, tracker frame → world frame, metres",
    ),
    ParameterSpec("world_frame", topics.WORLD_FRAME, f"frame_id of {topics.CAMERA_POSE}"),
    ParameterSpec("tracker_frame", topics.TRACKER_FRAME, f"frame_id of {topics.MARKER_POSE}"),
    ParameterSpec(
        "publish_tf", True,
        f"broadcast {topics.TF} (world → camera_frame at each camera pose) and "
        f"{topics.TF_STATIC} (world → tracker, camera_frame → marker) as tf2_msgs/TFMessage; "
        "needs tf2_msgs (a full ROS install), else one info line and nothing is sent",
    ),
    ParameterSpec(
        "camera_frame", topics.OPTICAL_FRAME,
        f"child frame of the camera's {topics.TF} transform: the images' frame_id",
    ),
    ParameterSpec(
        "max_speed_m_s", 2.0, "reject a marker moving faster than this (m/s)",
        range=(0.001, 1000.0),
    ),
    ParameterSpec(
        "max_angular_speed_deg_s", 720.0, "reject a marker turning faster than this (degrees/s)",
        range=(1.0, 1e6),
    ),
    ParameterSpec(
        "rotation_tolerance", DEFAULT_ROTATION_TOLERANCE,
        "allowed | |q| - 1 | and max |RᵀR - I| of input rotations", range=(1e-9, 0.1),
    ),
    ParameterSpec(
        "ros_topic", topics.TRACKER_POSE,
        "source=ros: PoseStamped topic of the tracker driver (not one of the bridge's outputs)",
    ),
    ParameterSpec("ros_unit", "m", "source=ros: unit of the driver's positions", choices=UNITS),
    ParameterSpec("ros_frame_id", "", "source=ros: expected header.frame_id; empty accepts any"),
    ParameterSpec("tool_id", "marker", "source=ros: name of the tool in diagnostics"),
    ParameterSpec("igtl_host", "127.0.0.1", "source=igtl: OpenIGTLink server host"),
    ParameterSpec("igtl_port", 18944, "source=igtl: OpenIGTLink server port", range=(1, 65535)),
    ParameterSpec(
        "igtl_device", "ScopeToTracker", "source=igtl: TRANSFORM device name; empty takes any"
    ),
    ParameterSpec(
        "igtl_unit", "mm", "source=igtl: unit of the TRANSFORM translation", choices=UNITS
    ),
    ParameterSpec(
        "igtl_stamp", "message",
        "source=igtl: stamp from the message header, or this host's receive time",
        choices=IGTL_STAMPS,
    ),
    ParameterSpec(
        "igtl_reconnect_interval_s", 0.5, "source=igtl: pause between reconnection attempts (s)",
        range=(0.01, 60.0),
    ),
    ParameterSpec(
        "igtl_stale_timeout_s", 0.0,
        "source=igtl: reconnect after this long without data (s); 0 disables",
        range=(0.0, 3600.0),
    ),
    ParameterSpec(
        "ndi_tracker_type", "polaris", "source=ndi: tracker model", choices=TRACKER_TYPES
    ),
    ParameterSpec("ndi_serial_port", "", "source=ndi: serial port (Polaris/Aurora); empty probes"),
    ParameterSpec("ndi_ip_address", "", "source=ndi: Vega IP address"),
    ParameterSpec("ndi_tcp_port", 8765, "source=ndi: Vega TCP port", range=(1, 65535)),
    ParameterSpec("ndi_romfiles", [""], "source=ndi: tool ROM files (Polaris/Vega)"),
    ParameterSpec(
        "ndi_tool_index", 0, "source=ndi: which tool of the frame to follow", range=(0, 64)
    ),
    ParameterSpec("ndi_rate_hz", 60.0, "source=ndi: polling rate (Hz)", range=(1.0, 400.0)),
    ParameterSpec(
        "ndi_max_rms_error_mm", 1.0,
        "source=ndi: reject a tool whose marker fit error exceeds this (mm); 0: no limit",
        range=(0.0, 100.0),
    ),
    ParameterSpec("csv_path", "", "source=csv: tracker log file"),
    ParameterSpec("csv_unit", "mm", "source=csv: unit of the log's translations", choices=UNITS),
    ParameterSpec(
        "csv_delimiter", "", "source=csv: column delimiter; empty detects tab/semicolon/comma"
    ),
    ParameterSpec("csv_tool", "", "source=csv: replay only rows of this tool; empty replays all"),
    ParameterSpec(
        "csv_rate", 1.0, "source=csv: replay speed factor; 0 = as fast as possible",
        range=(0.0, 1000.0),
    ),
    *HEALTH_PARAMETERS,
)

#: Parameters whose change re-sends /tf_static (or starts/stops the broadcaster).
TF_PARAMETERS = frozenset(
    {"publish_tf", "T_world_tracker", "handeye_file", "world_frame", "tracker_frame",
     "camera_frame"}
)

#: Parameters whose change restarts the source with the new values.
SOURCE_PARAMETERS = frozenset(
    {"source", "tool_id", "rotation_tolerance"}
    | {spec.name for spec in PARAMETERS if spec.name.startswith(("ros_", "igtl_", "ndi_", "csv_"))}
)


def world_tracker_from_parameter(values: Sequence[float]) -> np.ndarray:
    """T_world_tracker (4,4) from the 16 row-major numbers of the parameter (metres)."""
    if len(values) != 16:
        raise TrackerSourceError(f"T_world_tracker needs 16 row-major numbers, got {len(values)}")
    T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise TrackerSourceError("T_world_tracker must be a finite homogeneous transform")
    T[:3, :3] = check_rotation_matrix(T[:3, :3], tolerance=1e-6)
    return T


def _speed_limits(values: Mapping[str, Any]) -> SpeedLimits:
    return SpeedLimits(values["max_speed_m_s"], values["max_angular_speed_deg_s"])


def _frame_names(values: Mapping[str, Any]) -> FrameNames:
    """The frame tree's names from the parameters (the marker keeps its REP 103 name)."""
    return FrameNames(
        world=values["world_frame"], tracker=values["tracker_frame"], camera=values["camera_frame"]
    )


class TrackerBridgeNode(Node):
    """Reads one tracker source and publishes the marker and camera poses."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("tracker_bridge", **kwargs)
        self.parameters = NodeParameters(self, PARAMETERS)
        p = self.parameters.values()
        # The per-sample chain endo-process runs offline too: gate, compose, restamp.
        self._chain = CameraPoseChain(
            self._load_handeye(p["handeye_file"]),
            world_tracker_from_parameter(p["T_world_tracker"]),
            _speed_limits(p),
        )
        self._health = InputHealth(self, "tracker input", settings=self.parameters)
        self._health.on_refresh(self._refresh_source_status)
        self._input_name = ""
        self._marker_publisher = create_reliable_publisher(self, PoseStamped, topics.MARKER_POSE)
        self._camera_publisher = create_reliable_publisher(self, PoseStamped, topics.CAMERA_POSE)
        self._tf: TfBroadcaster | None = None
        self._frames = _frame_names(p)
        self._source: BackgroundSource | None = None
        self._subscription: Subscription | None = None
        self._wake: GuardCondition | None = None
        self._guarded_item = self._health.guard(self._process_item)
        source = self._build_source(p)  # refuses a configuration that cannot work first
        self._report_handeye(p["handeye_file"])
        self._apply_tf(p["publish_tf"], self._static_edges(p, self._chain.T_world_tracker,
                                                           self._chain.calibration))
        self._run_source(p, source)
        self.parameters.on_change(self._apply_parameters)

    # -- parameters ---------------------------------------------------------------

    def _apply_parameters(self, changes: Mapping[str, Any], values: Mapping[str, Any]) -> None:
        """Put accepted run-time changes into effect; nothing changes if one is refused.

        New values are checked first (the transform, the hand–eye file, the
        new source's configuration and input topic), then applied: limits
        at the next sample, frames at the next publish, a source parameter
        by stopping the source and starting one with the new values.

        Raises:
            Endo3dError: a value that cannot work (TrackerSourceError,
                HandEyeFileError, ParameterValidationError, ...); the
                reason the caller gets.
        """
        chain = self._chain
        T_world_tracker = chain.T_world_tracker
        if "T_world_tracker" in changes:
            T_world_tracker = world_tracker_from_parameter(values["T_world_tracker"])
        calibration = chain.calibration
        if "handeye_file" in changes:
            calibration = self._load_handeye(values["handeye_file"])
        restart = bool(changes.keys() & SOURCE_PARAMETERS)
        tf_change = bool(changes.keys() & TF_PARAMETERS)
        static = self._static_edges(values, T_world_tracker, calibration) if tf_change else []
        source = self._build_source(values) if restart else None
        chain.T_world_tracker = T_world_tracker
        chain.gate.limits = _speed_limits(values)
        if calibration is not chain.calibration:
            chain.calibration = calibration
            self._report_handeye(values["handeye_file"])
        if tf_change:
            self._frames = _frame_names(values)
            self._apply_tf(values["publish_tf"], static)
        if restart:
            self._stop_source()
            chain.reset()  # the new source's stamps start their own history
            self._run_source(values, source)

    def _load_handeye(self, path: str) -> HandEyeCalibration:
        return HandEyeCalibration.load(path) if path else HandEyeCalibration.identity()

    @property
    def calibration(self) -> HandEyeCalibration:
        """The hand–eye and clock calibration in use."""
        return self._chain.calibration

    def _report_handeye(self, path: str) -> None:
        offset_ms = self.calibration.time_offset_ns * 1e-6
        self._health.set_value("time_offset_ms", f"{offset_ms:.3f}")
        if path:
            self.get_logger().info(
                f"hand-eye from {path}: time offset {offset_ms:.3f} ms, "
                f"residuals {self.calibration.residuals}"
            )
        else:
            self.get_logger().warning(
                f"no handeye_file: {topics.CAMERA_POSE} is the marker pose "
                "(T_marker_camera = identity, no time offset)"
            )

    # -- transforms ---------------------------------------------------------------

    def _static_edges(
        self,
        values: Mapping[str, Any],
        T_world_tracker: np.ndarray,
        calibration: HandEyeCalibration,
    ) -> list[StampedTransform]:
        """The /tf_static edges for these values; checks the frame names too.

        Returns an empty list when ``publish_tf`` is off.

        Raises:
            TransformError: an empty frame name, or a frame that would be its
                own parent (e.g. ``camera_frame`` equal to ``world_frame``).
        """
        if not values["publish_tf"]:
            return []
        frames = _frame_names(values)
        camera_transform(np.eye(4), 0, frames=frames)  # world → camera must be a valid edge
        return static_transforms(
            T_world_tracker=T_world_tracker,
            T_marker_camera=calibration.T_marker_camera,
            stamp_ns=self.get_clock().now().nanoseconds,
            frames=frames,
        )

    def _apply_tf(self, publish: bool, static: list[StampedTransform]) -> None:
        """Start or stop the broadcaster and send the static edges."""
        if publish and self._tf is None:
            self._tf = TfBroadcaster(self)
        elif not publish and self._tf is not None:
            self._tf.close()
            self._tf = None
        if self._tf is None:
            state = "off"
        elif self._tf.available:
            state = f"{topics.TF} and {topics.TF_STATIC}"
        else:
            state = "not published (no tf2_msgs)"
        self._health.set_value("tf", state)
        if self._tf is not None:
            self._tf.send_static(static)

    @property
    def tf_broadcaster(self) -> TfBroadcaster | None:
        """The /tf broadcaster (None when ``publish_tf`` is off)."""
        return self._tf

    def _check_input_topic(self, topic: str) -> str:
        """The resolved input topic; refused when it is one of the bridge's own outputs.

        Raises:
            ParameterValidationError: the bridge would consume its own poses.
        """
        resolved = self.resolve_topic_name(topic)
        outputs = (self._marker_publisher.topic_name, self._camera_publisher.topic_name)
        if resolved in outputs:
            raise ParameterValidationError(
                f"parameter ros_topic: {topic!r} is the bridge's own output {resolved}; "
                f"set it to the tracker driver's topic (default {topics.TRACKER_POSE})"
            )
        return resolved

    # -- sources --------------------------------------------------------------------

    def _build_source(self, p: Mapping[str, Any]) -> BackgroundSource | None:
        """Check the source's configuration and build it, not yet running (None for ros).

        Raises:
            Endo3dError: a configuration that cannot work (a colliding
                ros_topic, an unreadable CSV log, ...).
        """
        log = self.get_logger().info
        source = p["source"]
        if source == "ros":
            self._check_input_topic(p["ros_topic"])
            return None
        if source == "igtl":
            from endo_tracker_bridge.sources.igtl import IgtlSource

            return IgtlSource(
                host=p["igtl_host"],
                port=p["igtl_port"],
                device_name=p["igtl_device"],
                unit=LengthUnit.parse(p["igtl_unit"]),
                stamp_from=p["igtl_stamp"],
                tolerance=p["rotation_tolerance"],
                reconnect_interval_s=p["igtl_reconnect_interval_s"],
                stale_timeout_s=p["igtl_stale_timeout_s"],
                log=log,
            )
        if source == "ndi":
            from endo_tracker_bridge.sources.ndi import NdiOptions, NdiSource

            options = NdiOptions(
                tracker_type=p["ndi_tracker_type"],
                serial_port=p["ndi_serial_port"],
                ip_address=p["ndi_ip_address"],
                tcp_port=p["ndi_tcp_port"],
                romfiles=tuple(f for f in p["ndi_romfiles"] if f),
                tool_index=p["ndi_tool_index"],
                rate_hz=p["ndi_rate_hz"],
                max_rms_error_mm=p["ndi_max_rms_error_mm"] or math.inf,
            )
            return NdiSource(options, p["rotation_tolerance"], log=log)
        from endo_tracker_bridge.sources.csv import CsvReplaySource

        return CsvReplaySource(
            p["csv_path"],
            unit=LengthUnit.parse(p["csv_unit"]),
            delimiter=p["csv_delimiter"],
            tool=p["csv_tool"],
            rate=p["csv_rate"],
            tolerance=p["rotation_tolerance"],
            log=log,
        )

    def _run_source(self, p: Mapping[str, Any], source: BackgroundSource | None) -> None:
        """Start reading ``source`` (built from ``p`` by :meth:`_build_source`)."""
        self._health.set_value("source", p["source"])
        if source is None:
            unit = LengthUnit.parse(p["ros_unit"])
            frame_id, tool_id, tolerance = p["ros_frame_id"], p["tool_id"], p["rotation_tolerance"]

            def on_pose(msg: PoseStamped) -> None:
                sample = sample_from_pose_stamped(msg, unit, frame_id, tool_id, tolerance)
                self._publish(sample)

            self._subscription = self._health.subscribe(
                PoseStamped, p["ros_topic"], on_pose, POSE_STREAM_QOS
            )
            self._input_name = self._subscription.topic_name
            self.get_logger().info(f"source ros: {self._subscription.topic_name} ({unit.value})")
            return
        # The source's thread wakes the executor through a guard condition, so
        # a pose is published as soon as it arrives, without a polling timer.
        self._input_name = f"{p['source']} source"
        self._health.watch(self._input_name)
        self._source = source
        self._wake = self.create_guard_condition(self._drain_source)
        source.start(self._wake.trigger)
        self.get_logger().info(f"source {p['source']} started")

    def _stop_source(self) -> None:
        """Stop the running source; poses it still held are dropped."""
        if self._input_name:
            self._health.unwatch(self._input_name)
            self._input_name = ""
        self._health.set_problem("connection", None)
        if self._subscription is not None:
            self.destroy_subscription(self._subscription)
            self._subscription = None
        if self._source is not None:
            self._source.stop()
            self._source = None
        if self._wake is not None:
            self.destroy_guard_condition(self._wake)
            self._wake = None

    def _drain_source(self) -> None:
        source = self._source
        if source is None:  # stopped while the wake-up was pending
            return
        for item in source.drain():
            self._health.received(self._input_name)
            self._guarded_item(source, item)
        self._refresh_source_status()

    def _refresh_source_status(self) -> None:
        """Copy the source's state into the status (each period, not only on data)."""
        source = self._source
        if source is None:
            return
        status = source.status()
        for key, value in status.items():
            self._health.set_value(key, value)
        connected = status.get("connected")
        where = status.get("server", "")
        self._health.set_problem(
            "connection",
            None if connected in (None, "True")
            else f"{self._input_name} not connected{f' to {where}' if where else ''}",
        )

    def _process_item(self, source: BackgroundSource, item: Any) -> None:
        self._publish(source.to_sample(item))

    # -- output ---------------------------------------------------------------------

    def _publish(self, sample: TrackerSample) -> None:
        """Gate the sample (raises to drop it), then publish the marker and camera poses."""
        pose = self._chain.accept(sample, time.monotonic_ns())
        if pose.clock_jump is not None:
            self._health.clock_jump(
                f"{pose.clock_jump.describe(f'tool {sample.tool_id!r} time')}; its history "
                "was reset"
            )
        tf = self._tf if self._tf is not None and self._tf.available else None
        # Built first: an edge tf cannot carry drops the sample before anything is published.
        camera_edge = None
        if tf is not None:
            camera_edge = camera_transform(pose.T_world_camera, pose.stamp_ns, frames=self._frames)
        tracker_frame = self.parameters["tracker_frame"]
        self._marker_publisher.publish(
            matrix_to_pose(sample.T_tracker_marker, sample.stamp_ns, tracker_frame)
        )
        self._camera_publisher.publish(
            matrix_to_pose(pose.T_world_camera, pose.stamp_ns, self.parameters["world_frame"])
        )
        if tf is not None and camera_edge is not None:
            tf.send([camera_edge])

    def close(self) -> None:
        """Stop the source's thread (called by run_node on shutdown)."""
        self._stop_source()
        if self._tf is not None:
            self._tf.close()
            self._tf = None


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``endo-tracker-bridge`` (parameters via ``--ros-args -p ...``).

    A configuration that cannot work gives one line on stderr and exit code 2
    (through :func:`endo_io.process.run_node`).
    """
    return run_node(TrackerBridgeNode, args, restart_on_lost_port=True)


if __name__ == "__main__":
    sys.exit(main())
