"""``endo-foxglove``: the graph's topics served live to Foxglove, without foxglove_bridge.

Subscribes (sensor-data QoS; the map transient-local) to the raw and
corrected image, relative and metric depth, camera_info, the world-frame
points and the map, the camera pose and the scale, and serves them with
foxglove-sdk's WebSocket server (ws://127.0.0.1:8765 by default; wss:// with
``tls_cert``/``tls_key``) as Foxglove's own schemas: RawImage,
CameraCalibration, PointCloud, PoseInFrame, FrameTransforms on ``/tf``
(world → endoscope_optical_frame per pose) and ``/tf_static`` (world →
tracker, optical frame → marker from ``T_world_tracker`` and
``handeye_file``), the scale as JSON with a top-level ``scale`` number, and
``/diagnostics`` as it is (CDR with its ROS schema, which Foxglove's
diagnostics panels read).

A slow viewer never slows the graph: DDS callbacks only leave each message
in a newest-wins slot (a message still waiting there when the next arrives
is superseded and counted); one thread converts and hands messages to the
SDK, whose per-client backlog is bounded (``message_backlog_size``; when
full the SDK drops that client's oldest messages, and the bridge counts the
event). Per-topic ``*_max_rate_hz`` throttles, clouds are decimated to
``*_max_points`` for the viewer only, and nothing is converted for a topic no
client has subscribed to. Counters are on ``/diagnostics``.
"""

from __future__ import annotations

import functools
import logging
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import foxglove
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from foxglove import Channel, Context, Schema
from foxglove.channels import (
    CameraCalibrationChannel,
    FrameTransformsChannel,
    PointCloudChannel,
    PoseInFrameChannel,
    RawImageChannel,
)
from foxglove.websocket import ChannelView, Client, ServerListener, WebSocketServer
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from endo_foxglove import convert
from endo_foxglove.mailbox import NewestWins
from endo_foxglove.plot_message import json_schema, plot_message
from endo_io import topics
from endo_io.bag.msgdef import message_definition
from endo_io.bag.serde import message_class, msgtype_of
from endo_io.diagnostics import InputHealth
from endo_io.errors import Endo3dError
from endo_io.parameters import NodeParameters, ParameterSpec
from endo_io.pose import pose_to_matrix
from endo_io.process import describing_only, run_node
from endo_io.qos import SENSOR_DATA_QOS
from endo_io.tf import StampedTransform, static_transforms
from endo_tracker_bridge.handeye_file import HandEyeCalibration

#: Foxglove channels of the transforms (same names as tf's topics).
TF_CHANNEL = topics.TF
TF_STATIC_CHANNEL = topics.TF_STATIC
#: The scale topic's type as endo_flow publishes it (x = s, y = std of ln s, z = state).
SCALE_TYPE = "geometry_msgs/msg/Vector3Stamped"
#: Seconds between re-sends of the static transforms (late clients get them).
STATIC_RESEND_S = 2.0
_SDK_LOGGER = "foxglove.websocket"
_OUTBOX_FULL = "outbox for client "
_IDENTITY_ROWS = [float(v) for v in np.eye(4).ravel()]


#: How long a WebSocket port still held by a stopped server is retried, seconds.
_BIND_RETRY_S = 3.0


class ViewerError(Endo3dError):
    """The bridge cannot start: bad TLS files, a port in use, a bad static transform."""


@dataclass(frozen=True)
class Stream:
    """One subscribed topic of the bridge.

    Attributes:
        key: parameter prefix (``<key>_topic``, ``<key>_max_rate_hz``).
        topic: default topic (:mod:`endo_io.topics`).
        msg_type: ROS message class; None for the scale (found at run time).
        max_rate_hz: default throttle, 0 = every message.
        resend: the last message is kept and sent again to each new subscriber.
        transient_local: reliable transient-local subscription (receives what a
            latched publisher sent before the bridge started); it matches only
            transient-local publishers, so it is used for the map alone.
        raw: passed through as CDR with its ROS schema (no Foxglove schema exists,
            e.g. ``/diagnostics`` for Foxglove's diagnostics panels).
    """

    key: str
    topic: str
    msg_type: type | None
    max_rate_hz: float
    resend: bool = False
    transient_local: bool = False
    raw: bool = False


