"""rosbag2-compatible MCAP writer.

What a file written here contains (see docs/bag_format.md):

* MCAP ``ros2`` profile; one Schema per type with its complete ``ros2msg``
  definition (:mod:`endo_io.bag.msgdef`); one ``cdr`` Channel per topic with
  metadata ``offered_qos_profiles`` and ``topic_type_hash``;
* messages in zstd (default), lz4 or uncompressed chunks, each chunk followed
  by its message indexes; on close a ``rosbag2`` Metadata record, the summary
  (schemas, channels, statistics, chunk/metadata indexes) and the footer.

Crash behaviour: every byte goes straight to the operating system (no Python
buffer), and the MCAP library writes a chunk only once it is complete, so a
process killed with SIGKILL leaves a file whose every complete chunk can be
read back (by :class:`endo_io.bag.BagReader`, which falls back to a linear
scan when the summary is missing). Only the chunk still being filled in
memory is lost; :meth:`BagWriter.flush` closes it early.

What counts as *written* is what is in a complete chunk on disk:
:attr:`BagWriter.written` counts those messages per topic, and the metadata
(metadata.yaml, the ``rosbag2`` record) counts only them. A write that fails
(a full disk, a file size limit) is cut back to the last whole record, so the
file still reads to its last complete chunk; the writer then refuses further
writes, and the messages of the chunk that did not fit are counted in
:attr:`BagWriter.lost`.

Paths: ``*.mcap`` writes that single file. Any other path is a rosbag2 bag
directory, created here, holding ``<name>_0.mcap`` (``_1``, ... when
``split_size_bytes`` is set) and a ``metadata.yaml`` that is written at once,
rewritten at every new topic and split, at each :meth:`BagWriter.flush`, at
most every :data:`METADATA_PERIOD_S` as chunks are written, and on close: the
directory of a killed recording opens as a bag and counts what its files hold.
"""

from __future__ import annotations

import contextlib
import os
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, cast

from mcap.opcode import Opcode
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from endo_io.bag.errors import BagError
from endo_io.bag.metadata import (
    ROSBAG2_METADATA_RECORD,
    SERIALIZED_METADATA_KEY,
    FileSummary,
    TopicSummary,
    bag_metadata,
    dump_bag_metadata,
    write_metadata_yaml,
)
from endo_io.bag.msgdef import MessageDefinition, message_definition, type_description_hash
from endo_io.bag.serde import msgtype_of, serialize

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
#: Chunk compressions a writer accepts.
COMPRESSIONS: tuple[str, ...] = tuple(_COMPRESSION)
#: A bag directory's metadata.yaml is rewritten at most this often as chunks
#: are written (and at every flush), so that a killed recorder's count is current.
METADATA_PERIOD_S = 1.0
_LIBRARY = "endo_io.bag"
_MAX_TIME_NS = 2**64 - 1


class _OsFileSink:
    """Write-only file that hands every write to the OS at once.

    Page-cache writes survive the death of the process, so a SIGKILLed
    recorder loses nothing that the MCAP writer had already written. A write
    that fails part way (a full disk) is cut back off the file, which then
    ends at the last whole record (the MCAP writer hands over one record, or
    one chunk's message indexes, per call); ``chunks_written`` counts the
    chunk records written whole.
    """

    def __init__(self, path: Path) -> None:
        try:
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError as exc:
            raise BagError(f"{path}: already exists, will not overwrite a bag") from exc
        except OSError as exc:
            raise BagError(f"{path}: cannot create ({exc.strerror})") from exc
        self.path = path
        self._position = 0
        self.chunks_written = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        start = self._position
        try:
            while view.nbytes:
                written = os.write(self._fd, view)
                view = view[written:]
                self._position += written
        except OSError:
            with contextlib.suppress(OSError):  # if this fails too, readers stop at the cut
                os.ftruncate(self._fd, start)
                self._position = start
            raise
        if len(data) and data[0] == Opcode.CHUNK:
            self.chunks_written += 1
        return len(data)

    def tell(self) -> int:
        return self._position

    def flush(self) -> None:
        """Nothing is buffered here."""

    def close(self) -> None:
        os.close(self._fd)


@dataclass
class _Topic:
    name: str
    msgtype: str
    offered_qos_profiles: str
    definition: MessageDefinition
    type_hash: str
    written: int = 0
    written_bytes: int = 0


class _FileStats:
    """One file's messages that are in complete chunks on disk."""

    def __init__(self, relative_path: str) -> None:
        self.relative_path = relative_path
        self.message_count = 0
        self.start_ns = _MAX_TIME_NS
        self.end_ns = 0
        self.topic_counts: dict[str, int] = {}

    def add(self, topic: str, log_time_ns: int) -> None:
        self.message_count += 1
        self.topic_counts[topic] = self.topic_counts.get(topic, 0) + 1
        self.start_ns = min(self.start_ns, log_time_ns)
        self.end_ns = max(self.end_ns, log_time_ns)

    def summary(self) -> FileSummary:
        if self.message_count == 0:
            return FileSummary(self.relative_path, 0, 0, 0)
        return FileSummary(
            self.relative_path, self.start_ns, self.end_ns - self.start_ns, self.message_count
        )


