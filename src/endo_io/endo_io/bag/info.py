"""What a bag holds, as ``ros2 bag info`` tells it: files, size, time span, compression, topics.

:func:`bag_info` reads a ``.mcap`` file or a bag directory with
:class:`~endo_io.bag.BagReader` and counts every message it can read, so the
per-topic counts, times and frequencies are those of the messages that are
really there (of the intact part, for a damaged bag). :func:`format_bag_info`
prints it in ``ros2 bag info``'s layout, with a frequency per topic and the
chunk compression added.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from endo_io.bag.errors import BagCorruptError
from endo_io.bag.reader import BagReader, ChunkStats

_LABEL_WIDTH = 19  # "Topic information: " as ros2 bag info aligns its values


@dataclass(frozen=True)
class TopicStats:
    """One topic of a bag.

    Attributes:
        name: Topic name.
        msgtype: ROS 2 type, e.g. ``sensor_msgs/msg/Image``.
        serialization_format: ``cdr`` for rosbag2 bags.
        count: Messages read.
        first_ns: Log time of the first message (ns), None when there is none.
        last_ns: Log time of the last message (ns), None when there is none.
    """

    name: str
    msgtype: str
    serialization_format: str
    count: int
    first_ns: int | None
    last_ns: int | None

    @property
    def frequency_hz(self) -> float | None:
        """Mean message rate, ``(count - 1) / (last - first)``; None below two distinct times."""
        if self.count < 2 or self.first_ns is None or self.last_ns is None:
            return None
        span = self.last_ns - self.first_ns
        return (self.count - 1) * 1e9 / span if span > 0 else None


@dataclass(frozen=True)
class BagInfo:
    """Summary of one bag (a file or a bag directory).

    Attributes:
        path: What was opened.
        files: Its MCAP files.
        size_bytes: Their total size.
        ros_distro: From the bag's rosbag2 metadata ("" if it has none).
        start_ns: Earliest log time read (None for an empty bag).
        end_ns: Latest log time read.
        message_count: Messages read.
        chunks: Chunk count, compression and sizes.
        topics: Per-topic statistics, by topic name.
        damage: The one-line error of a damaged bag (everything before it was
            counted), else None.
        warnings: One-line warnings about the bag directory (see
            :attr:`BagReader.warnings`).
    """

    path: Path
    files: list[Path]
    size_bytes: int
    ros_distro: str
    start_ns: int | None
    end_ns: int | None
    message_count: int
    chunks: ChunkStats
    topics: list[TopicStats]
    damage: str | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def duration_ns(self) -> int:
        """End minus start, 0 for an empty bag."""
        if self.start_ns is None or self.end_ns is None:
            return 0
        return self.end_ns - self.start_ns


def bag_info(path: str | os.PathLike[str]) -> BagInfo:
    """Read a bag and summarise it.

    Raises:
        BagNotFoundError: the path (or a file metadata.yaml lists) is missing.
        BagError: it is not an MCAP file or rosbag2 MCAP directory.
    """
    with BagReader(path) as reader:
        counts: dict[str, int] = {}
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        damage = None
        try:
            for message in reader.messages():
                topic, stamp = message.topic, message.log_time_ns
                counts[topic] = counts.get(topic, 0) + 1
                if topic not in first or stamp < first[topic]:
                    first[topic] = stamp
                if topic not in last or stamp > last[topic]:
                    last[topic] = stamp
        except BagCorruptError as error:
            damage = str(error)
        topics = [
            TopicStats(
                name,
                info.msgtype,
                info.serialization_format,
                counts.get(name, 0),
                first.get(name),
                last.get(name),
            )
            for name, info in sorted(reader.topics.items())
        ]
        files = reader.files
        metadata = reader.metadata or {}
        return BagInfo(
            path=reader.path,
            files=files,
            size_bytes=sum(f.stat().st_size for f in files),
            ros_distro=str(metadata.get("ros_distro") or ""),
            start_ns=min(first.values(), default=None),
            end_ns=max(last.values(), default=None),
            message_count=sum(counts.values()),
            chunks=reader.chunk_stats,
            topics=topics,
            damage=damage,
            warnings=list(reader.warnings),
        )


def _size(n_bytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n_bytes < 1024 or unit == "GiB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1024
    raise AssertionError("unreachable")


def _stamp(ns: int) -> str:
    seconds, rest = divmod(ns, 1_000_000_000)
    local = time.strftime("%b %d %Y %H:%M:%S", time.localtime(seconds))
    return f"{local}.{rest:09d} ({seconds}.{rest:09d})"


def _compression(chunks: ChunkStats) -> str:
    if chunks.count == 0:
        return "none (no chunks)"
    kinds = ", ".join(
        f"{name or 'none'}" + (f" ({n} of {chunks.count} chunks)" if n != chunks.count else "")
        for name, n in sorted(chunks.compression.items())
    )
    ratio = chunks.uncompressed_bytes / chunks.compressed_bytes if chunks.compressed_bytes else 1.0
    return (
        f"{kinds}; {chunks.count} chunks, {_size(chunks.uncompressed_bytes)} uncompressed, "
        f"ratio {ratio:.2f}"
    )


def _labelled(label: str, lines: Iterable[str]) -> list[str]:
    out = []
    for i, line in enumerate(lines):
        head = f"{label}:" if i == 0 else ""
        out.append(f"{head:<{_LABEL_WIDTH}}{line}")
    return out


def format_bag_info(info: BagInfo) -> str:
    """``ros2 bag info``'s layout, plus per-topic frequency and chunk compression."""
    lines = _labelled("Files", [f.name for f in info.files])
    lines += _labelled("Bag size", [_size(info.size_bytes)])
    lines += _labelled("Storage id", ["mcap"])
    lines += _labelled("ROS Distro", [info.ros_distro or "unknown"])
    duration_s, duration_ns = divmod(info.duration_ns, 1_000_000_000)
    lines += _labelled("Duration", [f"{duration_s}.{duration_ns:09d}s"])
    if info.start_ns is not None and info.end_ns is not None:
        lines += _labelled("Start", [_stamp(info.start_ns)])
        lines += _labelled("End", [_stamp(info.end_ns)])
    lines += _labelled("Messages", [str(info.message_count)])
    lines += _labelled("Compression", [_compression(info.chunks)])
    width = max((len(t.name) for t in info.topics), default=0)
    type_width = max((len(t.msgtype) for t in info.topics), default=0)
    topic_lines = []
    for topic in info.topics:
        hz = topic.frequency_hz
        frequency = f"{hz:.2f} Hz" if hz is not None else "-"
        topic_lines.append(
            f"Topic: {topic.name:<{width}} | Type: {topic.msgtype:<{type_width}} | "
            f"Count: {topic.count} | Frequency: {frequency} | "
            f"Serialization Format: {topic.serialization_format}"
        )
    lines += _labelled("Topic information", topic_lines or ["(none)"])
    if info.damage:
        lines += _labelled("Damage", [info.damage])
    return "\n".join(lines)


__all__ = ["BagInfo", "TopicStats", "bag_info", "format_bag_info"]
