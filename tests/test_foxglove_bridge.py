"""endo-foxglove against a real WebSocket client, fed over DDS by other processes.

The client is the ``websockets`` package speaking the Foxglove WebSocket
protocol. It offers the subprotocols a current viewer offers: Lichtblick's
player asks for ``foxglove.websocket.v1`` and ``foxglove.sdk.v1`` (that
order), and the Foxglove app offers ``foxglove.sdk.v1`` too; every
foxglove-sdk on PyPI (0.5.0 … 0.30.3, the newest) accepts only
``foxglove.sdk.v1``, the same messages under a new name. Test 0 pins that
negotiation down: a client offering both (either order) gets
``foxglove.sdk.v1``, one offering only ``foxglove.websocket.v1`` or nothing
gets HTTP 400 (docs/viewers.md, "Which viewers connect"). Messages are
decoded with a small protobuf wire-format reader driven by the schema
(FileDescriptorSet) the server advertises, so nothing of the SDK's own
encoder is trusted.

1. ``endo-replay`` plays a bag written here (images, depth, camera_info, a
   world cloud with NaN points, camera poses); the client must receive the
   cloud (finite point count, coordinates), the camera's FrameTransform
   (equal to the pose) and the image (pixels) as published.
2. A client that subscribes and then never reads: a publisher process keeps
   its rate, the bridge keeps forwarding, and /diagnostics counts the slow
   client's drops.

Run as a script (``python test_websocket_bridge.py publish ...``) this file
is the publisher process of test 2.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import queue
import re
import shutil
import signal
import ssl
import struct
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
import websockets
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray

from endo_bringup.dds_profile import with_large_frame_profile
from endo_io.bag import BagWriter, message_class
from endo_io.camera import CameraModel
from endo_io.image import array_to_image
from endo_io.pointcloud import xyz_to_pointcloud2
from endo_io.pose import matrix_to_pose, quaternion_to_matrix, rigid_transform
from endo_io.qos import create_reliable_publisher
from endo_io.stamp import ns_to_stamp
from endo_io.topics import (
    CAMERA_INFO,
    CAMERA_POSE,
    DEPTH,
    DIAGNOSTICS,
    IMAGE_RAW,
    OPTICAL_FRAME,
    POINTS,
    SCALE,
    TF,
    WORLD_FRAME,
)

BIN = Path(sys.executable).parent
#: The protocol's old name and the one foxglove-sdk speaks (the same messages).
WEBSOCKET_V1, SDK_V1 = "foxglove.websocket.v1", "foxglove.sdk.v1"
#: What the test clients offer, in Lichtblick's order (a viewer offering both).
SUBPROTOCOLS = [WEBSOCKET_V1, SDK_V1]
T0 = 1_763_900_000_000_000_000
PERIOD_NS = 50_000_000  # 20 Hz
FRAMES = 10
W, H = 32, 24

pytestmark = pytest.mark.ros


# -- protobuf wire format, driven by the advertised FileDescriptorSet ---------------------------

def _varint(buf: bytes, i: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        byte = buf[i]
        i += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, i
        shift += 7


def _wire_fields(buf: bytes) -> dict[int, list[tuple[int, Any]]]:
    fields: dict[int, list[tuple[int, Any]]] = defaultdict(list)
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = buf[i : i + 8], i + 8
        elif wire == 2:
            length, i = _varint(buf, i)
            value, i = buf[i : i + length], i + length
        elif wire == 5:
            value, i = buf[i : i + 4], i + 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
        fields[number].append((wire, value))
    return fields


def _strings(fields: dict[int, list[tuple[int, Any]]], number: int) -> list[str]:
    return [bytes(v).decode() for _, v in fields.get(number, [])]


class ProtobufSchema:
    """Message descriptors of a FileDescriptorSet, enough to decode Foxglove's schemas."""

    def __init__(self, descriptor_set: bytes) -> None:
        self.messages: dict[str, dict[str, tuple[int, int, int, str]]] = {}
        for _, file_bytes in _wire_fields(descriptor_set)[1]:  # FileDescriptorSet.file
            file_fields = _wire_fields(file_bytes)
            package = (_strings(file_fields, 2) or [""])[0]
            for _, message in file_fields.get(4, []):  # FileDescriptorProto.message_type
                self._add(message, package)

    def _add(self, message: bytes, scope: str) -> None:
        fields = _wire_fields(message)
        name = f"{scope}.{_strings(fields, 1)[0]}"
        entries = {}
        for _, field in fields.get(2, []):  # DescriptorProto.field
            f = _wire_fields(field)
            type_name = (_strings(f, 6) or [""])[0].lstrip(".")
            entries[_strings(f, 1)[0]] = (f[3][0][1], f[4][0][1], f[5][0][1], type_name)
        self.messages[name] = entries
        for _, nested in fields.get(3, []):
            self._add(nested, name)

    def decode(self, type_name: str, data: bytes) -> dict[str, Any]:
        wire = _wire_fields(data)
        result: dict[str, Any] = {}
        for name, (number, label, kind, nested) in self.messages[type_name].items():
            values = [self._value(kind, nested, w, v) for w, v in wire.get(number, [])]
            if label == 3:  # repeated (packed doubles arrive as one bytes value)
                result[name] = [x for v in values for x in (v if isinstance(v, list) else [v])]
            elif values:
                result[name] = values[-1]
        return result

    def _value(self, kind: int, nested: str, wire: int, value: Any) -> Any:
        if kind == 1:  # double
            if wire == 2:
                return list(struct.unpack(f"<{len(value) // 8}d", value))
            return struct.unpack("<d", value)[0]
        if kind == 2:  # float
            return struct.unpack("<f", value)[0]
        fixed = {6: "<Q", 7: "<I", 15: "<i", 16: "<q"}  # fixed64, fixed32, sfixed32, sfixed64
        if kind in fixed:
            return struct.unpack(fixed[kind], value)[0]
        if kind == 9:
            return bytes(value).decode()
        if kind == 12:
            return bytes(value)
        if kind == 11:
            return self.decode(nested, bytes(value))
        return value  # varint kinds: ints, bools, enums


