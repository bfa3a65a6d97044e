"""The value types a bag reader hands out: a message, a topic's summary, chunk totals, damage."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal


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


#: What a damaged region cost (:attr:`DamagedRegion.lost`): ``span``, the
#: messages logged from ``start_ns`` to ``end_ns`` (a chunk or a message
#: record that cannot be read: the messages before and after it are read);
#: ``rest``, every message of the file logged from ``start_ns`` on (the file is
#: cut there, or unreadable from there on); ``none``, no message (a metadata
#: record, the closing magic).
LostMessages = Literal["span", "rest", "none"]


@dataclass(frozen=True, slots=True)
class DamagedRegion:
    """A damaged region of one MCAP file, and which messages it cost, by log time.

    Attributes:
        path: The MCAP file.
        offset: Byte offset in it where the damage starts.
        file_size: The file's size in bytes.
        reason: What is wrong there, one line (``chunk CRC mismatch (...)``).
        lost: Which messages it cost (:data:`LostMessages`).
        start_ns: For ``span``, the earliest log time of the messages lost
            (the chunk's ``message_start_time``); for ``rest``, the latest log
            time read before the damage (messages logged at it may be lost
            too, later ones are); None for ``none``, or for ``rest`` when
            nothing before the damage was read.
        end_ns: For ``span``, the latest log time of the messages lost
            (inclusive); None otherwise (``rest``: open to the end).
        lost_counts: Topic -> messages lost, as the file's message indexes
            count them; None where they do not say (no index, a damaged
            index, ``rest``).
    """

    path: Path
    offset: int
    file_size: int
    reason: str
    lost: LostMessages
    start_ns: int | None = None
    end_ns: int | None = None
    lost_counts: dict[str, int] | None = None

    def __str__(self) -> str:
        """The one line the reader's :class:`~endo_io.bag.BagCorruptError` says for it."""
        return (
            f"{self.path}: truncated or corrupt at byte {self.offset} of {self.file_size} "
            f"({self.reason})"
        )
