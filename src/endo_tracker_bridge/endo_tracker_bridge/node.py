"""``endo-tracker-bridge``: one tracker in, the endoscope camera pose out.

Parameter ``source`` picks the input (``ros``, ``igtl``, ``ndi``, ``csv``).
Each accepted marker pose is published twice:

* ``/tracker/pose``: T_tracker_marker, frame ``tracker``, metres, stamped
  with the tracker's own stamp (what ``endo-handeye`` reads back);
* ``/endoscope/pose``: T_world_camera = T_world_tracker · T_tracker_marker ·
  T_marker_camera, frame ``world``, stamped at the tracker stamp minus the
  calibrated time offset (camera clock).

Rejected samples (NaN, non-unit quaternion, tool missing, time going
backwards, speed jump, bad message) are dropped and counted by cause on
``/diagnostics``; the node keeps running, and network/serial sources
reconnect by themselves.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node

from endo_io.diagnostics import InputHealth
from endo_io.errors import Endo3dError
from endo_io.pose import matrix_to_pose
from endo_io.process import run_node
from endo_io.qos import SENSOR_DATA_QOS, create_reliable_publisher
from endo_tracker_bridge.composition import compose_camera_pose, corrected_stamp_ns
from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.errors import TrackerSourceError
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.sample import TrackerSample
from endo_tracker_bridge.sources.background import BackgroundSource
from endo_tracker_bridge.sources.ros import sample_from_pose_stamped
from endo_tracker_bridge.validation import (
    DEFAULT_ROTATION_TOLERANCE,
    SampleGate,
    SpeedLimits,
    check_rotation_matrix,
)

SOURCES = ("ros", "igtl", "ndi", "csv")
IDENTITY_ROWS = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]


def _float_range(low: float, high: float) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=low, to_value=high, step=0.0)]


def _int_range(low: int, high: int) -> list[IntegerRange]:
    return [IntegerRange(from_value=low, to_value=high, step=1)]


def world_tracker_from_parameter(values: Sequence[float]) -> np.ndarray:
    """T_world_tracker (4,4) from the 16 row-major numbers of the parameter (metres)."""
    if len(values) != 16:
        raise TrackerSourceError(f"T_world_tracker needs 16 row-major numbers, got {len(values)}")
    T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise TrackerSourceError("T_world_tracker must be a finite homogeneous transform")
    T[:3, :3] = check_rotation_matrix(T[:3, :3], tolerance=1e-6)
    return T


class TrackerBridgeNode(Node):
    """Reads one tracker source and publishes the marker and camera poses."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("tracker_bridge", **kwargs)
        p = self._declare_parameters()
        self._world_frame, self._tracker_frame = p["world_frame"], p["tracker_frame"]
        self._T_world_tracker = world_tracker_from_parameter(p["T_world_tracker"])
        if p["handeye_file"]:
            self.calibration = HandEyeCalibration.load(p["handeye_file"])
            offset_ms = self.calibration.time_offset_ns * 1e-6
            self.get_logger().info(
                f"hand-eye from {p['handeye_file']}: time offset {offset_ms:.3f} ms, "
                f"residuals {self.calibration.residuals}"
            )
        else:
            self.calibration = HandEyeCalibration.identity()
            self.get_logger().warning(
                "no handeye_file: /endoscope/pose is the marker pose "
                "(T_marker_camera = identity, no time offset)"
            )
        self._tolerance = p["rotation_tolerance"]
        self._gate = SampleGate(SpeedLimits(p["max_speed_m_s"], p["max_angular_speed_deg_s"]))
        self._health = InputHealth(self, f"tracker input ({p['source']})")
        self._health.set_value("time_offset_ms", f"{self.calibration.time_offset_ns * 1e-6:.3f}")
        self._marker_publisher = create_reliable_publisher(self, PoseStamped, "/tracker/pose")
        self._camera_publisher = create_reliable_publisher(self, PoseStamped, "/endoscope/pose")
        self._source: BackgroundSource | None = None
        self._guarded_item = self._health.guard(self._process_item)
        self._start_source(p)

    # -- parameters ---------------------------------------------------------------

    def _declare_parameters(self) -> dict[str, Any]:
        spec: list[tuple[str, Any, str, Any]] = [
            ("source", "ros", "Tracker input: ros | igtl | ndi | csv.", None),
            (
                "handeye_file",
                "",
                "handeye.yaml from endo-handeye; empty: identity hand-eye, no time offset.",
                None,
            ),
            (
                "T_world_tracker",
                IDENTITY_ROWS,
                "16 row-major numbers, tracker frame → world frame, metres.",
                None,
            ),
            ("world_frame", "world", "frame_id of /endoscope/pose.", None),
            ("tracker_frame", "tracker", "frame_id of /tracker/pose.", None),
            (
                "max_speed_m_s",
                2.0,
                "Reject a marker moving faster than this (m/s).",
                _float_range(0.001, 1000.0),
            ),
            (
                "max_angular_speed_deg_s",
                720.0,
                "Reject a marker turning faster than this (degrees/s).",
                _float_range(1.0, 1e6),
            ),
            (
                "rotation_tolerance",
                DEFAULT_ROTATION_TOLERANCE,
                "Allowed | |q| - 1 | and max |RᵀR - I| of input rotations.",
                _float_range(1e-9, 0.1),
            ),
            (
                "ros_topic",
                "/tracker/driver_pose",
                "source=ros: PoseStamped topic of the driver.",
                None,
            ),
            ("ros_unit", "m", "source=ros: unit of the driver's positions, m | mm.", None),
            ("ros_frame_id", "", "source=ros: expected header.frame_id; empty accepts any.", None),
            ("tool_id", "marker", "source=ros: name of the tool in diagnostics.", None),
            ("igtl_host", "127.0.0.1", "source=igtl: OpenIGTLink server host.", None),
            ("igtl_port", 18944, "source=igtl: OpenIGTLink server port.", _int_range(1, 65535)),
            (
                "igtl_device",
                "ScopeToTracker",
                "source=igtl: TRANSFORM device name; empty takes any.",
                None,
            ),
            ("igtl_unit", "mm", "source=igtl: unit of the TRANSFORM translation, mm | m.", None),
            (
                "igtl_stamp",
                "message",
                "source=igtl: stamp from the message header | receive time.",
                None,
            ),
            (
                "igtl_reconnect_interval_s",
                0.5,
                "source=igtl: pause between reconnection attempts (s).",
                _float_range(0.01, 60.0),
            ),
            (
                "igtl_stale_timeout_s",
                0.0,
                "source=igtl: reconnect after this long without data (s); 0 disables.",
                _float_range(0.0, 3600.0),
            ),
            ("ndi_tracker_type", "polaris", "source=ndi: polaris | vega | aurora.", None),
            (
                "ndi_serial_port",
                "",
                "source=ndi: serial port (Polaris/Aurora); empty probes.",
                None,
            ),
            ("ndi_ip_address", "", "source=ndi: Vega IP address.", None),
            ("ndi_tcp_port", 8765, "source=ndi: Vega TCP port.", _int_range(1, 65535)),
            ("ndi_romfiles", [""], "source=ndi: tool ROM files (Polaris/Vega).", None),
            (
                "ndi_tool_index",
                0,
                "source=ndi: which tool of the frame to follow.",
                _int_range(0, 64),
            ),
            ("ndi_rate_hz", 60.0, "source=ndi: polling rate (Hz).", _float_range(1.0, 400.0)),
            (
                "ndi_max_rms_error_mm",
                1.0,
                "source=ndi: reject a tool whose marker fit error exceeds this (mm).",
                _float_range(0.0, 100.0),
            ),
            ("csv_path", "", "source=csv: tracker log file.", None),
            ("csv_unit", "mm", "source=csv: unit of the log's translations, mm | m.", None),
            (
                "csv_delimiter",
                "",
                "source=csv: column delimiter; empty detects tab/semicolon/comma.",
                None,
            ),
            ("csv_tool", "", "source=csv: replay only rows of this tool; empty replays all.", None),
            (
                "csv_rate",
                1.0,
                "source=csv: replay speed factor; 0 = as fast as possible.",
                _float_range(0.0, 1000.0),
            ),
        ]
        values: dict[str, Any] = {}
        for name, default, description, ranges in spec:
            descriptor = ParameterDescriptor(description=description)
            if isinstance(default, float):
                descriptor.floating_point_range = ranges
            elif isinstance(default, int):
                descriptor.integer_range = ranges
            elif isinstance(default, list) and isinstance(default[0], str):
                descriptor.type = ParameterType.PARAMETER_STRING_ARRAY
            values[name] = self.declare_parameter(name, default, descriptor).value
        if values["source"] not in SOURCES:
            raise TrackerSourceError(
                f"unknown source '{values['source']}' (expected {', '.join(SOURCES)})"
            )
        return values

    # -- sources --------------------------------------------------------------------

    def _start_source(self, p: dict[str, Any]) -> None:
        log = self.get_logger().info
        source = p["source"]
        if source == "ros":
            unit = LengthUnit.parse(p["ros_unit"])

            def on_pose(msg: PoseStamped) -> None:
                sample = sample_from_pose_stamped(
                    msg, unit, p["ros_frame_id"], p["tool_id"], self._tolerance
                )
                self._publish(self._gate.check(sample))

            self.create_subscription(
                PoseStamped, p["ros_topic"], self._health.guard(on_pose), SENSOR_DATA_QOS
            )
            self.get_logger().info(f"source ros: {p['ros_topic']} ({unit.value})")
            return
        if source == "igtl":
            from endo_tracker_bridge.sources.igtl import IgtlSource

            self._source = IgtlSource(
                host=p["igtl_host"],
                port=p["igtl_port"],
                device_name=p["igtl_device"],
                unit=LengthUnit.parse(p["igtl_unit"]),
                stamp_from=p["igtl_stamp"],
                tolerance=self._tolerance,
                reconnect_interval_s=p["igtl_reconnect_interval_s"],
                stale_timeout_s=p["igtl_stale_timeout_s"],
                log=log,
            )
        elif source == "ndi":
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
            self._source = NdiSource(options, self._tolerance, log=log)
        else:
            from endo_tracker_bridge.sources.csv import CsvReplaySource

            self._source = CsvReplaySource(
                p["csv_path"],
                unit=LengthUnit.parse(p["csv_unit"]),
                delimiter=p["csv_delimiter"],
                tool=p["csv_tool"],
                rate=p["csv_rate"],
                tolerance=self._tolerance,
                log=log,
            )
        # The source's thread wakes the executor through a guard condition, so
        # a pose is published as soon as it arrives, without a polling timer.
        self._wake = self.create_guard_condition(self._drain_source)
        self._source.start(self._wake.trigger)
        self.get_logger().info(f"source {source} started")

    def _drain_source(self) -> None:
        assert self._source is not None
        for item in self._source.drain():
            self._guarded_item(item)
        for key, value in self._source.status().items():
            self._health.set_value(key, value)

    def _process_item(self, item: Any) -> None:
        assert self._source is not None
        self._publish(self._gate.check(self._source.to_sample(item)))

    # -- output ---------------------------------------------------------------------

    def _publish(self, sample: TrackerSample) -> None:
        T_world_camera = compose_camera_pose(
            self._T_world_tracker, sample.T_tracker_marker, self.calibration.T_marker_camera
        )
        camera_stamp_ns = corrected_stamp_ns(sample.stamp_ns, self.calibration.time_offset_ns)
        self._marker_publisher.publish(
            matrix_to_pose(sample.T_tracker_marker, sample.stamp_ns, self._tracker_frame)
        )
        self._camera_publisher.publish(
            matrix_to_pose(T_world_camera, camera_stamp_ns, self._world_frame)
        )

    def close(self) -> None:
        """Stop the source's thread (called by run_node on shutdown)."""
        if self._source is not None:
            self._source.stop()


def main(args: Sequence[str] | None = None) -> int:
    """Console script ``endo-tracker-bridge`` (parameters via ``--ros-args -p ...``)."""
    try:
        return run_node(TrackerBridgeNode, args)
    except Endo3dError as error:
        print(f"endo-tracker-bridge: {type(error).__name__}: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
