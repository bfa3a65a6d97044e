"""The two value types a bag reader hands out: one message, and one topic's summary."""

from __future__ import annotations

from dataclasses import dataclass


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
