"""One MCAP file: its channels, and its messages in log-time order, tolerant of damage.

Records are read by :mod:`endo_io.bag.mcap_records` (the ``mcap`` package's
record classes over a :class:`~endo_io.bag.mcap_records.BoundedFile`, chunks
decompressed in bounded steps), so that no length field is trusted before it
is checked against the bytes there are; the summary section is parsed by the
``mcap`` package's ``SeekingReader`` over the same bounded file. This module
decides *which* records to read, in what order, and what to do when one is
damaged.

Two ways to find the messages:

* **Index** (a complete file): the summary's chunk indexes give every chunk's
  offset and time range, and its statistics the per-topic counts.
* **Scan** (no summary, an unchunked file, or a file cut short by a crash):
  one linear pass over the top-level records lists the chunks and top-level
  message records and their time ranges without decompressing
  (message counts come from the message-index records that follow each
  chunk; a chunk without them, or one that declares new channels, is
  decompressed once). The pass stops at the first unreadable record; that
  byte offset is the damage.

Either way the result is a list of *segments* (a chunk, or one top-level
message) with time ranges, merged by a heap keyed on ``(log_time, file
offset, index in chunk)``: a segment is opened when its start time comes up,
so overlapping chunks still come out in exact log-time order, while at most
the overlapping chunks are held in memory. A chunk that fails to read
(corrupt bytes, CRC mismatch) is skipped and remembered; after the last
intact message the iterator raises :class:`BagCorruptError` naming the file
and the byte offset of the first damage.

Each damaged region is also kept as a :class:`~endo_io.bag.interfaces.DamagedRegion`
(:attr:`McapFile.damaged_regions`) saying which messages it cost by log time:
a chunk's time range from its index or its header, with the per-topic
counts of its message indexes when they are readable; for a cut, everything
after the last message read. A chunk is read only when its start time comes
up, so a region found while reading is known only once the reading has got
there.
"""

from __future__ import annotations

