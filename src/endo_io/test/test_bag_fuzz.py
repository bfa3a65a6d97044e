"""Fuzzing untrusted bags: the reader meets truncation, flipped bytes and hostile lengths.

Bags come from other people's rigs. Whatever the damage, reading must

* raise nothing but the project's named errors (:class:`BagError` and its
  subclasses),
* return every message stored before the first damaged byte, and nothing
  that was not stored (chunk CRCs catch flipped message bytes),
* never allocate what a length field declares before checking it against
  the bytes there are (peak traced memory stays a small multiple of the
  file, even when a field declares ``2**60`` bytes).

The budget is small in ``make test`` (``ENDO3D_FUZZ_EXAMPLES``, default 30
examples per property) and large in ``make fuzz``.
"""

from __future__ import annotations

import os
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import Chunk, Footer, Header
from mcap.stream_reader import MAGIC_SIZE
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Float32

from endo_io.bag import BagError, BagReader, BagWriter
from endo_io.bag.mcap_file import MCAP_MAGIC
from endo_io.bag.mcap_records import DECOMPRESS_STEP

pytestmark = pytest.mark.fuzz

EXAMPLES = int(os.environ.get("ENDO3D_FUZZ_EXAMPLES", "30"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
CHUNKS = 4
PER_CHUNK = 4
HOSTILE = [0, 1, 21, 22, 2**31, 2**32 - 1, 2**32, 2**60, 2**63, 2**64 - 1]
# Peak traced memory allowed while reading a damaged copy of these ~10 KB
# bags: one decompression step (a hostile declared size gets no more than
# that), and a little; one allocation of a declared size would be gigabytes.
MEMORY_LIMIT = DECOMPRESS_STEP + (1 << 20)


class Layout:
    """An intact bag's bytes and where each of its messages lives.

    A plain class (not a dataclass), so that hypothesis prints it short.
    """

    def __init__(
        self,
        raw: bytes,
        messages: list[tuple[str, int, bytes]],
        chunk_ends: list[int],
        length_fields: list[int],
    ) -> None:
        self.raw = raw
        self.messages = messages  # (topic, log time, data), in log-time order
        self.chunk_ends = chunk_ends  # file offset where the chunk holding messages[i] ends
        self.length_fields = length_fields  # offsets of 8-byte length fields

    def __repr__(self) -> str:
        return f"Layout({len(self.raw)} bytes, {len(self.messages)} messages)"


def _write_bag(path: Path, compression: str) -> list[tuple[str, int, bytes]]:
    rng = np.random.default_rng(5)
    written = []
    with BagWriter(path, compression=compression) as writer:
        writer.add_topic("/image", "sensor_msgs/msg/Image")
        writer.add_topic("/value", "std_msgs/msg/Float32")
        for c in range(CHUNKS):
            for k in range(PER_CHUNK):
                i = c * PER_CHUNK + k
                if k % 2:
                    data = serialize_message(Float32(data=float(i)))
                    topic = "/value"
                else:
                    image = Image(height=4, width=6, encoding="mono8", step=6)
                    image.data = rng.integers(0, 256, 24, dtype=np.uint8).tobytes()
                    data, topic = serialize_message(image), "/image"
                writer.write(topic, data, 1_000 + 10 * i)
                written.append((topic, 1_000 + 10 * i, data))
            writer.flush()
    return written


def _top_level_records(raw: bytes) -> Iterator[tuple[int, int, int]]:
    """(offset, opcode, body length) of every top-level record of an intact file."""
    position = MAGIC_SIZE
    while position < len(raw) - MAGIC_SIZE:
        opcode = raw[position]
        length = int.from_bytes(raw[position + 1 : position + 9], "little")
        yield position, opcode, length
        position += 9 + length


def _layout(path: Path, written: list[tuple[str, int, bytes]]) -> Layout:
    raw = path.read_bytes()
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) == CHUNKS
    chunk_ends = [
        chunks[i // PER_CHUNK].chunk_start_offset + chunks[i // PER_CHUNK].chunk_length
        for i in range(len(written))
    ]
    fields = []
    for offset, opcode, _ in _top_level_records(raw):
        fields.append(offset + 1)  # the record length
        if opcode == 0x06:  # chunk: its uncompressed size and its data length
            compression_length = int.from_bytes(raw[offset + 37 : offset + 41], "little")
            fields += [offset + 9 + 16, offset + 9 + 32 + compression_length]
    return Layout(raw, written, chunk_ends, fields)


@pytest.fixture(scope="module")
def layouts(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Layout]:
    base = tmp_path_factory.mktemp("fuzz_bags")
    result = {}
    for compression in ("zstd", "lz4", "none"):
        path = base / f"{compression}.mcap"
        result[compression] = _layout(path, _write_bag(path, compression))
    return result


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz_scratch") / "damaged.mcap"


def _read_damaged(path: Path, data: bytes) -> tuple[list[tuple[str, int, bytes]], int]:
    """Every message read from ``data`` (as a file) before the error, and peak traced memory."""
    path.write_bytes(data)
    got: list[tuple[str, int, bytes]] = []
    tracemalloc.start()
    try:
        with BagReader(path) as reader:
            for message in reader.messages():
                got.append((message.topic, message.log_time_ns, message.data))
    except BagError as error:
        text = str(error)
        assert "\n" not in text and str(path) in text
        if "byte " in text:  # "... at byte N of SIZE ...": never past the end of the file
            offset = int(text.split("byte ", 1)[1].split(" ", 1)[0])
            assert offset <= len(data), text
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return got, peak


def _check(layout: Layout, got: list[tuple[str, int, bytes]], first_damage: int, peak: int):
    stored = set(layout.messages)
    assert all(m in stored for m in got), "a message that was never written came back"
    pairs = zip(layout.messages, layout.chunk_ends, strict=True)
    intact = [m for m, end in pairs if end <= first_damage]
    returned = set(got)
    missing = [m[1] for m in intact if m not in returned]
    assert not missing, f"intact messages before byte {first_damage} were lost: {missing}"
    assert peak < MEMORY_LIMIT, f"reading a {len(layout.raw)}-byte file peaked at {peak} bytes"


COMPRESSIONS = st.sampled_from(["zstd", "lz4", "none"])


@FUZZ
@given(compression=COMPRESSIONS, fraction=st.floats(0.0, 1.0))
def test_truncated_bag_returns_every_message_before_the_cut(
    layouts, scratch, compression, fraction
):
    layout = layouts[compression]
    cut = round(fraction * len(layout.raw))
    got, peak = _read_damaged(scratch, layout.raw[:cut])
    _check(layout, got, cut, peak)


@FUZZ
@given(
    compression=COMPRESSIONS,
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), min_size=1, max_size=4),
    drop_summary=st.booleans(),
)
def test_flipped_bytes_cost_only_the_damaged_chunks(
    layouts, scratch, compression, flips, drop_summary
):
    layout = layouts[compression]
    raw = bytearray(layout.raw)
    if drop_summary:  # as a SIGKILLed recorder leaves it: no summary, no footer
        raw = raw[: max(layout.chunk_ends)]
    positions = []
    for fraction, xor in flips:
        position = min(int(fraction * len(raw)), len(raw) - 1)
        raw[position] ^= xor
        positions.append(position)
    got, peak = _read_damaged(scratch, bytes(raw))
    _check(layout, got, min(positions), peak)


