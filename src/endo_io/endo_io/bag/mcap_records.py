"""Bounded reading of MCAP records: no length field is trusted before it is checked.

Bags come from other people's rigs, crashed recorders and interrupted copies,
so every length in them may be wrong. The ``mcap`` package's record parsers
read a length and then ask for that many bytes; Python's ``file.read(n)``
allocates ``n`` bytes before it finds the file shorter, and
``zstandard.decompress`` allocates the size a chunk declares. Here:

* :class:`BoundedFile` wraps the open file so that a read past its end is
  refused (:class:`LengthBeyondData`) *before* anything is allocated: a
  record, chunk or string declaring more bytes than the file has left is
  damage, whatever the number (``2**60`` included).
* :func:`decompress_chunk` refuses a chunk that declares more than
  ``max_chunk_bytes`` uncompressed, then decompresses it in steps of at most
  :data:`DECOMPRESS_STEP` bytes and stops as soon as the output exceeds the
  declared size, so memory follows the data actually produced, never a
  declared number.
* :func:`chunk_records` parses the records inside a chunk and checks each
  one's length against what is left of the chunk (the ``mcap`` package would
  return a message cut short as if it were whole).

Every failure is a :class:`RecordDamage` whose text is the one-line reason the
reader reports.
"""

from __future__ import annotations

import io
import zlib
from typing import IO, Any

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

#: Output produced per decompression step; bounds the memory a chunk costs
#: beyond the bytes it really decompresses to.
DECOMPRESS_STEP = 1 << 22
#: Default limit on a chunk's declared uncompressed size (a chunk holds at
#: least one whole message, so this is also the largest message read).
DEFAULT_MAX_CHUNK_BYTES = 1 << 30
#: opcode (u8) + record length (u64)
RECORD_PREFIX = 9
# channel id u16 + sequence u32 + log time u64 + publish time u64
_MESSAGE_HEADER = 22
_CHUNK_HEADER = 8 + 8 + 8 + 4 + 4  # start, end, uncompressed size, crc, compression length
_OPCODE_NAMES = {int(op): op.name.lower().replace("_", " ") for op in Opcode}


class RecordDamage(Exception):  # noqa: N818 - internal signal, reported as text by the reader
    """A record cannot be read; ``str()`` is the one-line reason."""


class LengthBeyondData(RecordDamage):
    """A length field declares more bytes than are left."""


def opcode_name(opcode: int) -> str:
    """Readable name of a record opcode (``chunk``, ``message index``, ...)."""
    return _OPCODE_NAMES.get(opcode, f"unknown (opcode 0x{opcode:02x})")


class BoundedFile:
    """A read-only view of the first ``size`` bytes of a file that refuses over-long reads.

    Args:
        file: An open binary file (positioned anywhere).
        size: The bytes that count as the file (its size when it was opened,
            so a file still being written reads as a consistent prefix).

    ``read(n)`` with ``n`` larger than what is left raises
    :class:`LengthBeyondData` without reading; a negative ``n`` (a corrupt
    length minus a header size) raises too. ``seek`` and ``tell`` work as on
    the file.
    """

    def __init__(self, file: IO[bytes], size: int) -> None:
        self._file = file
        self.size = size
        self._position = file.tell()

    def read(self, n: int | None = -1) -> bytes:
        """Read exactly ``n`` bytes (all that is left when ``n`` is None)."""
        left = self.size - self._position
        if n is None:
            n = left
        if n < 0:
            raise RecordDamage(f"a length field is {n}, negative after its header")
        if n > left:
            raise LengthBeyondData(
                f"a length field declares {n} bytes at byte {self._position}, "
                f"where the file has {max(left, 0)} left"
            )
        data = self._file.read(n)
        self._position += len(data)
        return data

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        """Move like ``file.seek``; returns the new position."""
        if whence == io.SEEK_END:
            offset, whence = self.size + offset, io.SEEK_SET
        self._position = self._file.seek(offset, whence)
        return self._position

    def tell(self) -> int:
        """The current position."""
        return self._position

    def seekable(self) -> bool:
        """Always True."""
        return True

    def readable(self) -> bool:
        """Always True."""
        return True


_RECORD_CLASSES: dict[int, Any] = {
    Opcode.ATTACHMENT: Attachment,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.DATA_END: DataEnd,
    Opcode.FOOTER: Footer,
    Opcode.HEADER: Header,
    Opcode.MESSAGE_INDEX: MessageIndex,
    Opcode.METADATA: Metadata,
    Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.SCHEMA: Schema,
    Opcode.STATISTICS: Statistics,
    Opcode.SUMMARY_OFFSET: SummaryOffset,
}


