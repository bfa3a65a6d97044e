"""Cross-reading with rosbags and mcap-ros2-support, both directions, plus odd MCAP layouts.

Equality is checked field by field on plain nested values, so a reader that
decodes with its own parser (rosbags, mcap-ros2-support) must produce exactly
the values that rclpy put in.
"""

from __future__ import annotations

import array
import dataclasses
import importlib
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from mcap.records import Chunk, Footer
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as McapRos2Writer
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as RosbagsWriter
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Float32

from endo_io.bag import (
    BagReader,
    BagWriter,
    MessageDefinition,
    UnknownMessageTypeError,
    deserialize,
    message_definition,
    msgtype_of,
)
from endo_io.bag.mcap_file import McapFile
from endo_io.bag.metadata import FileSummary, TopicSummary, bag_metadata, write_metadata_yaml

T0 = 1_700_000_000_000_000_000


def image(encoding: str, dtype: type, channels: int, seed: int) -> Image:
    rng = np.random.default_rng(seed)
    h, w = 12, 16
    if dtype is np.float32:
        pixels = rng.uniform(0.01, 0.3, size=(h, w, channels)).astype(np.float32)
    else:
        pixels = rng.integers(0, np.iinfo(dtype).max, size=(h, w, channels), dtype=dtype)
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=0)
    msg.step = w * channels * np.dtype(dtype).itemsize
    msg.data = pixels.tobytes()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000 + seed, 999_999_999
    msg.header.frame_id = "endoscope_optical_frame"
    return msg


