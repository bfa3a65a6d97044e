"""Repairing bags: a clean copy of what a damaged file still holds, and a fresh metadata.yaml.

* :func:`recover` reads every intact message of a damaged, truncated or
  SIGKILLed bag and writes them into a new, complete file (summary, footer,
  the source's schemas, QoS offers and type hashes), saying how many were
  kept and how many the source's own indexes count as lost.
* :func:`reindex` rewrites a bag directory's ``metadata.yaml`` from the MCAP
  files in it (what ``ros2 bag reindex`` does), for a directory whose
  metadata is missing, stale, or lists files twice or not at all.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from endo_io.bag.errors import BagCorruptError, BagError, BagNotFoundError
from endo_io.bag.metadata import (
    METADATA_FILENAME,
    FileSummary,
    TopicSummary,
    bag_metadata,
    read_metadata_yaml,
    split_file_order,
    write_metadata_yaml,
)
from endo_io.bag.reader import BagReader
from endo_io.bag.writer import BagWriter


@dataclass
class RecoverReport:
    """What :func:`recover` kept.

    Attributes:
        kept: Topic -> messages written to the new file.
        counted: Topic -> messages the source's indexes (summary statistics,
            message indexes) count; for a file cut inside a chunk, the part of
            that chunk after the cut is counted nowhere.
        damage: The source's one-line damage error, None if it was intact.
    """

    kept: dict[str, int] = field(default_factory=dict)
    counted: dict[str, int] = field(default_factory=dict)
    damage: str | None = None

    @property
    def kept_total(self) -> int:
        """Messages written to the new file."""
        return sum(self.kept.values())

    @property
    def lost_total(self) -> int:
        """Messages the source's indexes count that could not be read."""
        return sum(max(0, n - self.kept.get(t, 0)) for t, n in self.counted.items())


def recover(
    source: str | os.PathLike[str],
    target: str | os.PathLike[str],
    *,
    compression: str | None = None,
) -> RecoverReport:
    """Write every intact message of ``source`` into a new bag ``target``.

    Args:
        source: A ``.mcap`` file or bag directory, damaged or not.
        target: New ``.mcap`` file or bag directory (must not exist).
        compression: Chunk compression of the new file; None: the one most of
            the source's chunks use (zstd if it has none).

    Returns:
        The counts kept and lost.

    Raises:
        BagNotFoundError: ``source`` is missing.
        BagError: ``source`` is not an MCAP bag, or ``target`` exists or
            cannot be written.
    """
    report = RecoverReport()
    with BagReader(source) as reader:
        if compression is None:
            chunks = reader.chunk_stats.compression
            common = max(chunks, key=lambda name: chunks[name]) if chunks else "zstd"
            compression = common or "none"
        definitions = reader.definitions()
        with BagWriter(target, compression=compression) as writer:
            for name, info in reader.topics.items():
                writer.add_topic(
                    name,
                    info.msgtype,
                    info.offered_qos_profiles,
                    message_definition_override=definitions.get(name),
                    type_description_hash_override=info.type_description_hash or None,
                )
                report.counted[name] = info.message_count
                report.kept[name] = 0
            try:
                for message in reader.messages():
                    writer.write(
                        message.topic, message.data, message.log_time_ns, message.publish_time_ns
                    )
                    report.kept[message.topic] += 1
            except BagCorruptError as error:
                report.damage = str(error)
    return report


@dataclass
class ReindexReport:
    """What :func:`reindex` wrote.

    Attributes:
        path: The metadata.yaml written.
        files: The MCAP files it lists, in order.
        message_count: Messages it counts (the intact ones).
        previous_count: The count of the metadata.yaml it replaced, None if
            there was none (or it was unreadable).
        damage: One-line errors of damaged files (their intact messages are
            counted).
    """

    path: Path
    files: list[str]
    message_count: int
    previous_count: int | None
    damage: list[str] = field(default_factory=list)


def reindex(directory: str | os.PathLike[str]) -> ReindexReport:
    """Rewrite ``<directory>/metadata.yaml`` from the ``.mcap`` files in it.

    Every ``*.mcap`` file in the directory is listed once, split files in
    ``_<n>`` order; counts, times and topics are those of the intact
    messages of each file. The old metadata's ``ros_distro`` is kept.

    Raises:
        BagNotFoundError: ``directory`` does not exist.
        BagError: it is not a directory, holds no ``.mcap`` file, or a file
            in it is not MCAP.
    """
    directory = Path(directory)
    if not directory.exists():
        raise BagNotFoundError(f"{directory}: no such bag directory")
    if not directory.is_dir():
        raise BagError(
            f"{directory}: not a directory (reindex rewrites a bag directory's {METADATA_FILENAME})"
        )
    files = sorted(directory.glob("*.mcap"), key=split_file_order)
    if not files:
        raise BagError(f"{directory}: holds no .mcap files to index")
    previous_count: int | None = None
    ros_distro: str | None = None
    try:
        previous = read_metadata_yaml(directory)
        previous_count = int(previous.get("message_count", 0))
        ros_distro = previous.get("ros_distro") or None
    except (BagError, TypeError, ValueError):
        pass
    topics: dict[str, TopicSummary] = {}
    summaries: list[FileSummary] = []
    damage: list[str] = []
    for path in files:
        with BagReader(path) as reader:
            counts = dict.fromkeys(reader.topics, 0)
            start, end = None, None
            try:
                for message in reader.messages():
                    counts[message.topic] += 1
                    stamp = message.log_time_ns
                    start = stamp if start is None else min(start, stamp)
                    end = stamp if end is None else max(end, stamp)
            except BagCorruptError as error:
                damage.append(str(error))
            if start is None or end is None:
                summaries.append(FileSummary(path.name, 0, 0, 0))
            else:
                summaries.append(FileSummary(path.name, start, end - start, sum(counts.values())))
            for name, info in reader.topics.items():
                known = topics.get(name)
                topics[name] = TopicSummary(
                    name=name,
                    msgtype=info.msgtype,
                    serialization_format=info.serialization_format,
                    offered_qos_profiles=(known or info).offered_qos_profiles,
                    type_description_hash=info.type_description_hash,
                    message_count=counts[name] + (known.message_count if known else 0),
                )
    metadata = bag_metadata(list(topics.values()), summaries, ros_distro=ros_distro)
    written = write_metadata_yaml(directory, metadata)
    return ReindexReport(
        path=written,
        files=[p.name for p in files],
        message_count=sum(s.message_count for s in summaries),
        previous_count=previous_count,
        damage=damage,
    )


__all__ = ["RecoverReport", "ReindexReport", "recover", "reindex"]