import dataclasses
import heapq
import os
import shlex
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.opcode import Opcode
from mcap.reader import FOOTER_SIZE, SeekingReader
from mcap.records import (
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import MAGIC_SIZE

from endo_io.bag.errors import BagCorruptError, BagError, BagNotFoundError
from endo_io.bag.interfaces import (
    BagMessage,
    ChunkStats,
    DamagedRegion,
    LostMessages,
    TopicInfo,
)
from endo_io.bag.mcap_records import (
    DEFAULT_MAX_CHUNK_BYTES,
    RECORD_PREFIX,
    BoundedFile,
    RecordDamage,
    chunk_records,
    read_cut_chunk,
    read_record,
)
from endo_io.bag.metadata import (
    ROSBAG2_METADATA_RECORD,
    SERIALIZED_METADATA_KEY,
    parse_bag_metadata,
)
from endo_io.bag.msgdef import MessageDefinition

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: The first bytes of an SQLite 3 database (rosbag2's sqlite3 storage, .db3 files).
SQLITE_MAGIC = b"SQLite format 3\x00"
_RECORD_PREFIX = RECORD_PREFIX
_FOOTER_CRC_SIZE = 4
_KIND_CHUNK = 0
_KIND_MESSAGE = 1
_KIND_RECOVERED = 2  # the readable head of a chunk cut short by the end of the file


@dataclass(frozen=True, slots=True)
class _Segment:
    """A readable unit: one chunk record, or one top-level message record."""

    start_ns: int
    end_ns: int
    offset: int
    length: int  # record body length (for top-level messages)
    kind: int
    channel_ids: frozenset[int] | None  # None: unknown, must be opened to filter


@dataclass(frozen=True, slots=True)
class _ChannelInfo:
    topic: str
    msgtype: str
    message_encoding: str
    offered_qos_profiles: str
    type_description_hash: str


def _describe(exc: BaseException) -> str:
    if isinstance(exc, RecordDamage):
        return str(exc)
    text = str(exc).strip().splitlines()
    detail = text[0][:120] if text else ""
    name = type(exc).__name__
    if name == "EndOfFile" and not detail:
        return "file ends inside a record"
    return f"{name}: {detail}" if detail else name


class McapFile:
    """Read one MCAP file (rosbag2 ``ros2`` profile or any CDR MCAP).

    Args:
        path: The ``.mcap`` file.
        validate_crcs: Check each chunk's CRC (when the writer stored one), so
            that a corrupt chunk is reported instead of yielding wrong bytes.
        max_chunk_bytes: A chunk declaring more uncompressed bytes is treated
            as damaged instead of being decompressed (it bounds the memory a
            hostile file can make the reader use).

    Raises:
        BagNotFoundError: the file does not exist.
        BagError: it cannot be opened or is not an MCAP file.
    """

    def __init__(
        self,
        path: Path,
        *,
        validate_crcs: bool = True,
        max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES,
    ) -> None:
        self.path = path
        self.validate_crcs = validate_crcs
        self.max_chunk_bytes = max_chunk_bytes
        try:
            self._raw: IO[bytes] = path.open("rb")
        except FileNotFoundError as exc:
            raise BagNotFoundError(f"{path}: no such bag file") from exc
        except IsADirectoryError as exc:
            raise BagError(f"{path}: is a directory, not an MCAP file") from exc
        except OSError as exc:
            raise BagError(f"{path}: cannot open ({exc.strerror})") from exc
        try:
            self.size = os.fstat(self._raw.fileno()).st_size
            self._file = BoundedFile(self._raw, self.size)
            self.profile = ""
            self.library = ""
            self.rosbag2_metadata: dict[str, Any] | None = None
            self.used_index = False
            self._schemas: dict[int, Schema] = {}
            self._channels: dict[int, _ChannelInfo] = {}
            self._channel_records: dict[int, Channel] = {}
            self._counts: dict[int, int] = {}
            self._segments: list[_Segment] = []
            self._regions: dict[int, DamagedRegion] = {}
            # chunk offset -> its messages per channel id, from the scan's message indexes
            self._chunk_counts: dict[int, dict[int, int]] = {}
            # chunk offset -> channel id -> offset of its message index (the summary's)
            self._index_offsets: dict[int, dict[int, int]] = {}
            self._recovered: dict[int, list[Any]] = {}
            self._chunk_compression: dict[str, int] = {}
            self._chunk_bytes = [0, 0]  # compressed, uncompressed
            head = self._raw.read(MAGIC_SIZE)
            self._file.seek(len(head))
            if head != MCAP_MAGIC:
                if MCAP_MAGIC.startswith(head):  # empty, or cut inside the magic
                    self._note(len(head), "file ends inside the MCAP magic", "rest")
                    return
                bag = Path(path).parent  # rosbag2's sqlite3 storage: convert its directory
                if head == SQLITE_MAGIC[:len(head)] and (bag / "metadata.yaml").exists():
                    raise BagError(
                        f"{path}: a sqlite3 (.db3) rosbag2 file, only mcap is supported (convert "
                        f"its bag: rosbags-convert --src {shlex.quote(str(bag))} --dst "
                        f"{shlex.quote(str(bag.with_name(bag.name + '_mcap')))} "
                        "--dst-storage mcap)")
                raise BagError(f"{path}: not an MCAP file (bad magic {head[:8]!r})")
            if not self._load_index():
                self._scan()
        except BaseException:
            self._raw.close()
            raise

    # -- opening ---------------------------------------------------------------

    def _load_index(self) -> bool:
        """Use the summary section if it is complete and consistent; False to scan instead."""
        stream = self._file
        try:
            if self.size < 2 * MAGIC_SIZE + FOOTER_SIZE:
                return False
            stream.seek(self.size - MAGIC_SIZE)
            if stream.read(MAGIC_SIZE) != MCAP_MAGIC:
                return False
            footer, _ = read_record(stream, self.size - MAGIC_SIZE - FOOTER_SIZE)
            if not isinstance(footer, Footer) or footer.summary_start == 0:
                return False
            summary_end = self.size - MAGIC_SIZE - _FOOTER_CRC_SIZE
            if not MAGIC_SIZE < footer.summary_start < summary_end:
                return False
            if footer.summary_crc != 0:
                stream.seek(footer.summary_start)
                summary_bytes = stream.read(summary_end - footer.summary_start)
                if zlib.crc32(summary_bytes) != footer.summary_crc:
                    return False
            stream.seek(0)
            reader = SeekingReader(stream, record_size_limit=self.size)  # type: ignore[arg-type]
            summary = reader.get_summary()
            header = reader.get_header()
        except Exception:
            return False
        if summary is None or summary.statistics is None:
            return False
        stats = summary.statistics
        if stats.chunk_count != len(summary.chunk_indexes):
            return False
        if stats.message_count > 0 and stats.chunk_count == 0:
            return False  # unchunked: messages are not indexed, scan them
        if len(summary.channels) < stats.channel_count:
            return False
        for index in summary.chunk_indexes:
            end = index.chunk_start_offset + index.chunk_length
            if index.chunk_start_offset < MAGIC_SIZE or end > footer.summary_start:
                return False
        for channel in summary.channels.values():
            if channel.schema_id != 0 and channel.schema_id not in summary.schemas:
                return False
        self.profile, self.library = header.profile, header.library
        self._schemas.update(summary.schemas)
        for channel in summary.channels.values():
            self._add_channel(channel)
        self._counts.update(stats.channel_message_counts)
        for index in summary.chunk_indexes:
            self._count_chunk(index.compression, index.compressed_size, index.uncompressed_size)
            self._index_offsets[index.chunk_start_offset] = dict(index.message_index_offsets)
        self._segments = [
            _Segment(
                index.message_start_time,
                index.message_end_time,
                index.chunk_start_offset,
                index.chunk_length,
                _KIND_CHUNK,
                frozenset(index.message_index_offsets) if index.message_index_offsets else None,
            )
            for index in summary.chunk_indexes
        ]
        for metadata_index in summary.metadata_indexes:
            if metadata_index.name != ROSBAG2_METADATA_RECORD:
                continue
            try:
                record, _ = read_record(stream, metadata_index.offset)
            except Exception as exc:
                self._note(metadata_index.offset, _describe(exc), "none")
                continue
            if isinstance(record, Metadata):
                self._take_metadata(record)
        self.used_index = True
        return True

    def _scan(self) -> None:
        """One linear pass listing segments; stops at the first unreadable record."""
        stream = self._file
        position = MAGIC_SIZE
        pending: tuple[Chunk, int, int] | None = None
        pending_counts: dict[int, int] = {}
        in_summary = False
        try:
            while position < self.size:
                record, end = read_record(stream, position)
                if isinstance(record, MessageIndex):
                    if pending is not None:
                        pending_counts[record.channel_id] = len(record.records)
                    position = end
                    continue
                if pending is not None:
                    self._finish_scanned_chunk(*pending, pending_counts)
                    pending, pending_counts = None, {}
                if isinstance(record, Chunk):
                    pending = (record, position, end)
                elif isinstance(record, Schema):
                    self._schemas.setdefault(record.id, record)
                elif isinstance(record, Channel):
                    self._add_channel(record)
                elif isinstance(record, Message) and not in_summary:
                    self._segments.append(
                        _Segment(
                            record.log_time,
                            record.log_time,
                            position,
                            end - position - _RECORD_PREFIX,
                            _KIND_MESSAGE,
                            frozenset((record.channel_id,)),
                        )
                    )
                    self._counts[record.channel_id] = self._counts.get(record.channel_id, 0) + 1
                elif isinstance(record, Metadata):
                    self._take_metadata(record)
                elif isinstance(record, Header):
                    self.profile, self.library = record.profile, record.library
                elif isinstance(record, DataEnd):
                    in_summary = True
                elif isinstance(record, Footer):
                    stream.seek(end)
                    if end + MAGIC_SIZE > self.size or stream.read(MAGIC_SIZE) != MCAP_MAGIC:
                        self._note(
                            end, "the closing MCAP magic after the footer is cut or damaged", "none"
                        )
                    return
                position = end
        except Exception as exc:
            if pending is not None:
                self._finish_scanned_chunk(*pending, pending_counts)
                pending = None
            reason = _describe(exc)
            self._recover_cut_chunk(position)
            self._note(position, reason, "rest", self._last_read_ns())
            return
        finally:
            if pending is not None:
                self._finish_scanned_chunk(*pending, pending_counts)
        self._note(position, "file ends before the MCAP footer", "rest", self._last_read_ns())

    def _note(
        self,
        offset: int,
        reason: str,
        lost: LostMessages,
        start_ns: int | None = None,
        end_ns: int | None = None,
        counts: dict[str, int] | None = None,
    ) -> None:
        """Remember the damage at ``offset`` (the first reason found there wins)."""
        if offset in self._regions:
            return
        if lost == "span" and (start_ns is None or end_ns is None or start_ns > end_ns):
            start_ns = end_ns = None  # a damaged chunk header's times say nothing
        self._regions[offset] = DamagedRegion(
            self.path, offset, self.size, reason, lost, start_ns, end_ns, counts
        )

    def _last_read_ns(self) -> int | None:
        """The latest log time of the messages the scan found so far (None: none)."""
        latest: int | None = None
        for segment in self._segments:
            if segment.kind == _KIND_RECOVERED:  # its header's range covers the cut part too
                times = [r.log_time for r in self._recovered[segment.offset]
                         if isinstance(r, Message)]  # fmt: skip
                end = max(times) if times else None
            else:
                end = segment.end_ns
            if end is not None and (latest is None or end > latest):
                latest = end
        return latest

    def _topic_counts(self, channel_counts: dict[int, int]) -> dict[str, int] | None:
        """Channel id -> count as topic -> count; None if a channel is not declared."""
        counts: dict[str, int] = {}
        for cid, count in channel_counts.items():
            info = self._channels.get(cid)
            if info is None:
                return None
            counts[info.topic] = counts.get(info.topic, 0) + count
        return counts

    def _segment_counts(self, segment: _Segment) -> dict[str, int] | None:
        """Topic -> messages in a segment, from its message indexes; None if they do not say."""
        if segment.kind == _KIND_MESSAGE:
            ids = segment.channel_ids or frozenset()
            return self._topic_counts({cid: 1 for cid in ids}) if len(ids) == 1 else None
        if segment.offset in self._chunk_counts:
            return self._topic_counts(self._chunk_counts[segment.offset])
        offsets = self._index_offsets.get(segment.offset)
        if not offsets:
            return None
        channel_counts: dict[int, int] = {}
        for cid, index_offset in offsets.items():
            try:  # outside the chunk: often intact when the chunk is not
                record, _ = read_record(self._file, index_offset)
            except Exception:
                return None
            if not isinstance(record, MessageIndex) or record.channel_id != cid:
                return None
            channel_counts[cid] = len(record.records)
        return self._topic_counts(channel_counts)

    def _count_chunk(self, compression: str, compressed: int, uncompressed: int) -> None:
        self._chunk_compression[compression] = self._chunk_compression.get(compression, 0) + 1
        self._chunk_bytes[0] += compressed
        self._chunk_bytes[1] += uncompressed

    def _finish_scanned_chunk(
        self, chunk: Chunk, offset: int, end: int, index_counts: dict[int, int]
    ) -> None:
        self._count_chunk(chunk.compression, len(chunk.data), chunk.uncompressed_size)
        if index_counts and all(cid in self._channels for cid in index_counts):
            for cid, count in index_counts.items():
                self._counts[cid] = self._counts.get(cid, 0) + count
            channel_ids = frozenset(index_counts)
            self._chunk_counts[offset] = dict(index_counts)
        else:
            try:
                records = chunk_records(
                    chunk, validate_crc=self.validate_crcs, max_chunk_bytes=self.max_chunk_bytes
                )
            except Exception as exc:
                counts = self._topic_counts(index_counts) if index_counts else None
                self._note(offset, _describe(exc), "span", chunk.message_start_time,
                           chunk.message_end_time, counts)  # fmt: skip
                return
            found: set[int] = set()
            for record in records:
                if isinstance(record, Message):
                    found.add(record.channel_id)
                    self._counts[record.channel_id] = self._counts.get(record.channel_id, 0) + 1
                elif isinstance(record, Schema):
                    self._schemas.setdefault(record.id, record)
                elif isinstance(record, Channel):
                    self._add_channel(record)
            channel_ids = frozenset(found)
        self._segments.append(
            _Segment(
                chunk.message_start_time,
                chunk.message_end_time,
                offset,
                end - offset - _RECORD_PREFIX,
                _KIND_CHUNK,
                channel_ids,
            )
        )

    def _recover_cut_chunk(self, offset: int) -> None:
        """Keep the complete messages at the head of a chunk that the end of the file cuts.

        A writer killed in the middle of writing a chunk leaves its first part:
        the compressed stream of that part still decompresses (zstd and lz4
        frames decode block by block), and every message record that is whole
        in it is as good as any other.
        """
        stream = self._file
        try:
            stream.seek(offset)
            prefix = stream.read(_RECORD_PREFIX)
            if prefix[0] != Opcode.CHUNK:
                return
            if offset + _RECORD_PREFIX + int.from_bytes(prefix[1:], "little") <= self.size:
                return  # the record fits in the file: corrupt, not cut
            chunk = read_cut_chunk(stream)
            records = chunk_records(
                chunk, validate_crc=False, max_chunk_bytes=self.max_chunk_bytes, partial=True
            )
        except Exception:
            return
        found: set[int] = set()
        for record in records:
            if isinstance(record, Schema):
                self._schemas.setdefault(record.id, record)
            elif isinstance(record, Channel):
                self._add_channel(record)
            elif isinstance(record, Message):
                found.add(record.channel_id)
                self._counts[record.channel_id] = self._counts.get(record.channel_id, 0) + 1
        if not found:
            return
        self._recovered[offset] = records
        self._segments.append(
            _Segment(
                chunk.message_start_time,
                chunk.message_end_time,
                offset,
                0,
                _KIND_RECOVERED,
                frozenset(found),
            )
        )

    def _add_channel(self, channel: Channel) -> None:
        if channel.id in self._channels:
            return
        schema = self._schemas.get(channel.schema_id)
        self._channel_records[channel.id] = channel
        self._channels[channel.id] = _ChannelInfo(
            topic=channel.topic,
            msgtype=schema.name if schema is not None else "",
            message_encoding=channel.message_encoding,
            offered_qos_profiles=channel.metadata.get("offered_qos_profiles", ""),
            type_description_hash=channel.metadata.get("topic_type_hash", ""),
        )

    def _take_metadata(self, record: Metadata) -> None:
        if record.name == ROSBAG2_METADATA_RECORD and SERIALIZED_METADATA_KEY in record.metadata:
            self.rosbag2_metadata = parse_bag_metadata(record.metadata[SERIALIZED_METADATA_KEY])

    # -- queries ---------------------------------------------------------------

    @property
    def damage(self) -> list[tuple[int, str]]:
        """Damaged regions found so far, as (byte offset, reason), by offset."""
        return [(region.offset, region.reason) for region in self.damaged_regions]

    @property
    def damaged_regions(self) -> list[DamagedRegion]:
        """Damaged regions found so far, with the messages each cost, by offset.

        Found at opening (a cut, a scan's damaged chunk) or while reading (a
        chunk that fails when its turn comes): a region after the messages
        read so far may not be known yet.
        """
        return [self._regions[offset] for offset in sorted(self._regions)]

    def topics(self) -> dict[str, TopicInfo]:
        """Topics of this file with their message counts (of the intact part)."""
        result: dict[str, TopicInfo] = {}
        for cid in sorted(self._channels):
            info = self._channels[cid]
            count = self._counts.get(cid, 0)
            previous = result.get(info.topic)
            if previous is not None:  # several channels on one topic: first one describes it
                result[info.topic] = dataclasses.replace(
                    previous, message_count=previous.message_count + count
                )
                continue
            result[info.topic] = TopicInfo(
                name=info.topic,
                msgtype=info.msgtype,
                serialization_format=info.message_encoding,
                offered_qos_profiles=info.offered_qos_profiles,
                message_count=count,
                type_description_hash=info.type_description_hash,
            )
        return result

    def chunk_stats(self) -> ChunkStats:
        """Count, compression and sizes of the complete chunks found."""
        return ChunkStats(
            count=sum(self._chunk_compression.values()),
            compression=dict(self._chunk_compression),
            compressed_bytes=self._chunk_bytes[0],
            uncompressed_bytes=self._chunk_bytes[1],
        )

    def definitions(self) -> dict[str, MessageDefinition]:
        """Topic -> the message definition stored in its schema (topics with a schema only)."""
        result: dict[str, MessageDefinition] = {}
        for cid in sorted(self._channel_records):
            channel = self._channel_records[cid]
            schema = self._schemas.get(channel.schema_id)
            if schema is None or channel.topic in result:
                continue
            try:
                text = schema.data.decode("utf-8")
            except UnicodeDecodeError:
                continue
            result[channel.topic] = MessageDefinition(schema.encoding, text)
        return result

    def time_range(self) -> tuple[int, int] | None:
        """(earliest, latest) log time in ns over the segments, None if there are none."""
        if not self._segments:
            return None
        return min(s.start_ns for s in self._segments), max(s.end_ns for s in self._segments)

    def corrupt_error(self) -> BagCorruptError | None:
        """The error to raise after the last intact message, or None if the file is sound."""
        regions = self.damaged_regions
        if not regions:
            return None
        more = f"; {len(regions) - 1} more damaged region(s)" if len(regions) > 1 else ""
        return BagCorruptError(f"{regions[0]}{more}")

    def messages(
        self,
        topics: frozenset[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[BagMessage]:
        """Yield intact messages in log-time order (ties: file order), then raise if damaged.

        Args:
            topics: Only these topics (None: all).
            start_ns: Only messages with log time >= start_ns.
            end_ns: Only messages with log time < end_ns.

        Raises:
            BagCorruptError: after the last intact message, if any part of the
                file could not be read.
        """
        if topics is None:
            channel_ids: frozenset[int] | None = None
        else:
            channel_ids = frozenset(c for c, i in self._channels.items() if i.topic in topics)
        heap: list[tuple[int, int, int, Any]] = []
        for segment in self._segments:
            if start_ns is not None and segment.end_ns < start_ns:
                continue
            if end_ns is not None and segment.start_ns >= end_ns:
                continue
            if (
                channel_ids is not None
                and segment.channel_ids is not None
                and segment.channel_ids.isdisjoint(channel_ids)
            ):
                continue
            heap.append((segment.start_ns, segment.offset, -1, segment))
        heapq.heapify(heap)
        heappop, heappush = heapq.heappop, heapq.heappush
        while heap:
            item = heappop(heap)
            if item[2] >= 0:
                yield item[3]
                continue
            loaded = self._load(item[3], channel_ids, topics, start_ns, end_ns)
            # Fast path: while this segment's messages come before everything
            # still queued, yield them directly instead of through the heap.
            head = heap[0] if heap else None
            for position, entry in enumerate(loaded):
                if head is not None and head < entry:
                    for rest in loaded[position:]:
                        heappush(heap, rest)
                    break
                yield entry[3]
        error = self.corrupt_error()
        if error is not None:
            raise error

    def _load(
        self,
        segment: _Segment,
        channel_ids: frozenset[int] | None,
        topics: frozenset[str] | None,
        start_ns: int | None,
        end_ns: int | None,
    ) -> list[tuple[int, int, int, BagMessage]]:
        """Read one segment's messages that pass the filters, sorted by (log time, position)."""
        stream = self._file
        try:
            if segment.kind == _KIND_RECOVERED:
                records = self._recovered[segment.offset]
            else:
                record, _ = read_record(stream, segment.offset)
                if segment.kind == _KIND_MESSAGE:
                    records = [record]
                elif isinstance(record, Chunk):
                    records = chunk_records(
                        record,
                        validate_crc=self.validate_crcs,
                        max_chunk_bytes=self.max_chunk_bytes,
                    )
                else:
                    raise RecordDamage("the summary's chunk index points at no chunk record")
        except Exception as exc:
            self._note(segment.offset, _describe(exc), "span", segment.start_ns, segment.end_ns,
                       self._segment_counts(segment))  # fmt: skip
            return []
        channels = self._channels
        offset = segment.offset
        out: list[tuple[int, int, int, BagMessage]] = []
        for index, record in enumerate(records):
            if type(record) is not Message:
                if isinstance(record, Schema):
                    self._schemas.setdefault(record.id, record)
                elif isinstance(record, Channel) and record.id not in channels:
                    self._add_channel(record)
                    if topics is not None and record.topic in topics:
                        channel_ids = (channel_ids or frozenset()) | {record.id}
                continue
            cid = record.channel_id
            if channel_ids is not None and cid not in channel_ids:
                continue
            log_time = record.log_time
            if (start_ns is not None and log_time < start_ns) or (
                end_ns is not None and log_time >= end_ns
            ):
                continue
            info = channels.get(cid)
            if info is None:
                self._note(offset, f"message on undeclared channel {cid}", "span",
                           segment.start_ns, segment.end_ns)  # fmt: skip
                continue
            out.append(
                (
                    log_time,
                    offset,
                    index,
                    BagMessage(
                        info.topic, info.msgtype, log_time, record.data, record.publish_time
                    ),
                )
            )
        out.sort()
        return out

    def close(self) -> None:
        """Close the file."""
        self._raw.close()