def camera_info() -> CameraInfo:
    msg = CameraInfo(width=640, height=480, distortion_model="rational_polynomial")
    msg.header.frame_id = "endoscope_optical_frame"
    msg.d = [-0.25, 0.125, 1e-3, -2e-3, 0.0, 0.5, -0.75, 0.0625]
    msg.k = [500.5, 0.0, 319.5, 0.0, 501.25, 239.5, 0.0, 0.0, 1.0]
    msg.p = [500.5, 0.0, 319.5, 0.0, 0.0, 501.25, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    msg.binning_y = 2
    msg.roi.do_rectify = True
    return msg


def pose(i: int) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = "tracker"
    msg.header.stamp.sec = i
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = 0.01 * i, -0.2, 1.5
    msg.pose.orientation.z, msg.pose.orientation.w = 0.6, 0.8
    return msg


def cloud() -> PointCloud2:
    points = np.arange(4 * 3 * 3, dtype=np.float32).reshape(4, 3, 3) / 7
    msg = PointCloud2(height=4, width=3, point_step=12, row_step=36, is_dense=True)
    msg.fields = [
        PointField(name=n, offset=4 * k, datatype=PointField.FLOAT32, count=1)
        for k, n in enumerate("xyz")
    ]
    msg.data = points.tobytes()
    msg.header.frame_id = "endoscope_optical_frame"
    return msg


def samples() -> list[tuple[str, Any, int]]:
    """(topic, rclpy message, log time ns), in log-time order."""
    return [
        ("/image/rgb8", image("rgb8", np.uint8, 3, 1), T0 + 1),
        ("/image/mono16", image("mono16", np.uint16, 1, 2), T0 + 2),
        ("/depth", image("32FC1", np.float32, 1, 3), T0 + 3),
        ("/camera_info", camera_info(), T0 + 4),
        ("/pose", pose(1), T0 + 5),
        ("/pose", pose(2), T0 + 6),
        ("/cloud", cloud(), T0 + 7),
        ("/scalar", Float32(data=-2.5), T0 + 8),
    ]


def plain(value: Any) -> Any:
    """Nested builtin values of a rclpy, rosbags or mcap-ros2 message."""
    if hasattr(value, "get_fields_and_field_types"):
        return {name: plain(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: plain(getattr(value, f.name))
            for f in dataclasses.fields(value)
            # rosbags adds __msgtype__ and the constants (upper case) as fields
            if not f.name.startswith("__") and not f.name.isupper()
        }
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, bytes | bytearray | array.array | list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    slots = getattr(type(value), "__slots__", None)
    if slots and type(value).__module__.startswith("mcap_ros2"):
        return {name: plain(getattr(value, name)) for name in slots}
    return value


def to_rosbags(msg: Any, store: Any) -> Any:
    """The rosbags typestore instance equal to an rclpy message."""
    fields = {}
    for name in msg.get_fields_and_field_types():
        value = getattr(msg, name)
        if hasattr(value, "get_fields_and_field_types"):
            fields[name] = to_rosbags(value, store)
        elif isinstance(value, array.array):
            fields[name] = np.array(value, dtype=np.dtype(value.typecode))
        elif isinstance(value, np.ndarray):
            fields[name] = value.copy()
        elif isinstance(value, list):
            fields[name] = [to_rosbags(v, store) for v in value]
        else:
            fields[name] = value
    return store.types[msgtype_of(msg)](**fields)


def to_mcap_ros2(msg: Any) -> Any:
    """The nested dict mcap-ros2-support encodes for an rclpy message."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: to_mcap_ros2(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, array.array | np.ndarray):
        return msg.tolist()
    if isinstance(msg, list):
        return [to_mcap_ros2(v) for v in msg]
    return msg


def write_ours(
    path: Path, compression: str = "zstd", *, crcs: bool = True
) -> list[tuple[str, Any, int]]:
    originals = samples()
    with BagWriter(path, compression=compression, chunk_size=2048, crcs=crcs) as writer:
        for topic, msg, t in originals:
            writer.write_message(topic, msg, t)
    return originals


@pytest.mark.parametrize(("name", "compression"), [("ours.mcap", "zstd"), ("ours_dir", "lz4")])
def test_rosbags_reads_our_bags(tmp_path, name, compression):
    path = tmp_path / name
    originals = write_ours(path, compression)
    with AnyReader([path]) as reader:
        got = [
            (c.topic, reader.deserialize(raw, c.msgtype), t, c.msgtype)
            for c, t, raw in reader.messages()
        ]
        assert {c.topic: c.msgcount for c in reader.connections}["/pose"] == 2
    assert len(got) == len(originals)
    for (topic, msg, t), (r_topic, r_msg, r_t, r_type) in zip(originals, got, strict=True):
        assert (r_topic, r_t, r_type) == (topic, t, msgtype_of(msg))
        assert plain(r_msg) == plain(msg)


def test_mcap_ros2_reads_our_bag(tmp_path):
    path = tmp_path / "ours.mcap"
    originals = write_ours(path, "zstd")
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        got = [
            (channel.topic, decoded, message.log_time)
            for _, channel, message, decoded in reader.iter_decoded_messages()
        ]
    assert len(got) == len(originals)
    for (topic, msg, t), (r_topic, r_msg, r_t) in zip(originals, got, strict=True):
        assert (r_topic, r_t) == (topic, t)
        assert plain(r_msg) == plain(msg)
    # The high-level mcap_ros2.reader (deprecated upstream, same decoder) agrees.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        ros2_reader = importlib.import_module("mcap_ros2.reader")
    high_level = [
        (m.channel.topic, plain(m.ros_msg), m.log_time_ns)
        for m in ros2_reader.read_ros2_messages(str(path))
    ]
    assert high_level == [(topic, plain(msg), t) for topic, msg, t in originals]


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_bag_without_crcs_reads_everywhere(tmp_path, compression):
    """crcs=False (endo-process, rosbag2 by default): CRCs stored as 0; every reader reads it."""
    path = tmp_path / "no_crc.mcap"
    originals = write_ours(path, compression, crcs=False)
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and len(summary.chunk_indexes) > 1
        got = [(c.topic, plain(d), m.log_time) for _, c, m, d in reader.iter_decoded_messages()]
    assert got == [(topic, plain(msg), t) for topic, msg, t in originals]
    with path.open("rb") as stream:
        records = list(StreamReader(stream, emit_chunks=True).records)
    assert {r.uncompressed_crc for r in records if isinstance(r, Chunk)} == {0}
    assert next(r for r in records if isinstance(r, Footer)).summary_crc == 0
    with BagReader(path) as ours:
        assert [(m.topic, plain(deserialize(m)), m.log_time_ns) for m in ours.messages()] == [
            (topic, plain(msg), t) for topic, msg, t in originals
        ]
    with AnyReader([path]) as rosbags_reader:
        assert len(list(rosbags_reader.messages())) == len(originals)


@pytest.mark.parametrize(
    ("store_name", "version"), [(Stores.ROS2_JAZZY, 9), (Stores.ROS2_HUMBLE, 8)]
)
def test_we_read_rosbags_mcap_bags(tmp_path, store_name, version):
    store = get_typestore(store_name)
    originals = samples()
    bag = tmp_path / "rosbags_bag"
    with RosbagsWriter(bag, version=version, storage_plugin=StoragePlugin.MCAP) as writer:
        connections: dict[str, Any] = {}
        for topic, msg, t in originals:
            msgtype = msgtype_of(msg)
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(
                connections[topic], t, store.serialize_cdr(to_rosbags(msg, store), msgtype)
            )
    with BagReader(bag) as reader:
        got = [(m.topic, deserialize(m), m.log_time_ns) for m in reader.messages()]
        assert reader.topics["/pose"].message_count == 2
        assert reader.topics["/camera_info"].msgtype == "sensor_msgs/msg/CameraInfo"
    assert got == originals
    # The lone .mcap file reads the same without its metadata.yaml.
    (mcap_path,) = bag.glob("*.mcap")
    with BagReader(mcap_path) as reader:
        assert [(m.topic, deserialize(m), m.log_time_ns) for m in reader.messages()] == originals


def test_we_read_mcap_ros2_bags(tmp_path):
    store = get_typestore(Stores.ROS2_JAZZY)  # an independent source of .msg text
    originals = samples()
    path = tmp_path / "mcap_ros2.mcap"
    with path.open("wb") as stream:
        writer = McapRos2Writer(stream, chunk_size=4096, compression=CompressionType.LZ4)
        schemas: dict[str, Any] = {}
        for topic, msg, t in originals:
            msgtype = msgtype_of(msg)
            if msgtype not in schemas:
                text, _ = store.generate_msgdef(msgtype, ros_version=2)
                schemas[msgtype] = writer.register_msgdef(msgtype, text)
            writer.write_message(topic, schemas[msgtype], to_mcap_ros2(msg), t, t - 1)
        writer.finish()
    with BagReader(path) as reader:
        got = [
            (m.topic, deserialize(m), m.log_time_ns, m.publish_time_ns) for m in reader.messages()
        ]
    assert got == [(topic, msg, t, t - 1) for topic, msg, t in originals]


def write_plain_mcap(path: Path, writer_options: dict[str, Any], log_times: list[int]) -> None:
    """Float32 messages (value = log time) through the bare mcap Writer, ros2 profile."""
    definition = message_definition("std_msgs/msg/Float32")
    with path.open("wb") as stream:
        writer = McapWriter(stream, **writer_options)
        writer.start(profile="ros2", library="test")
        schema_id = writer.register_schema(
            "std_msgs/msg/Float32", "ros2msg", definition.text.encode()
        )
        channel_id = writer.register_channel("/value", "cdr", schema_id)
        for t in log_times:
            writer.add_message(channel_id, t, serialize_message(Float32(data=float(t))), t)
        writer.finish()


# Log times out of order, so that chunks overlap in time.
SHUFFLED = [0, 500, 10, 510, 20, 520, 30, 530, 40, 540, 50, 550, 5, 505, 15, 515]


def read_float_values(path: Path) -> tuple[list[tuple[int, float]], McapFile]:
    with BagReader(path) as reader:
        values = [(m.log_time_ns, deserialize(m).data) for m in reader.messages()]
        assert reader.topics["/value"].message_count == len(SHUFFLED)
        return values, reader._files[0]


def test_no_summary_no_index_file_reads_in_time_order(tmp_path):
    path = tmp_path / "no_summary.mcap"
    options = {
        "chunk_size": 64,
        "compression": CompressionType.ZSTD,
        "index_types": IndexType.NONE,
        "repeat_channels": False,
        "repeat_schemas": False,
        "use_statistics": False,
        "use_summary_offsets": False,
    }
    write_plain_mcap(path, options, SHUFFLED)
    values, mcap_file = read_float_values(path)
    assert not mcap_file.used_index
    assert values == [(t, float(t)) for t in sorted(SHUFFLED)]


def test_unchunked_file_reads_in_time_order(tmp_path):
    path = tmp_path / "unchunked.mcap"
    write_plain_mcap(path, {"use_chunking": False}, SHUFFLED)
    values, mcap_file = read_float_values(path)
    assert not mcap_file.used_index
    assert values == [(t, float(t)) for t in sorted(SHUFFLED)]


def test_indexed_overlapping_chunks_read_in_time_order(tmp_path):
    path = tmp_path / "indexed.mcap"
    write_plain_mcap(path, {"chunk_size": 64, "compression": CompressionType.LZ4}, SHUFFLED)
    values, mcap_file = read_float_values(path)
    assert mcap_file.used_index
    assert values == [(t, float(t)) for t in sorted(SHUFFLED)]


def idl_definition(msgtype: str, dependencies: list[str]) -> str:
    """rosbag2's ros2idl text: each .idl preceded by 80 '=' and ``IDL: <type>``."""
    parts = []
    for name in [msgtype, *dependencies]:
        package, namespace, short = name.split("/")
        text = (Path(sys.prefix) / "share" / package / namespace / f"{short}.idl").read_text()
        parts.append(f"{'=' * 80}\nIDL: {name}\n{text}")
    return "\n".join(parts)


def test_ros2idl_schema_file(tmp_path):
    path = tmp_path / "idl.mcap"
    text = idl_definition(
        "geometry_msgs/msg/PoseStamped",
        [
            "std_msgs/msg/Header",
            "builtin_interfaces/msg/Time",
            "geometry_msgs/msg/Pose",
            "geometry_msgs/msg/Point",
            "geometry_msgs/msg/Quaternion",
        ],
    )
    poses = [pose(i) for i in range(3)]
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start(profile="ros2", library="test")
        schema_id = writer.register_schema(
            "geometry_msgs/msg/PoseStamped", "ros2idl", text.encode()
        )
        channel_id = writer.register_channel("/pose", "cdr", schema_id)
        for i, msg in enumerate(poses):
            writer.add_message(channel_id, 100 + i, serialize_message(msg), 100 + i)
        writer.finish()
    with BagReader(path) as reader:
        assert reader.topics["/pose"].msgtype == "geometry_msgs/msg/PoseStamped"
        assert [deserialize(m) for m in reader.messages()] == poses


WIDGET_MSG = "int32 count\nstring label\nfloat64[] weights\n"


def test_unknown_type_is_passed_through_raw(tmp_path):
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(WIDGET_MSG, "acme_msgs/msg/Widget"))
    widget_cls = store.types["acme_msgs/msg/Widget"]
    widgets = [
        store.serialize_cdr(
            widget_cls(i, f"w{i}", np.array([0.5 * i, -1.0])), "acme_msgs/msg/Widget"
        )
        for i in range(3)
    ]
    path = tmp_path / "unknown.mcap"
    with BagWriter(path) as writer:
        writer.add_topic(
            "/widget",
            "acme_msgs/msg/Widget",
            message_definition_override=MessageDefinition("ros2msg", WIDGET_MSG),
        )
        for i, data in enumerate(widgets):
            writer.write("/widget", data, 10 * i)
            writer.write_message("/scalar", Float32(data=float(i)), 10 * i + 1)
    with BagReader(path) as reader:
        got = list(reader.messages())
        assert reader.topics["/widget"].msgtype == "acme_msgs/msg/Widget"
        assert reader.topics["/widget"].message_count == 3
    assert [(m.topic, m.log_time_ns) for m in got] == [
        (topic, 10 * i + k) for i in range(3) for k, topic in enumerate(["/widget", "/scalar"])
    ]
    assert [m.data for m in got if m.topic == "/widget"] == widgets
    assert all(m.msgtype == "acme_msgs/msg/Widget" for m in got if m.topic == "/widget")
    for message in got:
        if message.topic == "/scalar":
            assert deserialize(message) == Float32(data=float(message.log_time_ns // 10))
        else:
            with pytest.raises(UnknownMessageTypeError, match="acme_msgs/msg/Widget"):
                deserialize(message)
    # A reader that only has the schema (rosbags) decodes the pass-through.
    with AnyReader([path]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/widget")
        decoded = [reader.deserialize(raw, conn.msgtype) for _, _, raw in reader.messages([conn])]
    assert [(d.count, d.label, d.weights.tolist()) for d in decoded] == [
        (i, f"w{i}", [0.5 * i, -1.0]) for i in range(3)
    ]


def test_type_without_any_definition_is_recorded_with_unknown_schema(tmp_path):
    path = tmp_path / "gadget.mcap"
    payload = b"\x00\x01\x00\x00\x07\x00\x00\x00"
    with BagWriter(path) as writer:
        writer.add_topic("/gadget", "acme_msgs/msg/Gadget")
        writer.write("/gadget", payload, 5)
    mcap_file = McapFile(path)
    try:
        (schema,) = mcap_file._schemas.values()
    finally:
        mcap_file.close()
    assert (schema.name, schema.encoding, schema.data) == ("acme_msgs/msg/Gadget", "unknown", b"")
    with BagReader(path) as reader:
        (message,) = reader.messages()
    assert (message.msgtype, message.data) == ("acme_msgs/msg/Gadget", payload)
    with pytest.raises(UnknownMessageTypeError):
        deserialize(message)


def test_split_bag_directory_merges_files_in_time_order(tmp_path):
    bag = tmp_path / "split_bag"
    bag.mkdir()
    topics = {"/a": [], "/b": []}
    files = []
    for index, (topic, times) in enumerate([("/a", range(0, 100, 10)), ("/b", range(5, 60, 10))]):
        name = f"split_bag_{index}.mcap"
        with BagWriter(bag / name, chunk_size=64) as writer:
            for t in times:
                writer.write_message(topic, Float32(data=float(t)), 1_000 + t)
                topics[topic].append(1_000 + t)
        files.append(FileSummary(name, 1_000 + min(times), max(times) - min(times), len(times)))
    summaries = [
        TopicSummary(t, "std_msgs/msg/Float32", "cdr", "", "", len(v)) for t, v in topics.items()
    ]
    write_metadata_yaml(bag, bag_metadata(summaries, files))
    expected = sorted((t, topic) for topic, times in topics.items() for t in times)
    with BagReader(bag) as reader:
        got = [(m.log_time_ns, m.topic, deserialize(m).data) for m in reader.messages()]
        assert reader.files == [bag / f.path for f in files]
        assert reader.topics["/a"].message_count == 10
        assert reader.topics["/b"].message_count == 6
        assert reader.time_range_ns == (1_000, 1_090)
    assert got == [(t, topic, float(t - 1_000)) for t, topic in expected]
    with BagReader(bag) as reader:  # filters apply across files
        window = [
            m.log_time_ns for m in reader.messages(topics=["/b"], start_ns=1_020, end_ns=1_040)
        ]
    assert window == [1_025, 1_035]
    # rosbags reads the directory through our metadata.yaml (file after file).
    with AnyReader([bag]) as reader:
        assert sorted(t for _, t, _ in reader.messages()) == [t for t, _ in expected]
