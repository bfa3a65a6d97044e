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

The summary (schemas, channels, statistics, chunk and metadata indexes) is
built from what the file sink saw reach the disk whole, never from the MCAP
library's bookkeeping, and file positions come from the file itself
(``os.lseek``). Any exception other than OSError inside a write (a
MemoryError, a KeyboardInterrupt of a tool that embeds the writer) stops the
writer: the file is cut back to its last whole chunk and message indexes
(the MCAP library's state is unknown then), the exception propagates, and
:meth:`BagWriter.close` still writes the summary and footer, so that every
reader opens the file with every message written before the failure.

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
import errno
import mmap
import os
import struct
import time
import types
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, cast

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC, CompressionType
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
#: What an output bag path (a tool's ``-o``) makes, for every tool's ``--help``.
OUTPUT_PATH_HELP = (
    "NAME.mcap: one MCAP file; any other NAME: a rosbag2 bag directory NAME/ holding "
    "NAME_0.mcap and metadata.yaml, as 'ros2 bag record -o NAME' makes"
)
#: The cause named in a failed write's message, by errno (the OS's text follows it).
_WRITE_FAILURES = {
    errno.ENOSPC: "disk full",
    errno.EFBIG: "file size limit",
    errno.EDQUOT: "disk quota exceeded",
}
_MAX_TIME_NS = 2**64 - 1


class _OsFileSink:
    """Write-only file that hands every write to the OS at once, and indexes what is whole.

    Page-cache writes survive the death of the process, so a SIGKILLed
    recorder loses nothing that the MCAP writer had already written. A write
    that fails part way (a full disk) is cut back off the file, which then
    ends at the last whole record (the MCAP writer hands over one record, or
    one chunk's message indexes, per call); ``chunks_written`` counts the
    chunk records written whole.

    Every chunk record written whole becomes a chunk index once its message
    indexes are written whole too; metadata records become metadata indexes.
    ``_committed`` (one tuple, assigned at once) is the end of the last whole
    group (header, chunk and its message indexes, metadata record) and how
    many indexes of each kind it holds: :meth:`cut_to_committed` cuts the
    file back to it after an exception anywhere, whatever the MCAP library's
    state. Positions come from the file (``os.lseek``), never from a count
    that an exception between a write and its update could leave stale.
    """

    def __init__(self, path: Path, *, direct: bool = False) -> None:
        try:
            # Read-write: after a cut, O_DIRECT writes read the file's last partial
            # block back (_DirectWrites.reload_tail).
            self._fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError as exc:
            raise BagError(f"{path}: already exists, will not overwrite a bag") from exc
        except OSError as exc:
            raise BagError(f"{path}: cannot create ({exc.strerror})") from exc
        self.path = path
        self._direct: _DirectWrites | None = None
        if direct:
            self._direct = _DirectWrites.open(path, self._fd)
        self.chunks_written = 0
        self.chunk_indexes: list[ChunkIndex] = []
        self.metadata_indexes: list[MetadataIndex] = []
        self._open_chunk: ChunkIndex | None = None
        self._committed = (0, 0, 0)

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        if not view.nbytes:
            return 0
        start = self.tell()
        try:
            if self._direct is not None:
                self._direct.write(view, start)
                if not self._direct.active:  # the file system refused O_DIRECT
                    self._direct.close()
                    self._direct = None
            else:
                while view.nbytes:
                    written = os.write(self._fd, view)
                    view = view[written:]
        except OSError:
            with contextlib.suppress(OSError):  # if this fails too, readers stop at the cut
                self._cut(start)
            raise
        self._index(memoryview(data), start)
        return len(data)

    def _index(self, data: memoryview, start: int) -> None:
        """Account for one whole write at ``start`` (see the class docstring)."""
        opcode = data[0]
        if opcode == Opcode.CHUNK:
            self._open_chunk = _chunk_index(data, start)
            self.chunks_written += 1
            return
        chunk = self._open_chunk
        if chunk is not None:
            if opcode == Opcode.MESSAGE_INDEX:
                chunk.message_index_offsets = _message_index_offsets(data, start)
                chunk.message_index_length = len(data)
            self.chunk_indexes.append(chunk)
            self._open_chunk = None
        if opcode == Opcode.METADATA:
            (name_length,) = struct.unpack_from("<I", data, 9)
            name = bytes(data[13 : 13 + name_length]).decode()
            self.metadata_indexes.append(MetadataIndex(start, len(data), name))
        self._committed = (start + len(data), len(self.chunk_indexes), len(self.metadata_indexes))

    def tell(self) -> int:
        return os.lseek(self._fd, 0, os.SEEK_CUR)

    def _cut(self, end: int) -> None:
        os.ftruncate(self._fd, end)
        os.lseek(self._fd, end, os.SEEK_SET)
        if self._direct is not None:
            self._direct.reload_tail(end)

    @property
    def committed(self) -> tuple[int, int, int]:
        """(end of the last whole group, chunk indexes, metadata indexes) up to it."""
        return self._committed

    def cut_to_committed(self, committed: tuple[int, int, int] | None = None) -> None:
        """Cut the file back to its last whole group (or an earlier ``committed``)."""
        end, chunks, metadata = self._committed if committed is None else committed
        self._cut(end)
        del self.chunk_indexes[chunks:]
        del self.metadata_indexes[metadata:]
        self._open_chunk = None
        self.chunks_written = chunks
        self._committed = (end, chunks, metadata)

    def flush(self) -> None:
        """Nothing is buffered here."""

    def close(self) -> None:
        try:
            if self._direct is not None:
                self._direct.close()
        finally:
            os.close(self._fd)


#: Alignment of ``O_DIRECT`` writes: file offset, length and buffer address
#: (the page size; block devices ask for 512 or 4096 bytes).
DIRECT_ALIGNMENT = 4096


class _DirectWrites:
    """An :class:`_OsFileSink`'s writes through ``O_DIRECT``, past the page cache.

    A buffered write of a large recording costs the kernel more than the
    copy: each page is allocated in the page cache, written back and
    reclaimed again, and once dirty pages pile up the writer is throttled.
    Here (ext4 on a virtio disk, in a memory cgroup) ``dd`` wrote 2 GB at
    90 MB/s with 3-5 s of system CPU buffered, at 700 MB/s with 0.3 s
    ``O_DIRECT`` (docs/benchmarks.md, "endo-process, session 14").

    ``O_DIRECT`` needs the file offset, the length and the buffer aligned
    (:data:`DIRECT_ALIGNMENT`). Each write is copied after the file's last
    partial block (held in :attr:`_stage`, a page-aligned anonymous map),
    the whole blocks go out through the ``O_DIRECT`` descriptor, and the
    new partial block at the end is written through the sink's ordinary
    descriptor as well, so every byte is with the operating system when
    :meth:`write` returns, as a buffered sink's (a SIGKILLed writer loses
    nothing it had written); the next write writes that block again, whole.
    A file system that refuses ``O_DIRECT`` (tmpfs at open, others at the
    first write: EINVAL), or a short write (a file size limit), hands the
    rest to the ordinary descriptor, which then reports the failure as a
    buffered sink does.
    """

    def __init__(self, fd: int, direct_fd: int) -> None:
        self._fd = fd
        self._direct_fd: int | None = direct_fd
        self._stage = mmap.mmap(-1, 4 << 20)
        self._tail = 0  # bytes of the file's last partial block, at _stage[:_tail]

    @classmethod
    def open(cls, path: Path, fd: int) -> _DirectWrites | None:
        """A second, ``O_DIRECT`` descriptor of the created file; None where it cannot be."""
        flag = getattr(os, "O_DIRECT", 0)
        if not flag:
            return None
        try:
            direct_fd = os.open(path, os.O_WRONLY | flag)
        except OSError:
            return None
        return cls(fd, direct_fd)

    def write(self, view: memoryview, start: int) -> None:
        """Write ``view`` at ``start`` (the file's end); leaves the ordinary descriptor after it."""
        tail, size = self._tail, view.nbytes
        total = tail + size
        if total > len(self._stage):
            grown = mmap.mmap(-1, max(total, 2 * len(self._stage)) + DIRECT_ALIGNMENT)
            grown[:tail] = self._stage[:tail]
            self._stage.close()
            self._stage = grown
        stage = self._stage
        stage[tail:total] = view
        base = start - tail
        whole = total - total % DIRECT_ALIGNMENT
        done = 0
        with memoryview(stage) as staged:  # released before the stage may be closed
            if self._direct_fd is not None and whole:
                done = self._direct_write(staged[:whole], base)
            if done < total:
                # The partial block at the end (or all that O_DIRECT did not take).
                os.lseek(self._fd, base + done, os.SEEK_SET)
                while done < total:
                    done += os.write(self._fd, staged[done:total])
            else:
                os.lseek(self._fd, start + size, os.SEEK_SET)
        keep = total % DIRECT_ALIGNMENT
        stage.move(0, total - keep, keep)
        self._tail = keep

    @property
    def active(self) -> bool:
        """False once the file system refused an ``O_DIRECT`` write."""
        return self._direct_fd is not None

    def _direct_write(self, blocks: memoryview, offset: int) -> int:
        """Whole blocks through ``O_DIRECT``; the bytes written (short on a limit or refusal)."""
        assert self._direct_fd is not None
        done = 0
        try:
            while done < blocks.nbytes:
                written = os.pwrite(self._direct_fd, blocks[done:], offset + done)
                if written <= 0 or written % DIRECT_ALIGNMENT:
                    return done + max(written, 0)
                done += written
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                return done  # the ordinary descriptor meets the failure again and reports it
            os.close(self._direct_fd)  # this file system takes no O_DIRECT writes
            self._direct_fd = None
        return done

    def reload_tail(self, end: int) -> None:
        """After the file was cut at ``end``: hold its last partial block again."""
        keep = end % DIRECT_ALIGNMENT
        data = os.pread(self._fd, keep, end - keep) if keep else b""
        self._stage[: len(data)] = data
        self._tail = len(data)

    def close(self) -> None:
        """Close the ``O_DIRECT`` descriptor and free the stage."""
        if self._direct_fd is not None:
            os.close(self._direct_fd)
            self._direct_fd = None
        with contextlib.suppress(BufferError):  # a traceback may still hold a view of it
            self._stage.close()


def _chunk_index(record: memoryview, offset: int) -> ChunkIndex:
    """The chunk index of one whole Chunk record written at ``offset`` (no message indexes yet)."""
    start_ns, end_ns, uncompressed_size, _crc, compression_length = struct.unpack_from(
        "<QQQII", record, 9)
    compression = bytes(record[41 : 41 + compression_length]).decode()
    (compressed_size,) = struct.unpack_from("<Q", record, 41 + compression_length)
    return ChunkIndex(
        message_start_time=start_ns,
        message_end_time=end_ns,
        chunk_start_offset=offset,
        chunk_length=len(record),
        message_index_offsets={},
        message_index_length=0,
        compression=compression,
        compressed_size=compressed_size,
        uncompressed_size=uncompressed_size,
    )


def _message_index_offsets(data: memoryview, offset: int) -> dict[int, int]:
    """Channel id -> file offset of each MessageIndex record in one write at ``offset``."""
    offsets = {}
    position = 0
    while position + 11 <= len(data):
        opcode, length, channel_id = struct.unpack_from("<BQH", data, position)
        if opcode == Opcode.MESSAGE_INDEX:
            offsets[channel_id] = offset + position
        position += 9 + length
    return offsets


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
        direct: Write the file with ``O_DIRECT``, past the page cache
            (:class:`_DirectWrites`; where the file system refuses it, as
            usual): for a writer of gigabytes, whose pages the kernel would
            otherwise fill, write back and reclaim at several ms of system
            CPU per frame of 640x480 float images (``endo-process``). The
            file and what survives a crash are the same.

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
        direct: bool = False,
    ) -> None:
        if compression not in _COMPRESSION:
            raise BagError(f"unknown compression {compression!r}; use zstd, lz4 or none")
        if chunk_size <= 0:
            raise BagError(f"chunk_size must be positive, got {chunk_size}")
        self.path = Path(path)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.crcs = bool(crcs)
        self.direct = bool(direct)
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
        self._summary_possible = True  # False after an OSError: the disk refused
        self._lost = 0
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._metadata_due = False
        self._metadata_written = time.monotonic()
        try:
            self._open_next_file()
        except BaseException:
            if self._is_directory:
                with contextlib.suppress(OSError):
                    self.path.rmdir()  # created here, and empty
            raise

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
        self._summary_possible = False
        if self._sink is not None:
            self._settle()
        cause = _WRITE_FAILURES.get(exc.errno or 0)
        self._stop(f"cannot {doing} ({cause + ': ' if cause else ''}{exc.strerror or exc})")
        return BagError(self._failure)

    def _interrupted(self, exc: BaseException) -> None:
        """Stop the writer after an exception other than OSError inside a write.

        The MCAP library's state is unknown then (the exception may have
        landed between any two of its statements): the file is cut back to
        its last whole group, the messages beyond it are lost, and
        :meth:`close` writes the summary from what the file holds.
        """
        if self._failure:
            return
        if self._sink is not None:
            try:
                self._sink.cut_to_committed()
            except OSError:
                self._summary_possible = False
            self._settle()
        self._mcap = None
        self._stop(f"writing stopped by {type(exc).__name__}" + (f" ({exc})" if str(exc) else ""))

    def _library_call(self, call: Callable[..., object], *args: Any, **kwargs: Any) -> None:
        """One call into the MCAP library that may write; then count what reached the disk.

        An OSError stops the writer with a BagError (:meth:`_fail`), any other
        exception stops it and propagates (:meth:`_interrupted`).
        """
        try:
            call(*args, **kwargs)
        except OSError as exc:
            raise self._fail(exc, "write") from exc
        except BaseException as exc:
            self._interrupted(exc)
            raise
        self._settle()

    def _stop(self, cause: str) -> None:
        self._lost += len(self._pending)
        self._pending.clear()
        held = sum(t.written for t in self._topics.values())
        where = self._sink.path if self._sink is not None else self.path
        self._failure = (
            f"{where}: {cause}; the bag holds the {held} "
            f"messages written before, {self._lost} not yet on disk are lost"
        )

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
        self._sink = _OsFileSink(file_path, direct=self.direct)
        self._chunks_seen = 0
        self._files.append(_FileStats(relative))
        self._schema_ids.clear()
        self._channel_ids.clear()
        self._schemas.clear()
        self._channels.clear()
        try:
            self._mcap = McapWriter(
                cast(IO[Any], self._sink),  # write/tell/flush is all it uses
                chunk_size=self.chunk_size,
                compression=_COMPRESSION[self.compression],
                enable_crcs=self.crcs,
            )
            self._mcap.start(profile="ros2", library=_LIBRARY)
            for topic in self._topics.values():
                self._register(topic)
        except BaseException as exc:
            # Not even a header is whole: no file rather than one no reader opens.
            self._files.pop()
            sink, self._sink, self._mcap = self._sink, None, None
            sink.close()
            with contextlib.suppress(OSError):
                file_path.unlink()
            if isinstance(exc, OSError):
                raise self._fail(exc, "write") from exc
            self._stop(f"writing stopped by {type(exc).__name__}")
            raise
        self._write_metadata_yaml()

    def _close_current_file(self) -> None:
        """Write the last chunk, the rosbag2 metadata record, summary and footer; close.

        After an exception other than OSError (here or in a write before),
        the file is cut back to its last whole group and finished from there
        (once more when the exception came while finishing), and the first
        exception propagates; after an OSError only the file is closed.
        """
        sink = self._sink
        assert sink is not None
        first: BaseException | None = None
        try:
            for _attempt in range(2):
                mark = None  # the file before the metadata record and summary
                try:
                    if self._mcap is not None and not self._failure:
                        # The last chunk first, so that the rosbag2 record counts what is on disk.
                        self._mcap.flush()
                        self._settle()
                    if self._summary_possible:
                        mark = sink.committed
                        self._finish_file(sink)
                    break
                except OSError as exc:
                    with contextlib.suppress(OSError):
                        sink.cut_to_committed(mark)  # no summary rather than half of one
                    if first is None:
                        raise self._fail(exc, "finish") from exc
                    break
                except BaseException as exc:
                    first = first or exc
                    self._interrupted(exc)
                    if not self._summary_possible:
                        break
                    sink.cut_to_committed(mark)
        finally:
            self._sink = self._mcap = None
            sink.close()
        if first is not None:
            raise first

    def _finish_file(self, sink: _OsFileSink) -> None:
        """The rosbag2 metadata record, data end, summary and footer, from what the file holds."""
        builder = RecordBuilder()
        record = dump_bag_metadata(self._metadata(all_files=False))
        Metadata(ROSBAG2_METADATA_RECORD, {SERIALIZED_METADATA_KEY: record}).write(builder)
        sink.write(builder.end())
        DataEnd(0).write(builder)
        sink.write(builder.end())
        stats = self._files[-1]
        statistics = Statistics(
            attachment_count=0,
            channel_count=len(self._channels),
            channel_message_counts={
                self._channel_ids[topic]: n for topic, n in stats.topic_counts.items()},
            chunk_count=len(sink.chunk_indexes),
            message_count=stats.message_count,
            message_end_time=stats.end_ns if stats.message_count else 0,
            message_start_time=stats.start_ns if stats.message_count else 0,
            metadata_count=len(sink.metadata_indexes),
            schema_count=len(self._schemas),
        )
        summary_start = sink.tell()
        offsets = []
        for opcode, group in (
            (Opcode.SCHEMA, list(self._schemas.values())),
            (Opcode.CHANNEL, list(self._channels.values())),
            (Opcode.STATISTICS, [statistics]),
            (Opcode.CHUNK_INDEX, sink.chunk_indexes),
            (Opcode.METADATA_INDEX, sink.metadata_indexes),
        ):
            group_start = builder.count
            for item in group:
                item.write(builder)
            if builder.count > group_start:
                offsets.append(SummaryOffset(
                    opcode, summary_start + group_start, builder.count - group_start))
        summary_offset_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        summary = builder.end()
        crc = 0
        if self.crcs:
            footer_head = struct.pack(
                "<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start)
            crc = zlib.crc32(footer_head, zlib.crc32(summary))
        Footer(summary_start, summary_offset_start, crc).write(builder)
        sink.write(summary + builder.end() + MCAP0_MAGIC)

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
        self._library_call(self._register, topic)  # may write the chunk being filled
        self._write_metadata_yaml()

    def _register(self, topic: _Topic) -> None:
        assert self._mcap is not None
        schema_id = self._schema_ids.get(topic.msgtype)
        if schema_id is None:
            data = topic.definition.text.encode()
            schema_id = self._mcap.register_schema(
                name=topic.msgtype, encoding=topic.definition.encoding, data=data)
            self._schemas[schema_id] = Schema(
                id=schema_id, data=data, encoding=topic.definition.encoding, name=topic.msgtype)
            self._schema_ids[topic.msgtype] = schema_id
        metadata = {
            "offered_qos_profiles": topic.offered_qos_profiles,
            "topic_type_hash": topic.type_hash,
        }
        channel_id = self._mcap.register_channel(
            topic=topic.name, message_encoding="cdr", schema_id=schema_id, metadata=metadata)
        self._channels[channel_id] = Channel(
            id=channel_id, topic=topic.name, message_encoding="cdr", metadata=metadata,
            schema_id=schema_id)
        self._channel_ids[topic.name] = channel_id

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
        self._library_call(
            self._mcap.add_message,
            channel_id=channel_id,
            log_time=int(log_time_ns),
            data=cast(bytes, data),  # any buffer works; avoid copying images
            publish_time=int(publish_time_ns),
            sequence=sequence,
        )
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
        self._library_call(self._mcap.flush)
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

        After a failed write (an OSError: the disk refused), only the file is
        closed (it reads to its last complete chunk; ``endo-bag recover``
        makes a complete copy); after an exception of another kind the file
        is finished from its last whole chunk. A bag directory's
        metadata.yaml is rewritten with what is on disk.

        Raises:
            BagError: finishing the file or its metadata.yaml failed.
        """
        if self._closed:
            return
        self._closed = True
        try:
            if self._sink is not None:
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


__all__ = ["COMPRESSIONS", "METADATA_PERIOD_S", "OUTPUT_PATH_HELP", "BagWriter"]
