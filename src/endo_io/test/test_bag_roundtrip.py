"""BagWriter -> BagReader -> deserialize round trips, with exact equality."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Float32

from endo_io.bag import (
    BagError,
    BagReader,
    BagWriter,
    deserialize,
    message_class,
    message_definition,
    msgtype_of,
    qos_profiles_from_yaml,
    qos_profiles_to_yaml,
)
from endo_io.bag.mcap_file import McapFile
from endo_io.bag.msgdef import DEFINITION_SEPARATOR

COMPRESSIONS = ["zstd", "lz4", "none"]
# encoding -> (dtype, channels)
ENCODINGS = {
    "mono8": (np.uint8, 1),
    "mono16": (np.uint16, 1),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}


def make_image(encoding: str, seed: int, height: int = 24, width: int = 32) -> Image:
    dtype, channels = ENCODINGS[encoding]
    rng = np.random.default_rng(seed)
    if dtype is np.float32:
        array = rng.uniform(0.01, 0.2, size=(height, width)).astype(np.float32)
        array[0, :3] = np.nan  # invalid depth per REP 118
    else:
        array = rng.integers(0, np.iinfo(dtype).max, size=(height, width, channels), dtype=dtype)
    msg = Image(height=height, width=width, encoding=encoding, is_bigendian=0)
    msg.step = width * channels * np.dtype(dtype).itemsize
    msg.data = array.tobytes()
    msg.header.stamp.sec = 1_700_000_000 + seed
    msg.header.stamp.nanosec = 123_456_789
    msg.header.frame_id = "endoscope_optical_frame"
    return msg


def make_camera_info() -> CameraInfo:
    msg = CameraInfo(width=640, height=480, distortion_model="plumb_bob")
    msg.header.frame_id = "endoscope_optical_frame"
    msg.header.stamp.sec = 42
    msg.d = [-0.31, 0.12, 0.001, -0.002, 0.0]
    msg.k = [520.5, 0.0, 320.25, 0.0, 521.0, 240.75, 0.0, 0.0, 1.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [520.5, 0.0, 320.25, 0.0, 0.0, 521.0, 240.75, 0.0, 0.0, 0.0, 1.0, 0.0]
    msg.binning_x = 2
    msg.roi.x_offset = 4
    msg.roi.width = 100
    return msg


def make_pose(i: int) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = "tracker"
    msg.header.stamp.sec = i
    msg.pose.position.x = 0.125 * i
    msg.pose.position.y = -1.5e-3
    msg.pose.position.z = 3.0
    msg.pose.orientation.x = 0.5
    msg.pose.orientation.y = 0.5
    msg.pose.orientation.z = 0.5
    msg.pose.orientation.w = 0.5
    return msg


def make_cloud(seed: int) -> PointCloud2:
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(5, 7, 3)).astype(np.float32)
    points[1, 2] = np.nan
    msg = PointCloud2(height=5, width=7, is_bigendian=False, point_step=12, row_step=84)
    msg.fields = [
        PointField(name=n, offset=4 * k, datatype=PointField.FLOAT32, count=1)
        for k, n in enumerate("xyz")
    ]
    msg.data = points.tobytes()
    msg.is_dense = False
    msg.header.frame_id = "endoscope_optical_frame"
    return msg


def sample_messages() -> list[tuple[str, object, int]]:
    """(topic, message, log_time_ns) in log-time order, every kind the tests need."""
    out: list[tuple[str, object, int]] = []
    t = 1_700_000_000_000_000_000
    for k, encoding in enumerate(ENCODINGS):
        out.append((f"/image/{encoding}", make_image(encoding, k), t + 10 * k))
    out.append(("/camera_info", make_camera_info(), t + 100))
    for i in range(3):
        out.append(("/pose", make_pose(i), t + 200 + i))
    out.append(("/cloud", make_cloud(3), t + 300))
    for i in range(4):
        out.append(("/scalar", Float32(data=0.25 * i), t + 400 + i))
    return out


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_round_trip_every_message_kind(tmp_path, compression):
    originals = sample_messages()
    # CDR alignment padding is not zeroed by rclpy, so the same message can
    # serialise to different bytes twice: compare with the bytes written.
    payloads = [serialize_message(msg) for _, msg, _ in originals]
    path = tmp_path / "bag.mcap"
    with BagWriter(path, compression=compression, chunk_size=4096) as writer:
        for (topic, msg, t), payload in zip(originals, payloads, strict=True):
            writer.add_topic(topic, msgtype_of(msg))
            writer.write(topic, payload, t)
    with BagReader(path) as reader:
        got = list(reader.messages())
        topics = reader.topics
    assert len(got) == len(originals)
    for (topic, msg, t), payload, bag_msg in zip(originals, payloads, got, strict=True):
        assert bag_msg.topic == topic
        assert bag_msg.log_time_ns == t
        assert bag_msg.publish_time_ns == t
        assert bag_msg.msgtype == msgtype_of(msg)
        assert bag_msg.data == payload
        decoded = deserialize(bag_msg)
        assert type(decoded) is type(msg)
        assert decoded == msg
    assert topics["/pose"].message_count == 3
    assert topics["/scalar"].msgtype == "std_msgs/msg/Float32"
    assert topics["/image/32FC1"].serialization_format == "cdr"
    assert topics["/image/rgb8"].type_description_hash.startswith("RIHS01_")
    # NaN payloads compare bytewise, not as floats.
    depth = next(m for m in got if m.topic == "/image/32FC1")
    array = np.frombuffer(deserialize(depth).data, dtype=np.float32)
    assert np.isnan(array[:3]).all() and np.isfinite(array[3:]).all()


def test_write_message_serialises_with_rclpy(tmp_path):
    originals = sample_messages()
    path = tmp_path / "typed.mcap"
    with BagWriter(path, compression="zstd") as writer:
        for topic, msg, t in originals:
            writer.write_message(topic, msg, t)
    with BagReader(path) as reader:
        decoded = [(m.topic, deserialize(m), m.log_time_ns) for m in reader.messages()]
    assert decoded == originals


def test_raw_write_and_publish_time(tmp_path):
    path = tmp_path / "raw.mcap"
    payload = serialize_message(Float32(data=2.5))
    with BagWriter(path) as writer:
        writer.add_topic("/x", "std_msgs/msg/Float32")
        writer.write("/x", payload, 10, publish_time_ns=7)
        writer.write("/x", bytearray(payload), 20)
    with BagReader(path) as reader:
        got = list(reader.messages())
    assert [(m.log_time_ns, m.publish_time_ns, m.data) for m in got] == [
        (10, 7, payload),
        (20, 20, payload),
    ]
    assert deserialize(got[0]) == Float32(data=2.5)


def test_qos_offers_round_trip_through_channel_metadata(tmp_path):
    offers = [
        QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=7,
            reliability=ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
            deadline=Duration(seconds=2, nanoseconds=5),
        ),
        QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE),
    ]
    text = qos_profiles_to_yaml(offers)
    path = tmp_path / "qos.mcap"
    with BagWriter(path) as writer:
        writer.add_topic("/calib", "sensor_msgs/msg/CameraInfo", text)
        writer.write_message("/calib", make_camera_info(), 5)
    with BagReader(path) as reader:
        stored = reader.topics["/calib"].offered_qos_profiles
    assert stored == text
    parsed = qos_profiles_from_yaml(stored)
    assert parsed[0] == offers[0]
    assert parsed[1].history == HistoryPolicy.KEEP_ALL
    assert parsed[1].reliability == ReliabilityPolicy.RELIABLE
    assert parsed[0].deadline.nanoseconds == 2_000_000_005
    # Default (unset) durations are {0, 0}; rosbag2's layout and key order.
    first = yaml.safe_load(text)[0]
    assert list(first) == [
        "history",
        "depth",
        "reliability",
        "durability",
        "deadline",
        "lifespan",
        "liveliness",
        "liveliness_lease_duration",
        "avoid_ros_namespace_conventions",
    ]
    assert first["reliability"] == "best_effort"
    assert first["durability"] == "transient_local"
    assert first["lifespan"] == {"sec": 0, "nsec": 0}


def test_qos_yaml_reads_version8_integers_and_legacy_infinity():
    text = (
        "- history: 1\n  depth: 5\n  reliability: 1\n  durability: 2\n"
        "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
        "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n"
        "  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  avoid_ros_namespace_conventions: false\n"
    )
    (profile,) = qos_profiles_from_yaml(text)
    assert profile.history == HistoryPolicy.KEEP_LAST and profile.depth == 5
    assert profile.reliability == ReliabilityPolicy.RELIABLE
    assert profile.durability == DurabilityPolicy.VOLATILE
    assert profile.deadline.nanoseconds == 2**63 - 1
    assert profile.liveliness_lease_duration.nanoseconds == 2**63 - 1


def test_schema_is_complete_ros2msg_text(tmp_path):
    definition = message_definition("sensor_msgs/msg/Image")
    assert definition.encoding == "ros2msg"
    sections = definition.text.split(f"\n{DEFINITION_SEPARATOR}\n")
    assert [s.splitlines()[0] for s in sections[1:]] == [
        "MSG: std_msgs/Header",
        "MSG: builtin_interfaces/Time",
    ]
    assert "uint32 height" in sections[0] and "string encoding" in sections[0]
    assert "string frame_id" in sections[1]
    assert "uint32 nanosec" in sections[2]
    # The same text is what the bag stores as the schema.
    path = tmp_path / "schema.mcap"
    with BagWriter(path) as writer:
        writer.write_message("/i", make_image("mono8", 0), 1)
    mcap_file = McapFile(path)
    try:
        (schema,) = mcap_file._schemas.values()
        assert schema.encoding == "ros2msg"
        assert schema.data.decode() == definition.text
        assert mcap_file.profile == "ros2"
        assert mcap_file.rosbag2_metadata is not None
        assert mcap_file.rosbag2_metadata["message_count"] == 1
        assert mcap_file.rosbag2_metadata["storage_identifier"] == "mcap"
    finally:
        mcap_file.close()


def test_filters_by_topic_and_time(tmp_path):
    path = tmp_path / "filter.mcap"
    with BagWriter(path, chunk_size=64) as writer:
        for i in range(20):
            writer.write_message("/a", Float32(data=float(i)), 1000 + 10 * i)
            writer.write_message("/b", Float32(data=-float(i)), 1005 + 10 * i)
    with BagReader(path) as reader:
        only_b = [deserialize(m).data for m in reader.messages(topics=["/b"])]
        window = [(m.topic, m.log_time_ns) for m in reader.messages(start_ns=1050, end_ns=1080)]
        single = list(reader.messages(topics="/a", start_ns=1190))
    assert only_b == [-float(i) for i in range(20)]
    assert window == [
        ("/a", 1050),
        ("/b", 1055),
        ("/a", 1060),
        ("/b", 1065),
        ("/a", 1070),
        ("/b", 1075),
    ]
    assert [(m.topic, m.log_time_ns) for m in single] == [("/a", 1190)]


def test_overlapping_chunks_come_out_in_time_order(tmp_path):
    path = tmp_path / "overlap.mcap"
    chunks = [[0, 40, 80], [10, 20, 90], [5, 85, 86], [100]]
    with BagWriter(path, chunk_size=1 << 20) as writer:
        for chunk in chunks:
            for t in chunk:
                writer.write_message("/t", Float32(data=float(t)), t)
            writer.flush()
    with BagReader(path) as reader:
        times = [m.log_time_ns for m in reader.messages()]
        values = [deserialize(m).data for m in reader.messages()]
    expected = sorted(t for chunk in chunks for t in chunk)
    assert times == expected
    assert values == [float(t) for t in expected]


def test_equal_log_times_keep_write_order(tmp_path):
    path = tmp_path / "ties.mcap"
    with BagWriter(path, chunk_size=32) as writer:
        for i in range(10):
            writer.write_message("/t", Float32(data=float(i)), 500)
    with BagReader(path) as reader:
        assert [deserialize(m).data for m in reader.messages()] == [float(i) for i in range(10)]


def test_directory_bag_writes_metadata_yaml(tmp_path):
    bag = tmp_path / "run1"
    with BagWriter(bag, compression="lz4") as writer:
        writer.add_topic(
            "/scalar", "std_msgs/msg/Float32", qos_profiles_to_yaml([QoSProfile(depth=3)])
        )
        for i in range(5):
            writer.write_message("/scalar", Float32(data=float(i)), 100 + i)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9
    assert meta["relative_file_paths"] == ["run1_0.mcap"]
    assert meta["message_count"] == 5
    assert meta["starting_time"]["nanoseconds_since_epoch"] == 100
    assert meta["duration"]["nanoseconds"] == 4
    (topic,) = meta["topics_with_message_count"]
    assert topic["message_count"] == 5
    assert topic["topic_metadata"]["type"] == "std_msgs/msg/Float32"
    assert topic["topic_metadata"]["offered_qos_profiles"][0]["depth"] == 3
    with BagReader(bag) as reader:
        assert [deserialize(m).data for m in reader.messages()] == [0.0, 1.0, 2.0, 3.0, 4.0]
        assert reader.files == [bag / "run1_0.mcap"]


def test_directory_bag_splits_by_size(tmp_path):
    bag = tmp_path / "split"
    with BagWriter(bag, chunk_size=256, split_size_bytes=2000) as writer:
        for i in range(60):
            writer.write_message("/scalar", Float32(data=float(i)), 1000 + i)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert len(meta["relative_file_paths"]) >= 2
    assert sum(f["message_count"] for f in meta["files"]) == 60
    with BagReader(bag) as reader:
        assert len(reader.files) == len(meta["relative_file_paths"])
        assert reader.topics["/scalar"].message_count == 60
        assert [deserialize(m).data for m in reader.messages()] == [float(i) for i in range(60)]


def test_message_class_and_writer_misuse(tmp_path):
    assert message_class("sensor_msgs/msg/Image") is Image
    assert message_class("std_msgs/Float32") is Float32
    path = tmp_path / "misuse.mcap"
    with BagWriter(path) as writer:
        writer.add_topic("/a", "std_msgs/msg/Float32")
        writer.add_topic("/a", "std_msgs/msg/Float32")  # same again: fine
        with pytest.raises(BagError, match="already added"):
            writer.add_topic("/a", "sensor_msgs/msg/Image")
        with pytest.raises(BagError, match="not added"):
            writer.write("/nope", b"\x00", 1)
        with pytest.raises(BagError, match="unsigned 64-bit"):
            writer.write("/a", b"\x00", -1)
    with pytest.raises(BagError, match="closed"):
        writer.write("/a", b"\x00", 1)
    with pytest.raises(BagError, match="already exists"):
        BagWriter(path)
    with pytest.raises(BagError, match="compression"):
        BagWriter(tmp_path / "other.mcap", compression="bz2")


def test_check_types_names_the_topic_and_both_types(tmp_path):
    from std_msgs.msg import String

    from endo_io.bag import TopicTypeError

    path = tmp_path / "typed.mcap"
    with BagWriter(path) as writer:
        writer.write_message("/image", String(data="x"), 5)
    with BagReader(path) as reader:
        reader.check_types({"/image": "std_msgs/msg/String", "/absent": "sensor_msgs/msg/Image"})
        with pytest.raises(TopicTypeError) as raised:
            reader.check_types({"/image": "sensor_msgs/msg/Image"})
    expected = f"{path}: /image holds std_msgs/msg/String, not sensor_msgs/msg/Image"
    assert str(raised.value) == expected