@FUZZ
@given(
    compression=COMPRESSIONS,
    field=st.integers(0, 10_000),
    value=st.sampled_from(HOSTILE) | st.integers(0, 2**64 - 1),
    drop_summary=st.booleans(),
)
def test_hostile_lengths_are_refused_before_allocation(
    layouts, scratch, compression, field, value, drop_summary
):
    layout = layouts[compression]
    raw = bytearray(layout.raw)
    offset = layout.length_fields[field % len(layout.length_fields)]
    raw[offset : offset + 8] = value.to_bytes(8, "little")
    if drop_summary:
        raw = raw[: max(layout.chunk_ends)]
    got, peak = _read_damaged(scratch, bytes(raw))
    _check(layout, got, offset, peak)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_a_declared_length_of_2_to_the_60_is_refused_by_name(layouts, scratch, compression):
    layout = layouts[compression]
    records = list(_top_level_records(layout.raw))
    chunk_offset = next(offset for offset, opcode, _ in records if opcode == 0x06)
    name_length = int.from_bytes(layout.raw[chunk_offset + 37 : chunk_offset + 41], "little")
    fields = {
        "record length": chunk_offset + 1,
        "uncompressed size": chunk_offset + 25,
        "data length": chunk_offset + 41 + name_length,
    }
    for what, field in fields.items():
        raw = bytearray(layout.raw[: max(layout.chunk_ends)])  # no summary: lengths are read
        raw[field : field + 8] = (2**60).to_bytes(8, "little")
        scratch.write_bytes(bytes(raw))
        tracemalloc.start()
        with BagReader(scratch) as reader, pytest.raises(BagError) as caught:
            list(reader.messages())
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert peak < 1 << 20, f"{what}: {peak} bytes"
        assert "declares 1152921504606846976 bytes" in str(caught.value), what
        assert f"byte {chunk_offset} of" in str(caught.value), what


def _bare_file(chunk: Chunk) -> bytes:
    builder = RecordBuilder()
    Header(profile="ros2", library="fuzz").write(builder)
    chunk.write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return MCAP_MAGIC + builder.end() + MCAP_MAGIC


def test_a_decompression_bomb_stops_at_the_declared_size(scratch):
    # 64 MiB of zeros compress to a few KiB; the chunk declares 100 bytes.
    bomb = zstandard.ZstdCompressor().compress(bytes(64 << 20))
    for declared in (100, 2**60):
        chunk = Chunk(
            compression="zstd",
            data=bomb,
            message_start_time=0,
            message_end_time=0,
            uncompressed_crc=0,
            uncompressed_size=declared,
        )
        scratch.write_bytes(_bare_file(chunk))
        tracemalloc.start()
        with BagReader(scratch) as reader, pytest.raises(BagError) as caught:
            list(reader.messages())
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert peak < 16 << 20, peak
        text = str(caught.value)
        assert f"{declared}" in text and "\n" not in text
