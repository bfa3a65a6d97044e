"""Read rosbag2 MCAP bags: one ``.mcap`` file, or a bag directory of split files.

A bag directory is described by its ``metadata.yaml``; its
``relative_file_paths`` name the MCAP files, whose messages are merged here
into one log-time-ordered stream. See :mod:`endo_io.bag.mcap_file` for how a
single file is read, including damaged ones.

When metadata.yaml and the directory disagree, the files decide, and each
discrepancy is one line in :attr:`BagReader.warnings`:

* a file listed twice (or under two spellings) is read once;
* an ``.mcap`` file in the directory that metadata.yaml does not list is read
  too (a writer stopped between creating a split file and rewriting the
  metadata, or a hand-edited list);
* a message count that differs from what the files hold is reported as
  stale (``endo-bag reindex DIR`` rewrites metadata.yaml from the files).

A listed file that is missing is still an error: data that the bag says
exists is gone, and playing the rest must be a deliberate choice (reindex).
"""

from __future__ import annotations

import dataclasses
import heapq
import os
import shlex
import types
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from endo_io.bag.errors import BagCorruptError, BagError, BagNotFoundError, TopicTypeError
from endo_io.bag.interfaces import BagMessage, ChunkStats, DamagedRegion, TopicInfo
from endo_io.bag.mcap_file import McapFile
from endo_io.bag.mcap_records import DEFAULT_MAX_CHUNK_BYTES
from endo_io.bag.metadata import read_metadata_yaml, split_file_order
from endo_io.bag.msgdef import MessageDefinition
from endo_io.bag.qos_yaml import qos_profiles_text


def _log_time(message: BagMessage) -> int:
    return message.log_time_ns