class BagWriter:
    """Write a rosbag2-compatible MCAP bag.

    Args:
        path: ``*.mcap`` for a single file, otherwise a bag directory to create.
            Existing files are never overwritten (BagError).
        compression: Chunk compression, ``zstd`` | ``lz4`` | ``none``.
        chunk_size: Uncompressed bytes after which a chunk is closed and
            written (a chunk holds at least one message).
        split_size_bytes: Directory bags only: start a new ``_<n>.mcap`` file
            once the current one exceeds this size. None: never split.
        crcs: Store each chunk's CRC-32 of its uncompressed records (and
            the summary's). False: both are written as 0, which the MCAP
            specification defines as "not computed"; it saves zlib's CRC
            over every byte written (~0.2 ms per MB here). rosbag2's MCAP
            storage plugin drops the chunk CRC by default too
            (``noChunkCRC``), but keeps the summary's.

    Use as a context manager; leaving the block (also by an exception)
    finalises the file. Not thread-safe: call it from one thread (a node's
    single-threaded executor), or serialise calls with a lock.

    Raises:
        BagError: from any method when the bag cannot be created or written;
            after a failed write the message names the file, the cause, how
            many messages the bag holds and how many were lost, and every
            later call raises it again.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        compression: str = "zstd",
        chunk_size: int = 1 << 20,
        *,
        split_size_bytes: int | None = None,
        crcs: bool = True,
    ) -> None:
        if compression not in _COMPRESSION:
            raise BagError(f"unknown compression {compression!r}; use zstd, lz4 or none")
        if chunk_size <= 0:
            raise BagError(f"chunk_size must be positive, got {chunk_size}")
        self.path = Path(path)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.crcs = bool(crcs)
        self._is_directory = self.path.suffix != ".mcap"
        if split_size_bytes is not None and not self._is_directory:
            raise BagError(f"{self.path}: split_size_bytes needs a bag directory, not a .mcap path")
        self._split_size = split_size_bytes
        if self._is_directory:
            if self.path.exists():
                raise BagError(f"{self.path}: already exists, will not overwrite a bag")
            try:
                self.path.mkdir(parents=True)
            except OSError as exc:
                raise BagError(
                    f"{self.path}: cannot create bag directory ({exc.strerror})"
                ) from exc
        elif not self.path.parent.is_dir():
            raise BagError(f"{self.path}: parent directory does not exist")
        self._topics: dict[str, _Topic] = {}
        self._channel_ids: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._files: list[_FileStats] = []
        self._sink: _OsFileSink | None = None
        self._mcap: McapWriter | None = None
        self._closed = False
        # Messages of the chunk being filled: (topic, payload bytes, log time).
        self._pending: list[tuple[str, int, int]] = []
        self._chunks_seen = 0
        self._failure = ""
        self._lost = 0
        self._metadata_due = False
        self._metadata_written = time.monotonic()
        self._open_next_file()

    # -- what is on disk -----------------------------------------------------

    @property
    def written(self) -> dict[str, tuple[int, int]]:
        """Topic -> (messages, payload bytes) in complete chunks on disk, over all files."""
        return {name: (t.written, t.written_bytes) for name, t in self._topics.items()}

    @property
    def lost(self) -> int:
        """Messages :meth:`write` accepted that a failed write kept off the disk."""
        return self._lost

    @property
    def failure(self) -> str:
        """The one-line error that stopped the writer, "" while it works."""
        return self._failure

    def _settle(self) -> None:
        """Count the pending messages as written once their chunk is on disk."""
        assert self._sink is not None
        if self._sink.chunks_written == self._chunks_seen:
            return
        # The MCAP writer puts every message added since its last chunk into
        # the next one, so a new chunk holds exactly the pending messages.
        self._chunks_seen = self._sink.chunks_written
        stats = self._files[-1]
        for topic, size, log_time_ns in self._pending:
            entry = self._topics[topic]
            entry.written += 1
            entry.written_bytes += size
            stats.add(topic, log_time_ns)
        self._pending.clear()
        self._metadata_due = True

    def _fail(self, exc: OSError, doing: str) -> BagError:
        """Stop the writer after a failed write; returns the error to raise."""
        if self._sink is not None:
            self._settle()
        self._lost += len(self._pending)
        self._pending.clear()
        held = sum(t.written for t in self._topics.values())
        where = self._sink.path if self._sink is not None else self.path
        self._failure = (
            f"{where}: cannot {doing} ({exc.strerror or exc}); the bag holds the {held} "
            f"messages written before, {self._lost} not yet on disk are lost"
        )
        return BagError(self._failure)

    # -- file handling -------------------------------------------------------

    @property
    def file_paths(self) -> list[Path]:
        """The MCAP files written so far, in order."""
        base = self.path if self._is_directory else self.path.parent
        return [base / f.relative_path for f in self._files]

    def _open_next_file(self) -> None:
        if self._is_directory:
            relative = f"{self.path.name}_{len(self._files)}.mcap"
            file_path = self.path / relative
        else:
            relative = self.path.name
            file_path = self.path
        self._sink = _OsFileSink(file_path)
        self._chunks_seen = 0
        self._files.append(_FileStats(relative))
        self._mcap = McapWriter(
            cast(IO[Any], self._sink),  # write/tell/flush is all it uses
            chunk_size=self.chunk_size,
            compression=_COMPRESSION[self.compression],
            enable_crcs=self.crcs,
        )
        try:
            self._mcap.start(profile="ros2", library=_LIBRARY)
        except OSError as exc:
            raise self._fail(exc, "write") from exc
        self._schema_ids.clear()
        self._channel_ids.clear()
        for topic in self._topics.values():
            self._register(topic)
        self._write_metadata_yaml()

    def _close_current_file(self) -> None:
        assert self._mcap is not None and self._sink is not None
        try:
            # The last chunk first, so that the rosbag2 record counts what is on disk.
            self._mcap.flush()
            self._settle()
            record = dump_bag_metadata(self._metadata(all_files=False))
            self._mcap.add_metadata(ROSBAG2_METADATA_RECORD, {SERIALIZED_METADATA_KEY: record})
            self._mcap.finish()
        except OSError as exc:
            raise self._fail(exc, "finish") from exc
        finally:
            self._sink.close()
            self._mcap = None

    def _metadata(self, *, all_files: bool) -> dict[str, Any]:
        files = self._files if all_files else self._files[-1:]
        if all_files:
            counts = {name: t.written for name, t in self._topics.items()}
        else:
            counts = dict(self._files[-1].topic_counts)
        topics = [
            TopicSummary(
                name=t.name,
                msgtype=t.msgtype,
                serialization_format="cdr",
                offered_qos_profiles=t.offered_qos_profiles,
                type_description_hash=t.type_hash,
                message_count=counts.get(t.name, 0),
            )
            for t in self._topics.values()
        ]
        return bag_metadata(topics, [f.summary() for f in files])

    def _write_metadata_yaml(self) -> None:
        """Rewrite a bag directory's metadata.yaml with what is on disk now."""
        if not self._is_directory:
            return
        try:
            write_metadata_yaml(self.path, self._metadata(all_files=True))
        except OSError as exc:
            raise self._fail(exc, f"update {self.path}/metadata.yaml") from exc
        self._metadata_due = False
        self._metadata_written = time.monotonic()

    # -- topics --------------------------------------------------------------

    def add_topic(
        self,
        name: str,
        msgtype: str,
        offered_qos_profiles: str = "",
        *,
        message_definition_override: MessageDefinition | None = None,
        type_description_hash_override: str | None = None,
    ) -> None:
        """Declare a topic before writing to it.

        Args:
            name: Topic name.
            msgtype: ROS 2 type, e.g. ``sensor_msgs/msg/Image``. Types that are
                not installed are recorded with an ``unknown`` (empty) schema,
                as rosbag2 does, unless ``message_definition_override`` is given.
            offered_qos_profiles: rosbag2 QoS YAML of the publishers
                (:func:`endo_io.bag.qos_yaml.qos_profiles_to_yaml`), "" if unknown.
            message_definition_override: Schema to store instead of the one
                built from the installed interface files (e.g. copied from
                another bag).
            type_description_hash_override: ``RIHS01_...`` hash to store
                instead of the installed type's (e.g. copied from another bag).

        Re-adding a topic with the same type does nothing; with another type
        it raises BagError.
        """
        self._check_open()
        existing = self._topics.get(name)
        if existing is not None:
            if existing.msgtype != msgtype:
                raise BagError(f"topic {name} already added as {existing.msgtype}, not {msgtype}")
            return
        definition = message_definition_override or message_definition(msgtype)
        type_hash = (
            type_description_hash_override
            if type_description_hash_override is not None
            else type_description_hash(msgtype)
        )
        topic = _Topic(name, msgtype, offered_qos_profiles, definition, type_hash)
        self._topics[name] = topic
        self._sequence[name] = 0
        self._register(topic)
        self._write_metadata_yaml()

    def _register(self, topic: _Topic) -> None:
        assert self._mcap is not None
        schema_id = self._schema_ids.get(topic.msgtype)
        if schema_id is None:
            schema_id = self._mcap.register_schema(
                name=topic.msgtype,
                encoding=topic.definition.encoding,
                data=topic.definition.text.encode(),
            )
            self._schema_ids[topic.msgtype] = schema_id
        self._channel_ids[topic.name] = self._mcap.register_channel(
            topic=topic.name,
            message_encoding="cdr",
            schema_id=schema_id,
            metadata={
                "offered_qos_profiles": topic.offered_qos_profiles,
                "topic_type_hash": topic.type_hash,
            },
        )

    # -- messages ------------------------------------------------------------

    def write(
        self,
        topic: str,
        data: bytes | bytearray | memoryview,
        log_time_ns: int,
        publish_time_ns: int | None = None,
    ) -> None:
        """Append one serialised (CDR) message.

        Args:
            topic: A topic declared with :meth:`add_topic`.
            data: The CDR bytes, stored unchanged.
            log_time_ns: Receive time, integer ns >= 0.
            publish_time_ns: Publish time, integer ns >= 0 (default: log time).

        The message is on disk (and counted in :attr:`written`) once its
        chunk is written: when the chunk is full, at :meth:`flush`, or at
        :meth:`close`.
        """
        self._check_open()
        channel_id = self._channel_ids.get(topic)
        if channel_id is None:
            raise BagError(f"topic {topic} was not added; call add_topic first")
        if publish_time_ns is None:
            publish_time_ns = log_time_ns
        if not (0 <= log_time_ns <= _MAX_TIME_NS and 0 <= publish_time_ns <= _MAX_TIME_NS):
            raise BagError(
                f"{topic}: timestamps must be unsigned 64-bit ns, got log {log_time_ns}, "
                f"publish {publish_time_ns}"
            )
        assert self._mcap is not None and self._sink is not None
        sequence = self._sequence[topic] = (self._sequence[topic] + 1) & 0xFFFFFFFF
        self._pending.append((topic, len(data), int(log_time_ns)))
        try:
            self._mcap.add_message(
                channel_id=channel_id,
                log_time=int(log_time_ns),
                data=cast(bytes, data),  # any buffer works; avoid copying images
                publish_time=int(publish_time_ns),
                sequence=sequence,
            )
        except OSError as exc:
            raise self._fail(exc, "write") from exc
        self._settle()
        if self._split_size is not None and self._sink.tell() >= self._split_size:
            self._close_current_file()
            self._open_next_file()
        elif self._metadata_due and time.monotonic() - self._metadata_written >= METADATA_PERIOD_S:
            self._write_metadata_yaml()

    def write_message(
        self, topic: str, message: Any, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Serialise a ROS 2 message with rclpy and append it; adds the topic on first use."""
        if topic not in self._topics:
            self.add_topic(topic, msgtype_of(message))
        elif self._topics[topic].msgtype != msgtype_of(message):
            raise BagError(
                f"topic {topic} is {self._topics[topic].msgtype}, got a {msgtype_of(message)}"
            )
        self.write(topic, serialize(message), log_time_ns, publish_time_ns)

    def flush(self) -> None:
        """Close the chunk being filled and write it now (it then survives a crash).

        A bag directory's metadata.yaml is rewritten too when that wrote a chunk.
        """
        self._check_open()
        assert self._mcap is not None
        try:
            self._mcap.flush()
        except OSError as exc:
            raise self._fail(exc, "write") from exc
        self._settle()
        if self._metadata_due:
            self._write_metadata_yaml()

    # -- lifetime ------------------------------------------------------------

    def _check_open(self) -> None:
        if self._failure:
            raise BagError(self._failure)
        if self._closed:
            raise BagError(f"{self.path}: writer is closed")

    def close(self) -> None:
        """Write the last chunk, the rosbag2 metadata record, summary and footer; idempotent.

        After a failed write, only the file is closed (it reads to its last
        complete chunk; ``endo-bag recover`` makes a complete copy) and a bag
        directory's metadata.yaml is rewritten with what is on disk.

        Raises:
            BagError: finishing the file or its metadata.yaml failed.
        """
        if self._closed:
            return
        self._closed = True
        failed_before = bool(self._failure)
        try:
            if failed_before:
                if self._sink is not None:
                    self._sink.close()
                    self._sink = None
                    self._mcap = None
            else:
                self._close_current_file()
        finally:
            if self._is_directory:
                try:
                    write_metadata_yaml(self.path, self._metadata(all_files=True))
                except OSError as exc:
                    if not self._failure:
                        raise self._fail(exc, f"update {self.path}/metadata.yaml") from exc

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: types.TracebackType | None,
    ) -> None:
        self.close()


__all__ = ["COMPRESSIONS", "METADATA_PERIOD_S", "BagWriter"]