STREAMS: tuple[Stream, ...] = (
    Stream("image_raw", topics.IMAGE_RAW, Image, 30.0),
    Stream("image_corrected", topics.IMAGE_CORRECTED, Image, 30.0),
    Stream("depth_relative", topics.DEPTH_RELATIVE, Image, 30.0),
    Stream("depth", topics.DEPTH, Image, 30.0),
    Stream("camera_info", topics.CAMERA_INFO, CameraInfo, 5.0, resend=True),
    Stream("points", topics.POINTS, PointCloud2, 10.0),
    Stream("map", topics.MAP, PointCloud2, 1.0, resend=True, transient_local=True),
    Stream("camera_pose", topics.CAMERA_POSE, PoseStamped, 0.0),
    Stream("scale", topics.SCALE, None, 0.0),
    Stream("diagnostics", topics.DIAGNOSTICS, DiagnosticArray, 0.0, raw=True),
)


def latched_qos() -> QoSProfile:
    """Reliable transient-local keep-last-1: receives the map published before we started."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


class SlowClientLog(logging.Handler):
    """Collects the SDK's "outbox for client X full" events (it drops that client's oldest data).

    The SDK logs the event through Python logging (logger ``foxglove.websocket``)
    once per client; it does not count the messages it drops after that.
    """

    def __init__(self) -> None:
        super().__init__(level=logging.INFO)
        self._lock = threading.Lock()
        self._clients: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        """Called by the SDK's threads for every record of ``foxglove.websocket``."""
        text = record.getMessage()
        if text.startswith(_OUTBOX_FULL):
            with self._lock:
                self._clients.append(text[len(_OUTBOX_FULL) :].split()[0])

    def take(self) -> list[str]:
        """Client addresses reported since the last call."""
        with self._lock:
            clients, self._clients = self._clients, []
            return clients


