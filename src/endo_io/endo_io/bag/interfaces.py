"""The value types a bag reader hands out: one message, one topic's summary, chunk totals."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class BagMessage:
    """One recorded message, exactly as stored.

    Attributes:
        topic: Topic name, e.g. ``/endoscope/image_raw``.
        msgtype: ROS 2 type name, e.g. ``sensor_msgs/msg/Image`` ("" if the
            channel has no schema).
        log_time_ns: Receive time in integer nanoseconds (MCAP ``log_time``).
        data: The serialised message (CDR for rosbag2 bags), never decoded here.
        publish_time_ns: Publish time in integer nanoseconds (MCAP ``publish_time``).
    """

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes
    publish_time_ns: int


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """A recorded topic.

    Attributes:
        name: Topic name.
        msgtype: ROS 2 type name, e.g. ``sensor_msgs/msg/Image``.
        serialization_format: Message encoding, ``cdr`` for rosbag2 bags.
        offered_qos_profiles: The publishers' offered QoS as rosbag2 stores it
            (a YAML list, see :mod:`endo_io.bag.qos_yaml`); "" if not recorded.
        message_count: Number of messages on this topic in the bag (the intact
            part of it, for a damaged bag).
        type_description_hash: ``RIHS01_...`` type hash if recorded, else "".
    """

    name: str
    msgtype: str
    serialization_format: str
    offered_qos_profiles: str
    message_count: int
    type_description_hash: str = ""


@dataclass(frozen=True, slots=True)
class ChunkStats:
    """The chunks of a bag (of its intact part, for a damaged one).

    Attributes:
        count: Number of chunks.
        compression: Compression name (``zstd``, ``lz4``, "" for none) ->
            number of chunks using it.
        compressed_bytes: Their stored data size.
        uncompressed_bytes: Their declared uncompressed size.
    """

    count: int = 0
    compression: dict[str, int] = field(default_factory=dict)
    compressed_bytes: int = 0
    uncompressed_bytes: int = 0