class BagReader:
    """Read a rosbag2-compatible MCAP bag.

    Args:
        path: A ``.mcap`` file, or a rosbag2 bag directory with metadata.yaml
            (its files are merged in log-time order).
        validate_crcs: Check chunk CRCs where the writer stored them.
        max_chunk_bytes: Treat a chunk declaring more uncompressed bytes as
            damaged (bounds the memory a corrupt or hostile file can cost).

    Raises:
        BagNotFoundError: the path, metadata.yaml or a listed file is missing.
        BagError: not an MCAP file / not a rosbag2 MCAP directory.

    Attributes:
        topics: Topic name -> :class:`TopicInfo`, over all files.
        metadata: The rosbag2 ``BagMetadata`` mapping (from metadata.yaml or
            the file's ``rosbag2`` record), or None if the bag has none.
        warnings: One line per way a bag directory's metadata.yaml disagrees
            with its files (see the module docstring); empty for a file.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        validate_crcs: bool = True,
        max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES,
    ) -> None:
        self.path = Path(path)
        self.metadata: dict[str, Any] | None = None
        self.warnings: list[str] = []
        self._files: list[McapFile] = []
        if not self.path.exists():
            raise BagNotFoundError(f"{self.path}: no such bag file or directory")
        try:
            if self.path.is_dir():
                self.metadata = read_metadata_yaml(self.path)
                storage = self.metadata.get("storage_identifier", "mcap")
                if storage != "mcap":
                    # rosbags (an endo_io dependency) converts; so does `ros2 bag convert`
                    raise BagError(
                        f"{self.path}: storage '{storage}' is not supported, only mcap "
                        f"(convert it: rosbags-convert --src {shlex.quote(str(self.path))} "
                        f"--dst {shlex.quote(str(self.path.with_name(self.path.name + '_mcap')))} "
                        "--dst-storage mcap)"
                    )
                if self.metadata.get("compression_mode"):
                    raise BagError(
                        f"{self.path}: rosbag2 {self.metadata['compression_mode']} compression "
                        "is not supported (MCAP chunk compression is)"
                    )
                for member in self._member_paths(self.metadata["relative_file_paths"]):
                    self._files.append(
                        McapFile(
                            member, validate_crcs=validate_crcs, max_chunk_bytes=max_chunk_bytes
                        )
                    )
            else:
                self._files.append(
                    McapFile(
                        self.path, validate_crcs=validate_crcs, max_chunk_bytes=max_chunk_bytes
                    )
                )
                self.metadata = self._files[0].rosbag2_metadata
        except BaseException:
            self.close()
            raise
        self.topics: dict[str, TopicInfo] = self._merge_topics()
        if self.path.is_dir():
            self._check_count()

    def _member_path(self, relative: str) -> Path:
        candidate = self.path / relative
        if not candidate.exists():
            # rosbag2 < version 4 stored paths including the bag directory name.
            fallback = self.path / Path(relative).name
            if fallback.exists():
                return fallback
            raise BagNotFoundError(
                f"{candidate}: listed in {self.path}/metadata.yaml but missing "
                f"(endo-bag reindex {self.path} lists the files that are there)"
            )
        return candidate

    def _member_paths(self, listed: list[str]) -> list[Path]:
        """The files to read: each listed file once, then the unlisted ``*.mcap`` files."""
        members: list[Path] = []
        seen: set[Path] = set()
        repeated: list[str] = []
        for relative in listed:
            member = self._member_path(relative)
            key = member.resolve()
            if key in seen:
                repeated.append(member.name)
                continue
            seen.add(key)
            members.append(member)
        if repeated:
            names = ", ".join(dict.fromkeys(repeated))
            self.warnings.append(
                f"{self.path}/metadata.yaml lists {names} more than once; reading each file once"
            )
        unlisted = sorted(
            (p for p in self.path.glob("*.mcap") if p.resolve() not in seen), key=split_file_order
        )
        if unlisted:
            names = ", ".join(p.name for p in unlisted)
            self.warnings.append(
                f"{self.path}/metadata.yaml does not list {names}; reading "
                f"{'it' if len(unlisted) == 1 else 'them'} too "
                f"(endo-bag reindex {self.path} rewrites metadata.yaml)"
            )
        return members + unlisted

    def _check_count(self) -> None:
        assert self.metadata is not None
        listed = self.metadata.get("message_count")
        held = self.message_count
        if not isinstance(listed, int) or listed == held:
            return
        if held < listed and self.damage is not None:
            return  # a damaged file: the damage error says what is missing
        self.warnings.append(
            f"{self.path}/metadata.yaml counts {listed} messages, the files hold {held}: it is "
            f"stale (endo-bag reindex {self.path} rewrites it)"
        )

    def _merge_topics(self) -> dict[str, TopicInfo]:
        merged: dict[str, TopicInfo] = {}
        for mcap_file in self._files:
            for name, info in mcap_file.topics().items():
                previous = merged.get(name)
                if previous is None:
                    merged[name] = info
                else:
                    merged[name] = dataclasses.replace(
                        previous, message_count=previous.message_count + info.message_count
                    )
        # metadata.yaml may carry QoS offers for topics whose channels lack them.
        if self.metadata is not None and self.path.is_dir():
            for entry in self.metadata.get("topics_with_message_count") or []:
                topic = (entry or {}).get("topic_metadata") or {}
                known = merged.get(topic.get("name", ""))
                if known is not None and not known.offered_qos_profiles:
                    qos = qos_profiles_text(topic.get("offered_qos_profiles"))
                    merged[known.name] = dataclasses.replace(known, offered_qos_profiles=qos)
        return merged

    @property
    def files(self) -> list[Path]:
        """The MCAP files of this bag, in metadata order."""
        return [f.path for f in self._files]

    @property
    def message_count(self) -> int:
        """Messages in the (intact part of the) bag."""
        return sum(t.message_count for t in self.topics.values())

    @property
    def chunk_stats(self) -> ChunkStats:
        """Chunk count, compression and sizes over all files (complete chunks only)."""
        compression: dict[str, int] = {}
        count = compressed = uncompressed = 0
        for mcap_file in self._files:
            stats = mcap_file.chunk_stats()
            count += stats.count
            compressed += stats.compressed_bytes
            uncompressed += stats.uncompressed_bytes
            for name, n in stats.compression.items():
                compression[name] = compression.get(name, 0) + n
        return ChunkStats(count, compression, compressed, uncompressed)

    def check_types(self, expected: dict[str, str]) -> None:
        """Check that each recorded topic of ``expected`` holds the type a tool reads from it.

        Args:
            expected: topic name -> ROS 2 type (``sensor_msgs/msg/Image``);
                topics the bag does not have are not checked (the caller says
                what a missing one means).

        Raises:
            TopicTypeError: one line naming the topic, the type it holds and
                the type expected.
        """
        for name, msgtype in expected.items():
            info = self.topics.get(name)
            if info is not None and info.msgtype != msgtype:
                raise TopicTypeError(
                    f"{self.path}: {name} holds {info.msgtype or 'messages without a type'}, "
                    f"not {msgtype}"
                )

    def definitions(self) -> dict[str, MessageDefinition]:
        """Topic -> message definition as the bag's schemas store it (first file wins)."""
        result: dict[str, MessageDefinition] = {}
        for mcap_file in self._files:
            for topic, definition in mcap_file.definitions().items():
                result.setdefault(topic, definition)
        return result

    @property
    def time_range_ns(self) -> tuple[int, int] | None:
        """(earliest, latest) log time in ns, None for an empty bag."""
        ranges = [r for f in self._files if (r := f.time_range()) is not None]
        if not ranges:
            return None
        return min(r[0] for r in ranges), max(r[1] for r in ranges)

    @property
    def damage(self) -> str | None:
        """One-line description of damage found so far (reading may find more), or None."""
        errors = [e for f in self._files if (e := f.corrupt_error()) is not None]
        return str(errors[0]) if errors else None

    @property
    def damaged_regions(self) -> list[DamagedRegion]:
        """Every damaged region found so far, per file in order, by offset.

        Each says which messages it cost, by log time
        (:class:`~endo_io.bag.interfaces.DamagedRegion`). Regions found at
        opening are here at once; a damaged chunk is found when reading gets
        to its start time, so one after the messages read so far may be
        missing (stay after the reading to know them all). A file of a split
        bag cut before any message could be read loses what was logged after
        the files before it: its ``rest`` starts at their latest log time.
        """
        regions: list[DamagedRegion] = []
        latest: int | None = None  # the latest log time of the files before this one
        for mcap_file in self._files:
            for region in mcap_file.damaged_regions:
                if region.lost == "rest" and region.start_ns is None and latest is not None:
                    region = dataclasses.replace(region, start_ns=latest)
                regions.append(region)
            span = mcap_file.time_range()
            if span is not None:
                latest = span[1] if latest is None else max(latest, span[1])
        return regions

    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[BagMessage]:
        """Iterate messages in log-time order (ties keep file order), raw CDR.

        Args:
            topics: Topic names to read (None: all).
            start_ns: Only log times >= start_ns.
            end_ns: Only log times < end_ns.

        Raises:
            BagCorruptError: after every intact message has been yielded, if
                any file is truncated or damaged (the message names the file
                and byte offset).
        """
        if isinstance(topics, str):
            topics = [topics]
        wanted = frozenset(topics) if topics is not None else None
        if len(self._files) == 1:
            yield from self._files[0].messages(wanted, start_ns, end_ns)
            return
        errors: list[BagCorruptError] = []

        def intact(mcap_file: McapFile) -> Iterator[BagMessage]:
            try:
                yield from mcap_file.messages(wanted, start_ns, end_ns)
            except BagCorruptError as exc:
                errors.append(exc)

        yield from heapq.merge(*(intact(f) for f in self._files), key=_log_time)
        if errors:
            raise errors[0]

    def close(self) -> None:
        """Close all files."""
        for mcap_file in self._files:
            mcap_file.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: types.TracebackType | None,
    ) -> None:
        self.close()