def read_record(stream: BoundedFile, offset: int) -> tuple[McapRecord | None, int]:
    """Read the top-level record at ``offset``; returns it (None: unknown opcode) and its end.

    The declared length is checked against the file before the body is read,
    and the parsed fields must fit in that length.

    Raises:
        LengthBeyondData: the file ends inside the record (a cut file), or its
            length field is larger than what is left (a corrupt one).
        RecordDamage: the body does not parse as its opcode says.
    """
    stream.seek(offset)
    left = stream.size - offset
    if left < RECORD_PREFIX:
        raise LengthBeyondData(f"file ends inside a record header ({left} of 9 bytes)")
    prefix = stream.read(RECORD_PREFIX)
    opcode = prefix[0]
    length = int.from_bytes(prefix[1:], "little")
    if length > left - RECORD_PREFIX:
        raise LengthBeyondData(
            f"file ends inside a{'n' if opcode_name(opcode)[0] in 'aeiou' else ''} "
            f"{opcode_name(opcode)} record (it declares {length} bytes, "
            f"{left - RECORD_PREFIX} are left)"
        )
    body = stream.read(length)
    end = offset + RECORD_PREFIX + length
    if opcode == Opcode.CHUNK:
        return _parse_chunk(body), end
    cls = _RECORD_CLASSES.get(opcode)
    if cls is None and opcode != Opcode.MESSAGE:
        return None, end  # unknown record types are skipped, as the MCAP spec says
    reader = ReadDataStream(io.BytesIO(body))
    try:
        if opcode == Opcode.MESSAGE:
            if length < _MESSAGE_HEADER:
                raise RecordDamage(f"message record of {length} bytes, shorter than its header")
            record = Message.read(reader, length)
        else:
            assert cls is not None
            record = cls.read(reader)
    except RecordDamage:
        raise
    except Exception as exc:  # struct.error, UnicodeDecodeError, EndOfFile ...
        raise RecordDamage(
            f"{opcode_name(opcode)} record is malformed ({type(exc).__name__})"
        ) from exc
    if reader.count > length:
        raise RecordDamage(f"{opcode_name(opcode)} record overruns its length")
    return record, end


def _parse_chunk(body: bytes) -> Chunk:
    size = len(body)
    if size < _CHUNK_HEADER:
        raise RecordDamage(f"chunk record of {size} bytes, shorter than its header")
    start = int.from_bytes(body[0:8], "little")
    end = int.from_bytes(body[8:16], "little")
    uncompressed_size = int.from_bytes(body[16:24], "little")
    crc = int.from_bytes(body[24:28], "little")
    compression_length = int.from_bytes(body[28:32], "little")
    data_start = _CHUNK_HEADER + compression_length + 8
    if data_start > size:
        raise LengthBeyondData(
            f"chunk compression name declares {compression_length} bytes, "
            f"{size - _CHUNK_HEADER} are left in the record"
        )
    try:
        compression = body[_CHUNK_HEADER : _CHUNK_HEADER + compression_length].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RecordDamage("chunk compression name is not UTF-8") from exc
    data_length = int.from_bytes(body[data_start - 8 : data_start], "little")
    if data_length > size - data_start:
        raise LengthBeyondData(
            f"chunk data declares {data_length} bytes, {size - data_start} are left in the record"
        )
    return Chunk(
        compression=compression,
        data=body[data_start : data_start + data_length],
        message_start_time=start,
        message_end_time=end,
        uncompressed_crc=crc,
        uncompressed_size=uncompressed_size,
    )


def read_cut_chunk(stream: BoundedFile) -> Chunk:
    """Read a chunk record whose data the end of the file cuts: keep the part that is there.

    ``stream`` is positioned after the record prefix. Raises
    :class:`RecordDamage` if even the chunk header is incomplete.
    """
    reader = ReadDataStream(stream)  # type: ignore[arg-type]  # read() is all it needs
    start, end, uncompressed_size, crc, compression_length = (
        reader.read8(),
        reader.read8(),
        reader.read8(),
        reader.read4(),
        reader.read4(),
    )
    compression = str(reader.read(compression_length), "utf-8")
    reader.read8()  # the declared data length, which the cut makes wrong
    data = stream.read(stream.size - stream.tell())
    return Chunk(
        compression=compression,
        data=data,
        message_start_time=start,
        message_end_time=end,
        uncompressed_crc=crc,
        uncompressed_size=uncompressed_size,
    )


def decompress_chunk(chunk: Chunk, max_chunk_bytes: int, *, partial: bool = False) -> bytes:
    """A chunk's records region, decompressed without trusting its declared size.

    Args:
        chunk: The chunk record.
        max_chunk_bytes: Refuse a chunk declaring more uncompressed bytes.
        partial: The chunk is cut short (a crashed writer): return what its
            data decompresses to, up to where it ends.

    Raises:
        RecordDamage: unknown compression, a declared size over the limit, or
            data that does not decompress to exactly the declared size.
    """
    declared = chunk.uncompressed_size
    if declared > max_chunk_bytes:
        raise RecordDamage(
            f"chunk declares {declared} bytes uncompressed, over the limit of {max_chunk_bytes}"
        )
    if chunk.compression == "":
        data = chunk.data
    elif chunk.compression == "zstd":
        data = _decompress_zstd(chunk.data, declared, partial)
    elif chunk.compression == "lz4":
        data = _decompress_lz4(chunk.data, declared, partial)
    else:
        raise RecordDamage(f"chunk compression {chunk.compression[:40]!r} is not supported")
    if len(data) != declared and not (partial and len(data) < declared):
        raise RecordDamage(
            f"{chunk.compression or 'uncompressed'} chunk holds {len(data)} bytes, "
            f"declares {declared}"
        )
    return data