class _Listener(ServerListener):
    """Server callbacks (SDK threads): note subscriptions so latched data is re-sent."""

    def __init__(self, on_subscribe: Callable[[str], None]) -> None:
        self._on_subscribe = on_subscribe
        self.clients: set[int] = set()
        self._lock = threading.Lock()
        self._subscriptions: Counter[int] = Counter()

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self._lock:
            self._subscriptions[client.id] += 1
            self.clients.add(client.id)
        self._on_subscribe(channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        with self._lock:
            self._subscriptions[client.id] -= 1
            if self._subscriptions[client.id] <= 0:
                self.clients.discard(client.id)
                del self._subscriptions[client.id]


def parameter_table() -> list[ParameterSpec]:
    """The bridge's parameters; read-only ones are fixed when the server starts."""
    specs = [
        ParameterSpec("host", "127.0.0.1", "Address the WebSocket server binds; 0.0.0.0 "
                      "exposes it to the network (then use TLS).", read_only=True),
        ParameterSpec("port", 8765, "WebSocket port; 0 picks a free one.", range=(0, 65535),
                      read_only=True),
        ParameterSpec("tls_cert", "", "PEM certificate file; with tls_key the server speaks "
                      "wss:// only.", read_only=True),
        ParameterSpec("tls_key", "", "PEM PKCS#8 private key file matching tls_cert.",
                      read_only=True),
        ParameterSpec("server_name", "endo3d", "Name the server gives Foxglove.",
                      read_only=True),
        ParameterSpec("message_backlog_size", 32, "Messages buffered per client; when full "
                      "the SDK drops that client's oldest data.", range=(1, 1024),
                      read_only=True),
        ParameterSpec("camera_frame", topics.OPTICAL_FRAME,
                      "Child frame of the camera pose's transform."),
        ParameterSpec("handeye_file", "", "handeye.yaml (endo-handeye): /tf_static optical "
                      "frame → marker; empty: not sent.", read_only=True),
        ParameterSpec("T_world_tracker", _IDENTITY_ROWS, "16 row-major numbers, tracker → "
                      "world, metres (as endo-tracker-bridge's): /tf_static world → tracker.",
                      read_only=True),
        ParameterSpec("send_world_tracker", True, "Send world → tracker on /tf_static.",
                      read_only=True),
        ParameterSpec("scale_type", SCALE_TYPE, "Message type of the scale topic "
                      "(pkg/msg/Name; endo_flow's by default); empty: found when the topic "
                      "appears in the graph.", read_only=True),
        ParameterSpec("scale_field", "", "Field path of the plotted scale (e.g. vector.x); "
                      "empty: a field named scale, else data, else x, else the first number."),
        ParameterSpec("points_max_points", 100_000, "Viewer-only decimation of each points "
                      "cloud (points).", range=(1, 10_000_000)),
        ParameterSpec("map_max_points", 300_000, "Viewer-only decimation of the map (points).",
                      range=(1, 10_000_000)),
    ]
    for stream in STREAMS:
        specs.append(ParameterSpec(f"{stream.key}_topic", stream.topic, f"Subscribed "
                                   f"{stream.key} topic (also the Foxglove channel name).",
                                   read_only=True))
        specs.append(ParameterSpec(f"{stream.key}_max_rate_hz", stream.max_rate_hz,
                                   f"Most {stream.key} messages per second sent to viewers; "
                                   "0: all.", range=(0.0, 1000.0)))
    return specs


class FoxgloveBridgeNode(Node):
    """Serves the graph's topics to Foxglove over a WebSocket (see the module docstring)."""

    def __init__(self, node_name: str = "endo_foxglove", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._p = self._declare_parameters()
        self.health = InputHealth(self, "viewer")
        self._mailbox: NewestWins[Any] = NewestWins()
        self._throttled: Counter[str] = Counter()
        self._forwarded: Counter[str] = Counter()
        self._last_accept: dict[str, float] = {}
        self._latched: dict[str, Any] = {}
        self._points_shown: dict[str, tuple[int, int]] = {}
        self._newest_pose_ns = 0
        self._streams = {s.key: s for s in STREAMS}
        self._topic_of = {s.key: str(self._p[f"{s.key}_topic"]) for s in STREAMS}
        self._key_of = {topic: key for key, topic in self._topic_of.items()}
        self._static_edges = self._load_static_transforms()

        self._fg_context = Context()
        self._channels = self._create_channels()
        self._scale_channel: Channel | None = None
        self._scale_subscription: Any = None
        self._slow_clients = SlowClientLog()
        self._slow_seen: set[str] = set()
        self._listener = _Listener(self._request_resend)
        # With scale_type given the channel exists before any client connects:
        # a channel added while a client is connected can lose that client's
        # first subscribe in foxglove-sdk 0.30 ("subscribe to unknown channel").
        self._discover_scale()
        # --help creates the node only to list its parameters: no server then
        # (a port in use must not stop the help text).
        self._server: WebSocketServer | None = None if describing_only() else self._start_server()

        self._ros_subscriptions = [
            self._subscribe(stream) for stream in STREAMS if stream.msg_type is not None
        ]
        self._forward_guarded = self.health.guard(self._forward)
        self._running = True
        self._worker = threading.Thread(target=self._work, name="foxglove-sender", daemon=True)
        self._worker.start()
        self._discover_timer = self.create_timer(1.0, self._discover_scale)
        self._static_timer = self.create_timer(STATIC_RESEND_S, self._send_static)
        self._report_timer = self.create_timer(1.0, self._report)
        if self._server is not None:
            scheme = "wss" if self._p["tls_cert"] else "ws"
            self.get_logger().info(
                f"Foxglove: open connection {scheme}://{self._p['host']}:{self._server.port}"
            )

    # -- parameters -------------------------------------------------------------

    def _declare_parameters(self) -> NodeParameters:
        return NodeParameters(self, parameter_table())

    def _load_static_transforms(self) -> list[StampedTransform]:
        T_world_tracker = None
        if self._p["send_world_tracker"]:
            rows = list(self._p["T_world_tracker"])
            if len(rows) != 16:
                raise ViewerError(f"T_world_tracker needs 16 row-major numbers, got {len(rows)}")
            T_world_tracker = np.asarray(rows, dtype=np.float64).reshape(4, 4)
        try:
            T_marker_camera = None
            if self._p["handeye_file"]:
                calibration = HandEyeCalibration.load(self._p["handeye_file"])
                T_marker_camera = calibration.T_marker_camera
            return static_transforms(
                T_world_tracker=T_world_tracker, T_marker_camera=T_marker_camera
            )
        except Endo3dError as error:
            raise ViewerError(str(error)) from error

    # -- Foxglove side ----------------------------------------------------------

    def _create_channels(self) -> dict[str, Any]:
        context = self._fg_context
        channels: dict[str, Any] = {}
        for key in ("image_raw", "image_corrected", "depth_relative", "depth"):
            channels[key] = RawImageChannel(self._topic_of[key], context=context)
        channels["camera_info"] = CameraCalibrationChannel(
            self._topic_of["camera_info"], context=context
        )
        channels["points"] = PointCloudChannel(self._topic_of["points"], context=context)
        channels["map"] = PointCloudChannel(self._topic_of["map"], context=context)
        channels["camera_pose"] = PoseInFrameChannel(
            self._topic_of["camera_pose"], context=context
        )
        for stream in STREAMS:
            if stream.raw and stream.msg_type is not None:
                msgtype = msgtype_of(stream.msg_type)
                definition = message_definition(msgtype)
                schema = Schema(
                    name=msgtype, encoding=definition.encoding, data=definition.text.encode()
                )
                channels[stream.key] = Channel(
                    self._topic_of[stream.key], schema=schema, message_encoding="cdr",
                    context=context,
                )
        channels["tf"] = FrameTransformsChannel(TF_CHANNEL, context=context)
        channels["tf_static"] = FrameTransformsChannel(TF_STATIC_CHANNEL, context=context)
        return channels

    def _start_server(self) -> WebSocketServer:
        cert = key = None
        if bool(self._p["tls_cert"]) != bool(self._p["tls_key"]):
            raise ViewerError("TLS needs both tls_cert and tls_key")
        if self._p["tls_cert"]:
            try:
                cert = Path(self._p["tls_cert"]).read_bytes()
                key = Path(self._p["tls_key"]).read_bytes()
            except OSError as error:
                raise ViewerError(f"cannot read TLS file: {error}") from error
        foxglove.set_log_level("INFO")  # SDK events reach Python logging (once per process)
        logging.getLogger(_SDK_LOGGER).addHandler(self._slow_clients)
        # A node created again in its process (endo_io.shm_ports) binds the port its
        # predecessor's server held: stop() does not wait for the socket to close
        # (about 10 ms here, longer on a starved machine), so "in use" is retried.
        deadline = time.monotonic() + _BIND_RETRY_S
        while True:
            try:
                return foxglove.start_server(
                    name=str(self._p["server_name"]),
                    host=str(self._p["host"]),
                    port=int(self._p["port"]),
                    server_listener=self._listener,
                    context=self._fg_context,
                    message_backlog_size=int(self._p["message_backlog_size"]),
                    tls_cert=cert,
                    tls_key=key,
                )
            except Exception as error:  # the SDK raises RuntimeError / its own error types
                if "in use" in str(error) and time.monotonic() < deadline:
                    time.sleep(0.05)
                    continue
                logging.getLogger(_SDK_LOGGER).removeHandler(self._slow_clients)
                raise ViewerError(
                    f"cannot start the WebSocket server on {self._p['host']}:{self._p['port']}: "
                    f"{error}"
                ) from error

    def _request_resend(self, topic: str) -> None:
        """A client subscribed to ``topic`` (SDK thread): send it the latched data again."""
        if topic == TF_STATIC_CHANNEL:
            self._mailbox.put("tf_static", None)
            return
        key = self._key_of.get(topic)
        if key is not None and key in self._latched:
            self._mailbox.put(key, self._latched[key])

    def _send_static(self) -> None:
        if self._static_edges:
            self._mailbox.put("tf_static", None)

    # -- ROS side ---------------------------------------------------------------

    def _subscribe(self, stream: Stream, msg_type: type | None = None) -> Any:
        qos = latched_qos() if stream.transient_local else SENSOR_DATA_QOS
        return self.create_subscription(
            msg_type or stream.msg_type,
            self._topic_of[stream.key],
            functools.partial(self._on_message, stream.key),
            qos,
            raw=stream.raw,
        )

    def _on_message(self, key: str, msg: Any) -> None:
        """DDS callback: throttle, then leave the message for the sending thread. Never blocks."""
        if self._streams[key].resend:
            self._latched[key] = msg
        rate = float(self._p[f"{key}_max_rate_hz"])
        now = time.monotonic()
        if rate > 0.0 and now - self._last_accept.get(key, -1e18) < 1.0 / rate:
            self._throttled[key] += 1
            return
        self._last_accept[key] = now
        self._mailbox.put(key, msg)

    def _discover_scale(self) -> None:
        """Subscribe to the scale topic once its type is known (parameter or graph)."""
        if self._scale_subscription is not None:
            return
        topic = self._topic_of["scale"]
        msgtype = str(self._p["scale_type"])
        if not msgtype:
            types = dict(self.get_topic_names_and_types()).get(topic, [])
            if not types:
                return
            msgtype = types[0]
        try:
            cls = message_class(msgtype)
        except Endo3dError as error:
            self.health.drop(type(error).__name__, f"{topic}: {error}")
            self._scale_subscription = False  # do not retry every second
            return
        self._scale_channel = Channel(
            topic, schema=json_schema(cls(), title=msgtype), context=self._fg_context
        )
        self._scale_subscription = self._subscribe(self._streams["scale"], cls)
        if not describing_only():
            self.get_logger().info(
                f"scale: {topic} is {msgtype}; sent as JSON, its value also as {topic}.scale"
            )

    # -- sending thread ---------------------------------------------------------

    def _work(self) -> None:
        while self._running:
            for key, msg in self._mailbox.take(0.5):
                if self._running:
                    self._forward_guarded(key, msg)

    def _forward(self, key: str, msg: Any) -> None:
        """Convert one message and log it on its channel (sending thread)."""
        if key == "tf_static":
            if not self._static_edges or not self._channels["tf_static"].has_sinks():
                return
            # Stamped like the newest pose, so a viewer's lookup at camera time finds them.
            stamp = self._newest_pose_ns
            edges = [
                StampedTransform(stamp, e.parent_frame, e.child_frame, e.translation, e.rotation)
                for e in self._static_edges
            ]
            self._channels["tf_static"].log(convert.frame_transforms(edges))
            return
        if key == "scale":
            if self._scale_channel is not None and self._scale_channel.has_sinks():
                self._scale_channel.log(plot_message(msg, str(self._p["scale_field"])))
                self._forwarded[key] += 1
            return
        channel = self._channels[key]
        if key == "camera_pose":
            T, stamp = pose_to_matrix(msg)
            self._newest_pose_ns = max(self._newest_pose_ns, stamp)
            edge = StampedTransform.from_matrix(
                T, stamp, msg.header.frame_id or topics.WORLD_FRAME, str(self._p["camera_frame"])
            )
            if self._channels["tf"].has_sinks():
                self._channels["tf"].log(convert.frame_transforms([edge]))
            if channel.has_sinks():
                channel.log(convert.pose_in_frame(msg))
            self._forwarded[key] += 1
            return
        if not channel.has_sinks():
            return
        if self._streams[key].raw:
            channel.log(bytes(msg))
        elif key in ("points", "map"):
            cloud = convert.point_cloud(msg, max_points=int(self._p[f"{key}_max_points"]))
            channel.log(cloud.message)
            self._points_shown[key] = (cloud.published, cloud.total)
        elif key == "camera_info":
            channel.log(convert.camera_calibration(msg))
        else:
            channel.log(convert.raw_image(msg, irradiance=key == "image_corrected"))
        self._forwarded[key] += 1

    # -- diagnostics ------------------------------------------------------------

    def _report(self) -> None:
        for client in self._slow_clients.take():
            self._slow_seen.add(client)
            self.health.drop(
                "SlowClient",
                f"viewer {client} does not keep up: its backlog of "
                f"{self._p['message_backlog_size']} messages is full, the Foxglove SDK now "
                "drops its oldest messages (the graph is not slowed)",
            )
        health = self.health
        health.set_value("clients", len(self._listener.clients))
        health.set_value("slow_clients", " ".join(sorted(self._slow_seen)) or "none")
        for key in self._streams:
            health.set_value(f"forwarded.{key}", self._forwarded[key])
            health.set_value(f"superseded.{key}", self._mailbox.superseded[key])
            health.set_value(f"throttled.{key}", self._throttled[key])
        for key, (shown, total) in self._points_shown.items():
            health.set_value(f"points_shown.{key}", f"{shown}/{total}")

    # -- lifetime ---------------------------------------------------------------

    @property
    def port(self) -> int:
        """The port the WebSocket server listens on (0 when describing only)."""
        return 0 if self._server is None else int(self._server.port)

    def close(self) -> None:
        """Stop the sending thread and the server (run_node calls this on shutdown)."""
        if not self._running:
            return
        self._running = False
        self._mailbox.close()
        self._worker.join(timeout=5.0)
        if self._server is not None:
            self._server.stop()
        logging.getLogger(_SDK_LOGGER).removeHandler(self._slow_clients)


def main(args: list[str] | None = None) -> int:
    """Console entry point of ``endo-foxglove`` (a bad setting: one line, exit code 2)."""
    return run_node(FoxgloveBridgeNode, args, restart_on_lost_port=True)


if __name__ == "__main__":
    sys.exit(main())