# -- data -----------------------------------------------------------------------------------------

def camera_pose(i: int) -> np.ndarray:
    return rigid_transform([0.1 * i, -0.2, 0.3 + 0.05 * i], [0.01 * i, 0.02, -0.03 * i])


def world_cloud(i: int) -> np.ndarray:
    rng = np.random.default_rng(100 + i)
    xyz = rng.uniform(-0.05, 0.05, size=(H, W, 3)).astype(np.float32)
    xyz[::3, ::5] = np.nan  # invalid points stay in an organised cloud
    return xyz


def image_pixels(i: int) -> np.ndarray:
    return np.random.default_rng(200 + i).integers(0, 256, size=(H, W), dtype=np.uint8)


def write_bag(path: Path) -> None:
    model = CameraModel.pinhole(width=W, height=H, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
    with BagWriter(path) as bag:
        for i in range(FRAMES):
            t = T0 + i * PERIOD_NS
            image = array_to_image(image_pixels(i), "mono8", t, OPTICAL_FRAME)
            bag.write_message(IMAGE_RAW, image, t)
            bag.write_message(CAMERA_INFO, model.to_camera_info(t), t)
            depth = np.full((H, W), 0.05 + 0.001 * i, dtype=np.float32)
            bag.write_message(DEPTH, array_to_image(depth, "32FC1", t, OPTICAL_FRAME), t)
            bag.write_message(CAMERA_POSE, matrix_to_pose(camera_pose(i), t, WORLD_FRAME), t)
            bag.write_message(POINTS, xyz_to_pointcloud2(world_cloud(i), t, WORLD_FRAME), t)
            scale = Vector3Stamped()
            scale.header.stamp, scale.header.frame_id = ns_to_stamp(t), OPTICAL_FRAME
            scale.vector.x, scale.vector.y = 0.02 + 0.001 * i, 0.1
            bag.write_message(SCALE, scale, t)


# -- processes ------------------------------------------------------------------------------------

@pytest.fixture
def dds_env(tmp_path: Path) -> dict[str, str]:
    """Loopback discovery, and shared memory large enough for 640x480 float frames."""
    env, _ = with_large_frame_profile(
        dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"), tmp_path
    )
    return env


def start_bridge(
    env: dict[str, str], *params: str
) -> tuple[subprocess.Popen[str], int, queue.Queue[str]]:
    """endo-foxglove on a free port of 127.0.0.1; returns the process, port and its output lines."""
    args = [str(BIN / "endo-foxglove"), "--ros-args", "-p", "port:=0"]
    for param in params:
        args += ["-p", param]
    proc = subprocess.Popen(
        args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stdout is not None
    stdout = proc.stdout
    threading.Thread(target=lambda: [lines.put(line) for line in stdout], daemon=True).start()
    end = time.monotonic() + 60.0
    seen = []
    while time.monotonic() < end:
        try:
            line = lines.get(timeout=0.5)
        except queue.Empty:
            assert proc.poll() is None, "endo-foxglove exited:\n" + "".join(seen)
            continue
        seen.append(line)
        match = re.search(r"open connection wss?://127\.0\.0\.1:(\d+)", line)
        if match:
            return proc, int(match.group(1)), lines
    proc.kill()
    raise AssertionError("endo-foxglove did not report its port:\n" + "".join(seen))


def iter_lines(lines: queue.Queue[str]) -> list[str]:
    """What a process printed so far (its reader thread's queue, emptied)."""
    got = []
    while not lines.empty():
        got.append(lines.get_nowait())
    return got


def stop(proc: subprocess.Popen[Any]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# -- client -------------------------------------------------------------------------------------

async def receive(port: int, wanted: dict[str, int], timeout_s: float) -> dict[str, Any]:
    """Subscribe to ``wanted`` topics; collect up to ``wanted[topic]`` decoded messages each."""
    result: dict[str, Any] = {"messages": defaultdict(list)}
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None
    ) as ws:
        result["subprotocol"] = ws.subprotocol
        channels: dict[str, dict[str, Any]] = {}
        by_subscription: dict[int, dict[str, Any]] = {}
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                left = max(0.01, end - time.monotonic())
                frame = await asyncio.wait_for(ws.recv(), timeout=left)
            except TimeoutError:
                break
            if isinstance(frame, str):
                message = json.loads(frame)
                result.setdefault("ops", []).append(message["op"])
                if message["op"] != "advertise":
                    continue
                subscriptions = []
                for channel in message["channels"]:
                    channels[channel["topic"]] = channel
                    if channel["topic"] in wanted:
                        sub_id = len(by_subscription) + 1
                        channel["decoder"] = ProtobufSchema(base64.b64decode(channel["schema"])) \
                            if channel["encoding"] == "protobuf" else None
                        by_subscription[sub_id] = channel
                        subscriptions.append({"id": sub_id, "channelId": channel["id"]})
                if subscriptions:
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            else:
                assert frame[0] == 0x01, f"unexpected binary opcode {frame[0]}"
                sub_id, _log_time = struct.unpack_from("<IQ", frame, 1)
                channel = by_subscription[sub_id]
                payload = frame[13:]
                if channel["encoding"] == "cdr":
                    decoded = deserialize_message(payload, message_class(channel["schemaName"]))
                elif channel["decoder"] is None:
                    decoded = json.loads(payload)
                else:
                    decoded = channel["decoder"].decode(channel["schemaName"], payload)
                got = result["messages"][channel["topic"]]
                got.append(decoded)
                if all(len(result["messages"][t]) >= n for t, n in wanted.items()):
                    break
        result["channels"] = channels
    return result


def stamp_ns(decoded: dict[str, Any]) -> int:
    ts = decoded["timestamp"]
    return int(ts.get("seconds", 0)) * 1_000_000_000 + int(ts.get("nanos", 0))


# -- tests --------------------------------------------------------------------------------------

def test_client_decodes_cloud_transform_and_image_from_a_replay(tmp_path, dds_env):
    bag = tmp_path / "graph.mcap"
    write_bag(bag)
    bridge, port, output = start_bridge(dds_env, "points_max_rate_hz:=0.0")
    try:
        replay = subprocess.Popen(
            [str(BIN / "endo-replay"), str(bag), "--loop"],
            env=dds_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
    except BaseException:
        stop(bridge)
        raise
    try:
        wanted = {
            POINTS: 3, TF: 3, IMAGE_RAW: 3, DEPTH: 1, DIAGNOSTICS: 3, SCALE: 2, CAMERA_INFO: 1
        }
        result = asyncio.run(receive(port, wanted, timeout_s=45.0))
    finally:
        stop(replay)
        stop(bridge)
    log = "".join(iter_lines(output))

    assert result["subprotocol"] == SDK_V1
    assert result["ops"][0] == "serverInfo"
    channels = result["channels"]
    assert channels[POINTS]["schemaName"] == "foxglove.PointCloud"
    assert channels[TF]["schemaName"] == "foxglove.FrameTransforms"
    assert channels[IMAGE_RAW]["schemaName"] == "foxglove.RawImage"
    messages = result["messages"]
    for topic, count in wanted.items():
        assert len(messages[topic]) >= count, (
            f"{topic}: {len(messages[topic])} messages; advertised {sorted(channels)}; "
            f"bridge output:\n{log}"
        )

    index = {T0 + i * PERIOD_NS: i for i in range(FRAMES)}
    for cloud in messages[POINTS]:
        i = index[stamp_ns(cloud)]
        expected = world_cloud(i).reshape(-1, 3)
        expected = expected[np.isfinite(expected).all(axis=1)]
        assert cloud["frame_id"] == WORLD_FRAME and cloud["point_stride"] == 12
        points = np.frombuffer(cloud["data"], dtype="<f4").reshape(-1, 3)
        assert len(points) == len(expected) == W * H - 8 * 7  # NaN rows dropped
        np.testing.assert_array_equal(points[17], expected[17])
        np.testing.assert_array_equal(points, expected)
    for tf in messages[TF]:
        (edge,) = tf["transforms"]
        assert (edge["parent_frame_id"], edge["child_frame_id"]) == (WORLD_FRAME, OPTICAL_FRAME)
        T_want = camera_pose(index[stamp_ns(edge)])
        t, q = edge["translation"], edge["rotation"]
        np.testing.assert_allclose([t.get("x", 0.0), t.get("y", 0.0), t.get("z", 0.0)],
                                   T_want[:3, 3], atol=1e-12)
        R = quaternion_to_matrix(np.array([q.get(k, 0.0) for k in "xyzw"]))
        np.testing.assert_allclose(R, T_want[:3, :3], atol=1e-12)
    for image in messages[IMAGE_RAW]:
        assert (image["width"], image["height"], image["encoding"]) == (W, H, "mono8")
        pixels = np.frombuffer(image["data"], dtype=np.uint8).reshape(H, W)
        np.testing.assert_array_equal(pixels, image_pixels(index[stamp_ns(image)]))
    # /diagnostics passes through as CDR with its ROS schema, the bridge's own status included
    assert channels[DIAGNOSTICS]["encoding"] == "cdr"
    assert channels[DIAGNOSTICS]["schemaName"] == "diagnostic_msgs/msg/DiagnosticArray"
    names = {status.name for msg in messages[DIAGNOSTICS] for status in msg.status}
    assert any(name.startswith("endo_foxglove") for name in names), names
    # camera_info (published volatile, as drivers do) as Foxglove's CameraCalibration
    assert channels[CAMERA_INFO]["schemaName"] == "foxglove.CameraCalibration"
    calibration = messages[CAMERA_INFO][0]
    assert (calibration["width"], calibration["height"]) == (W, H)
    np.testing.assert_allclose(calibration["K"], [30.0, 0, 15.5, 0, 30.0, 11.5, 0, 0, 1])
    assert calibration["frame_id"] == OPTICAL_FRAME
    # The scale (endo_flow's Vector3Stamped): its fields as JSON plus `scale`
    assert channels[SCALE]["encoding"] == "json"
    assert channels[SCALE]["schemaName"] == "geometry_msgs/msg/Vector3Stamped"
    for scale in messages[SCALE]:
        stamp = scale["header"]["stamp"]
        i = index[stamp["sec"] * 1_000_000_000 + stamp["nsec"]]
        assert scale["vector"]["x"] == scale["scale"] == pytest.approx(0.02 + 0.001 * i)
    depth = messages[DEPTH][0]
    assert depth["encoding"] == "32FC1" and depth["step"] == 4 * W
    values = np.frombuffer(depth["data"], dtype="<f4")
    np.testing.assert_allclose(values, 0.05 + 0.001 * index[stamp_ns(depth)], rtol=1e-7)


def test_subprotocol_negotiation_of_the_viewers(dds_env):
    """Both names offered (either order) → foxglove.sdk.v1; only the old name or none → 400."""

    async def handshake(offer: list[str] | None) -> tuple[str | None, str]:
        protocols = None if offer is None else [websockets.Subprotocol(p) for p in offer]
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=protocols) as ws:
            return ws.subprotocol, json.loads(await ws.recv())["op"]

    async def refused(offer: list[str] | None) -> int:
        with pytest.raises(websockets.exceptions.InvalidStatus) as error:
            await handshake(offer)
        return error.value.response.status_code

    bridge, port, _ = start_bridge(dds_env)
    try:
        assert asyncio.run(handshake([WEBSOCKET_V1, SDK_V1])) == (SDK_V1, "serverInfo")
        assert asyncio.run(handshake([SDK_V1, WEBSOCKET_V1])) == (SDK_V1, "serverInfo")
        assert asyncio.run(handshake([SDK_V1])) == (SDK_V1, "serverInfo")
        # A viewer that knows only the old name (Lichtblick <= 1.21, Foxglove Studio 1.x)
        assert asyncio.run(refused([WEBSOCKET_V1])) == 400
        assert asyncio.run(refused(None)) == 400
        assert bridge.poll() is None  # refused handshakes do not disturb the server
        assert asyncio.run(handshake(SUBPROTOCOLS)) == (SDK_V1, "serverInfo")
    finally:
        stop(bridge)


def test_a_scale_of_any_type_is_found_in_the_graph(tmp_path, dds_env):
    """scale_type empty: the bridge subscribes with the type the graph reports."""
    bag = tmp_path / "scale.mcap"
    with BagWriter(bag) as writer:
        for i in range(10):
            t = T0 + i * PERIOD_NS
            writer.write_message(SCALE, Float64MultiArray(data=[0.5 + i, 0.25]), t)
    replay = subprocess.Popen(
        [str(BIN / "endo-replay"), str(bag), "--loop"],
        env=dds_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        bridge, port, output = start_bridge(dds_env, "scale_type:=''", "scale_field:=data[1]")
    except BaseException:
        stop(replay)
        raise
    try:
        end, seen = time.monotonic() + 30.0, []
        while time.monotonic() < end and not any("scale: " in line for line in seen):
            with contextlib.suppress(queue.Empty):
                seen.append(output.get(timeout=0.5))
        assert any("std_msgs/msg/Float64MultiArray" in line for line in seen), "".join(seen)
        result = asyncio.run(receive(port, {SCALE: 2}, timeout_s=20.0))
    finally:
        stop(replay)
        stop(bridge)
    channel = result["channels"][SCALE]
    assert channel["schemaName"] == "std_msgs/msg/Float64MultiArray"
    assert json.loads(channel["schema"])["properties"]["scale"]["type"] == ["number", "null"]
    for message in result["messages"][SCALE]:
        assert message["scale"] == 0.25 and message["data"][0] in [0.5 + i for i in range(10)]


# -- a client that never reads ------------------------------------------------------------------

class DiagnosticsListener:
    """/diagnostics of the bridge, in an rclpy context of its own, spun in a thread."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("foxglove_bridge_test", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.values: dict[str, str] = {}
        self.level = 0
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            if status.name.startswith("endo_foxglove"):
                self.values = {kv.key: kv.value for kv in status.values}
                self.level = int.from_bytes(status.level, "little") \
                    if isinstance(status.level, bytes) else int(status.level)

    def _spin(self) -> None:
        while self._running:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self._running = False
        self._thread.join()
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


async def stalled_and_reading_clients(
    port: int, publisher: subprocess.Popen[Any], timeout_s: float
) -> dict[str, int]:
    """One client subscribes and never reads again; another reads until the publisher ends."""
    async def subscribe(ws: Any) -> None:
        while True:
            message = json.loads(await ws.recv())
            if message["op"] == "advertise":
                ids = [c["id"] for c in message["channels"] if c["topic"] in (DEPTH, IMAGE_RAW)]
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": k + 1, "channelId": channel_id} for k, channel_id in enumerate(ids)
                ]}))
                return

    counts = {"stalled": 0, "reading": 0}
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None, max_queue=1
    ) as stalled, websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None
    ) as reading:
        await subscribe(stalled)
        await subscribe(reading)
        stalled.transport.pause_reading()  # never reads again: its socket buffers fill up
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and publisher.poll() is None:
            try:
                frame = await asyncio.wait_for(reading.recv(), timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(frame, bytes):
                counts["reading"] += 1
    return counts


def test_a_client_that_never_reads_does_not_stall_the_graph(tmp_path, dds_env):
    rate_hz, seconds = 20.0, 5.0
    listener = DiagnosticsListener()
    report = tmp_path / "publisher.json"
    # The publisher starts first and waits for the bridge's subscription.
    publisher = subprocess.Popen(
        [sys.executable, __file__, "publish", str(rate_hz), str(seconds), str(report)],
        env=dds_env,
    )
    try:
        bridge, port, _ = start_bridge(dds_env, "message_backlog_size:=4",
                                       "depth_max_rate_hz:=0.0", "image_raw_max_rate_hz:=0.0")
    except BaseException:
        stop(publisher)
        listener.close()
        raise
    try:
        counts = asyncio.run(stalled_and_reading_clients(port, publisher, timeout_s=40.0))
        assert publisher.wait(timeout=10) == 0
        time.sleep(1.5)  # one more diagnostics period
        values = dict(listener.values)
    finally:
        stop(publisher)
        stop(bridge)
        listener.close()

    published = json.loads(report.read_text())
    # The publisher kept its rate (640x480 float depth + mono image per frame).
    assert published["rate_hz"] >= 0.8 * rate_hz, published
    # The bridge went on converting and sending every frame it was given ...
    forwarded = int(values["forwarded.depth"])
    assert forwarded >= 0.7 * published["frames"], json.dumps([values, published])
    # ... and the reading client kept receiving while the other one stalled.
    assert counts["reading"] >= 0.5 * forwarded, counts
    # The stalled client's drops are counted and it is named.
    assert int(values["dropped.SlowClient"]) >= 1, values
    assert "127.0.0.1:" in values["slow_clients"], values


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_tls_serves_wss_only_and_bad_tls_settings_stop_with_one_line(tmp_path, dds_env):
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
         "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True,
    )
    bridge, port, _ = start_bridge(dds_env, f"tls_cert:={cert}", f"tls_key:={key}")

    async def handshake(url: str, context: ssl.SSLContext | None) -> str | None:
        async with websockets.connect(url, subprotocols=SUBPROTOCOLS, ssl=context) as ws:
            return json.loads(await ws.recv())["op"]

    try:
        trusted = ssl.create_default_context(cafile=str(cert))
        assert asyncio.run(handshake(f"wss://127.0.0.1:{port}", trusted)) == "serverInfo"
        with pytest.raises((websockets.exceptions.WebSocketException, OSError)):
            asyncio.run(handshake(f"ws://127.0.0.1:{port}", None))
    finally:
        stop(bridge)

    result = subprocess.run(
        [str(BIN / "endo-foxglove"), "--ros-args", "-p", "port:=0", "-p", f"tls_cert:={cert}"],
        env=dds_env, capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == (
        "endo-foxglove: ViewerError: TLS needs both tls_cert and tls_key"
    )
    assert "Traceback" not in result.stderr


def publish(rate_hz: float, seconds: float, report: Path) -> int:
    """Publisher process of the slow-client test: depth and raw image at ``rate_hz``."""
    rclpy.init()
    node = rclpy.create_node("slow_client_publisher")
    depth_pub = create_reliable_publisher(node, Image, DEPTH, depth=5)
    image_pub = create_reliable_publisher(node, Image, IMAGE_RAW, depth=5)
    depth = np.random.default_rng(1).uniform(0.02, 0.1, (480, 640)).astype(np.float32)
    image = (depth * 2000).astype(np.uint8)
    end_discovery = time.monotonic() + 20.0
    while depth_pub.get_subscription_count() == 0 and time.monotonic() < end_discovery:
        rclpy.spin_once(node, timeout_sec=0.05)
    stamps: list[float] = []

    def tick() -> None:
        t = time.time_ns()
        depth_pub.publish(array_to_image(depth, "32FC1", t, OPTICAL_FRAME))
        image_pub.publish(array_to_image(image, "mono8", t, OPTICAL_FRAME))
        stamps.append(time.monotonic())

    node.create_timer(1.0 / rate_hz, tick)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.01)
    span = stamps[-1] - stamps[0] if len(stamps) > 1 else float("inf")
    report.write_text(json.dumps({"frames": len(stamps), "rate_hz": (len(stamps) - 1) / span}))
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__" and sys.argv[1:2] == ["publish"]:
    sys.exit(publish(float(sys.argv[2]), float(sys.argv[3]), Path(sys.argv[4])))