def _decompress_zstd(data: bytes, declared: int, partial: bool) -> bytes:
    reader = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True)
    pieces: list[bytes] = []
    produced = 0
    try:
        while True:
            piece = reader.read(min(DECOMPRESS_STEP, declared - produced + 1))
            if not piece:
                break
            pieces.append(piece)
            produced += len(piece)
            if produced > declared:
                raise RecordDamage(f"zstd chunk decompresses to more than the {declared} declared")
    except zstandard.ZstdError as exc:
        if not partial:
            raise RecordDamage(f"zstd data does not decompress ({exc})") from exc
    return pieces[0] if len(pieces) == 1 else b"".join(pieces)


def _decompress_lz4(data: bytes, declared: int, partial: bool) -> bytes:
    decompressor = lz4.frame.LZ4FrameDecompressor()
    pieces: list[bytes] = []
    produced = 0
    source = data
    try:
        while not decompressor.eof:
            piece = decompressor.decompress(
                source, max_length=min(DECOMPRESS_STEP, declared - produced + 1)
            )
            source = b""
            pieces.append(piece)
            produced += len(piece)
            if produced > declared:
                raise RecordDamage(f"lz4 chunk decompresses to more than the {declared} declared")
            if not piece and decompressor.needs_input:
                if partial:
                    break
                raise RecordDamage("lz4 frame ends early")
    except RuntimeError as exc:  # lz4.frame raises RuntimeError on bad data
        if not partial:
            raise RecordDamage(f"lz4 data does not decompress ({exc})") from exc
    return b"".join(pieces)


def chunk_records(
    chunk: Chunk,
    *,
    validate_crc: bool,
    max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES,
    partial: bool = False,
) -> list[Any]:
    """The Schema, Channel and Message records in a chunk, each length checked.

    Args:
        chunk: The chunk record.
        validate_crc: Compare the CRC of the decompressed data with the
            chunk's (when the writer stored one).
        max_chunk_bytes: See :func:`decompress_chunk`.
        partial: The chunk is cut short: return its complete records and
            stop at the first incomplete one instead of raising.

    Raises:
        RecordDamage: the chunk does not decompress, its CRC does not match,
            or a record in it is malformed or overruns the chunk.
    """
    data = decompress_chunk(chunk, max_chunk_bytes, partial=partial)
    if validate_crc and not partial and chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise RecordDamage(
                f"chunk CRC mismatch (stored {chunk.uncompressed_crc:#010x}, data {crc:#010x})"
            )
    return parse_records(data, partial=partial)


def parse_records(data: bytes, *, partial: bool = False) -> list[Any]:
    """Parse a chunk's records region (Schema, Channel, Message; others skipped).

    A record whose length runs past the end of ``data``, a message shorter
    than its header, or a record whose fields overrun its length raises
    :class:`RecordDamage` (``partial``: the records before it are returned).
    """
    size = len(data)
    stream = ReadDataStream(io.BytesIO(data))
    records: list[Any] = []
    position = 0
    while position < size:
        if size - position < RECORD_PREFIX:
            if partial:
                break
            raise LengthBeyondData(f"chunk ends inside a record header at chunk byte {position}")
        opcode = data[position]
        length = int.from_bytes(data[position + 1 : position + RECORD_PREFIX], "little")
        body = position + RECORD_PREFIX
        if length > size - body:
            if partial:
                break
            raise LengthBeyondData(
                f"{opcode_name(opcode)} record at chunk byte {position} declares {length} bytes, "
                f"{size - body} are left in the chunk"
            )
        end = body + length
        stream.read(RECORD_PREFIX)
        try:
            if opcode == Opcode.MESSAGE:
                if length < _MESSAGE_HEADER:
                    raise RecordDamage(f"message record of {length} bytes, shorter than its header")
                records.append(Message.read(stream, length))
            elif opcode == Opcode.CHANNEL:
                records.append(Channel.read(stream))
            elif opcode == Opcode.SCHEMA:
                records.append(Schema.read(stream))
        except RecordDamage:
            raise
        except Exception as exc:  # struct.error, UnicodeDecodeError, EndOfFile ...
            raise RecordDamage(
                f"{opcode_name(opcode)} record at chunk byte {position} is malformed "
                f"({type(exc).__name__})"
            ) from exc
        if stream.count > end:
            raise RecordDamage(
                f"{opcode_name(opcode)} record at chunk byte {position} overruns its length"
            )
        if stream.count < end:
            stream.read(end - stream.count)
        position = end
    return records


__all__ = [
    "DECOMPRESS_STEP",
    "DEFAULT_MAX_CHUNK_BYTES",
    "RECORD_PREFIX",
    "BoundedFile",
    "LengthBeyondData",
    "RecordDamage",
    "chunk_records",
    "decompress_chunk",
    "opcode_name",
    "parse_records",
    "read_cut_chunk",
    "read_record",
]
