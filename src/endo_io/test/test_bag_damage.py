"""Damaged and missing bags: every intact message comes back, then a clear error."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import MessageIndex
from mcap.stream_reader import StreamReader
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from endo_io.bag import (
    BagCorruptError,
    BagError,
    BagNotFoundError,
    BagReader,
    BagWriter,
    DamagedRegion,
    deserialize,
)

MESSAGES_PER_CHUNK = 5
CHUNKS = 6
# MCAP layout facts used to locate message records inside an uncompressed
# chunk: record prefix (opcode u8 + length u64) = 9 bytes; chunk body before
# its records = start, end, uncompressed size (u64 x3) + crc (u32) +
# compression string (u32 length + "") + records length (u64) = 40 bytes;
# message body before its data = channel u16 + sequence u32 + 2 x u64 time = 22.
CHUNK_RECORDS_START = 9 + 40
MESSAGE_OVERHEAD = 9 + 22


def small_image(i: int) -> Image:
    rng = np.random.default_rng(i)
    msg = Image(height=6, width=8, encoding="rgb8", step=24)
    msg.data = rng.integers(0, 255, size=6 * 24, dtype=np.uint8).tobytes()
    msg.header.stamp.sec = i
    msg.header.frame_id = "endoscope_optical_frame"
    return msg


def write_chunked_bag(path, compression: str) -> list[tuple[int, bytes]]:
    """CHUNKS chunks of MESSAGES_PER_CHUNK images; returns (log_time, cdr) written."""
    written = []
    with BagWriter(path, compression=compression, chunk_size=1 << 20) as writer:
        writer.add_topic("/image", "sensor_msgs/msg/Image")
        for c in range(CHUNKS):
            for k in range(MESSAGES_PER_CHUNK):
                i = c * MESSAGES_PER_CHUNK + k
                payload = serialize_message(small_image(i))
                writer.write("/image", payload, 1_000 + 10 * i)
                written.append((1_000 + 10 * i, payload))
            writer.flush()
    return written


def chunk_layout(path) -> list[tuple[int, int, list[int]]]:
    """(chunk start, chunk end, [file offset of the end of each message record]) per chunk."""
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
        layout = []
        for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            ends = []
            for offset in index.message_index_offsets.values():
                stream.seek(offset)
                record = next(StreamReader(stream, skip_magic=True).records)
                assert isinstance(record, MessageIndex)
                ends.extend(o for _, o in record.records)
            layout.append(
                (index.chunk_start_offset, index.chunk_start_offset + index.chunk_length, ends)
            )
    return layout


def read_until_error(path) -> tuple[list[tuple[int, bytes]], BagCorruptError | None]:
    got: list[tuple[int, bytes]] = []
    try:
        with BagReader(path) as reader:
            for message in reader.messages():
                got.append((message.log_time_ns, message.data))
    except BagCorruptError as exc:
        return got, exc
    return got, None


def assert_clear_error(error: BagCorruptError | None, path, offset: int | None = None) -> None:
    assert error is not None, "a damaged bag must end with BagCorruptError"
    text = str(error)
    assert str(path) in text and "byte" in text and "\n" not in text
    if offset is not None:
        assert f"byte {offset} " in text


def cut_copy(source, target, cut: int):
    target.write_bytes(source.read_bytes()[:cut])
    return target


def test_uncompressed_bag_cut_anywhere_returns_every_whole_message(tmp_path):
    path = tmp_path / "full.mcap"
    written = write_chunked_bag(path, "none")
    size = path.stat().st_size
    layout = chunk_layout(path)
    data_size = len(written[0][1])
    record_ends = []
    for start, _, offsets in layout:
        record_ends.extend(
            start + CHUNK_RECORDS_START + o + MESSAGE_OVERHEAD + data_size for o in offsets
        )
    assert len(record_ends) == len(written)
    rng = np.random.default_rng(7)
    cuts = {0, 3, 8, 20, size - 1, *rng.integers(9, size - 1, size=14).tolist()}
    cuts |= {end for _, end, _ in layout} | {
        record_ends[3],
        record_ends[3] - 1,
        record_ends[12] + 2,
    }
    for cut in sorted(cuts):
        damaged = cut_copy(path, tmp_path / f"cut_{cut}.mcap", cut)
        got, error = read_until_error(damaged)
        expected = sum(1 for end in record_ends if end <= cut)
        assert got == written[:expected], f"cut at {cut}"
        assert_clear_error(error, damaged)


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_compressed_bag_cut_anywhere_returns_a_prefix_with_all_whole_chunks(tmp_path, compression):
    path = tmp_path / "full.mcap"
    written = write_chunked_bag(path, compression)
    size = path.stat().st_size
    layout = chunk_layout(path)
    rng = np.random.default_rng(11)
    cuts = {5, size - 10, *rng.integers(9, size, size=10).tolist()}
    cuts |= {end for _, end, _ in layout} | {start + 60 for start, _, _ in layout}
    for cut in sorted(cuts):
        damaged = cut_copy(path, tmp_path / f"cut_{cut}.mcap", cut)
        got, error = read_until_error(damaged)
        whole_chunks = sum(1 for _, end, _ in layout if end <= cut)
        assert len(got) >= whole_chunks * MESSAGES_PER_CHUNK, f"cut at {cut}"
        assert got == written[: len(got)], f"cut at {cut}"
        assert_clear_error(error, damaged)


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_cut_inside_last_chunk_keeps_its_whole_messages(tmp_path, compression):
    # zstd and lz4 decode block by block (<= 128 KiB): cut near the end of a
    # chunk of large images and the messages at its head still come back.
    # (The exact count depends on block boundaries.)
    rng = np.random.default_rng(3)
    path = tmp_path / "large.mcap"
    written = []
    with BagWriter(path, compression=compression, chunk_size=1 << 22) as writer:
        writer.add_topic("/image", "sensor_msgs/msg/Image")
        for i in range(10):
            msg = Image(height=120, width=160, encoding="rgb8", step=480)
            msg.data = rng.integers(0, 255, size=120 * 480, dtype=np.uint8).tobytes()
            written.append((100 + i, serialize_message(msg)))
            writer.write("/image", written[-1][1], 100 + i)
            if i == 4:
                writer.flush()
    start, end, _ = chunk_layout(path)[-1]
    damaged = cut_copy(path, tmp_path / "cut.mcap", start + 3 * (end - start) // 4)
    got, error = read_until_error(damaged)
    assert 5 < len(got) < 10
    assert got == written[: len(got)]
    assert_clear_error(error, damaged, offset=start)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_corrupt_chunk_is_skipped_and_reported(tmp_path, compression):
    path = tmp_path / "full.mcap"
    written = write_chunked_bag(path, compression)
    layout = chunk_layout(path)
    bad_start, bad_end, _ = layout[2]
    raw = bytearray(path.read_bytes())
    middle = (bad_start + bad_end) // 2
    raw[middle : middle + 16] = bytes(b ^ 0x5A for b in raw[middle : middle + 16])
    damaged = tmp_path / "corrupt.mcap"
    damaged.write_bytes(bytes(raw))
    got, error = read_until_error(damaged)
    lost = set(range(2 * MESSAGES_PER_CHUNK, 3 * MESSAGES_PER_CHUNK))
    assert got == [w for i, w in enumerate(written) if i not in lost]
    assert_clear_error(error, damaged, offset=bad_start)
    # The same damage in a file that lost its summary (scan instead of index).
    data_end = layout[-1][1]
    while raw[data_end] != 0x0F:  # skip the last chunk's message index records
        data_end += 9 + int.from_bytes(raw[data_end + 1 : data_end + 9], "little")
    no_summary = tmp_path / "corrupt_cut.mcap"
    no_summary.write_bytes(bytes(raw[:data_end]))
    got, error = read_until_error(no_summary)
    assert got == [w for i, w in enumerate(written) if i not in lost]
    assert_clear_error(error, no_summary, offset=bad_start)


def test_damage_is_reported_before_reading(tmp_path):
    path = tmp_path / "full.mcap"
    write_chunked_bag(path, "zstd")
    damaged = cut_copy(path, tmp_path / "cut.mcap", path.stat().st_size // 2)
    with BagReader(damaged) as reader:
        assert reader.damage is not None and str(damaged) in reader.damage
        assert 0 < reader.topics["/image"].message_count < CHUNKS * MESSAGES_PER_CHUNK
    with BagReader(path) as reader:
        assert reader.damage is None
        assert reader.topics["/image"].message_count == CHUNKS * MESSAGES_PER_CHUNK


def test_missing_paths_and_non_bags(tmp_path):
    with pytest.raises(BagNotFoundError, match="no such bag"):
        BagReader(tmp_path / "nope.mcap")
    with pytest.raises(FileNotFoundError):  # BagNotFoundError is one too
        BagReader(tmp_path / "nope.mcap")
    empty_dir = tmp_path / "empty_bag"
    empty_dir.mkdir()
    with pytest.raises(BagNotFoundError, match=r"metadata\.yaml"):
        BagReader(empty_dir)
    listed = tmp_path / "listed"
    with BagWriter(listed) as writer:
        writer.write_message("/image", small_image(0), 5)
    (listed / "listed_0.mcap").unlink()
    with pytest.raises(BagNotFoundError, match=r"listed_0\.mcap"):
        BagReader(listed)
    text = tmp_path / "notes.mcap"
    text.write_text("this is not a bag at all\n")
    with pytest.raises(BagError, match="not an MCAP file"):
        BagReader(text)


def test_a_sqlite3_bag_names_the_command_that_converts_it(tmp_path):
    # `ros2 bag record` before Jazzy wrote sqlite3 (.db3) bags; the error said only
    # "not supported": the command it names now works as printed
    import shlex
    import subprocess
    import sys
    from pathlib import Path

    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from endo_io.bag import serialize

    typestore = get_typestore(Stores.ROS2_JAZZY)
    bag = tmp_path / "humble rig"
    writer = Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3)
    writer.open()
    connection = writer.add_connection("/image", "sensor_msgs/msg/Image", typestore=typestore)
    writer.write(connection, 5, serialize(small_image(0)))
    writer.close()
    with pytest.raises(BagError) as caught:
        BagReader(bag)
    message = str(caught.value)
    assert message.startswith(f"{bag}: storage 'sqlite3' is not supported, only mcap (convert it: ")
    command = message.split("(convert it: ", 1)[1].rstrip(")")
    argv = shlex.split(command)
    argv[0] = str(Path(sys.executable).parent / argv[0])
    subprocess.run(argv, check=True, capture_output=True, timeout=120)
    with BagReader(tmp_path / "humble rig_mcap") as reader:
        assert [(m.topic, m.log_time_ns) for m in reader.messages()] == [("/image", 5)]
    # the .db3 file itself, not its directory: the same command, not "bad magic"
    (db3,) = bag.glob("*.db3")
    with pytest.raises(BagError, match="sqlite3") as caught:
        BagReader(db3)
    assert f"rosbags-convert --src {shlex.quote(str(bag))} " in str(caught.value)


def test_empty_and_magic_only_files_are_truncated_bags(tmp_path):
    for cut in (0, 4, 8):
        path = tmp_path / f"stub_{cut}.mcap"
        path.write_bytes(b"\x89MCAP0\r\n"[:cut])
        got, error = read_until_error(path)
        assert got == []
        assert_clear_error(error, path, offset=cut)


def test_decoded_messages_of_a_cut_bag_are_exact(tmp_path):
    path = tmp_path / "full.mcap"
    write_chunked_bag(path, "lz4")
    layout = chunk_layout(path)
    damaged = cut_copy(path, tmp_path / "cut.mcap", layout[3][1] + 1)
    decoded = []
    with BagReader(damaged) as reader, pytest.raises(BagCorruptError):
        for message in reader.messages():
            decoded.append(deserialize(message))
    assert decoded == [small_image(i) for i in range(4 * MESSAGES_PER_CHUNK)]


def test_a_cut_in_the_closing_magic_names_an_offset_inside_the_file(tmp_path):
    # Issue 16: a bag one byte short reported "byte 14997367 of 14997366".
    path = tmp_path / "full.mcap"
    written = write_chunked_bag(path, "zstd")
    size = path.stat().st_size
    for cut in range(size - 8, size):
        damaged = cut_copy(path, tmp_path / f"cut_{cut}.mcap", cut)
        got, error = read_until_error(damaged)
        assert got == written, f"cut at {cut}"
        assert_clear_error(error, damaged, offset=size - 8)
        assert f"of {cut} " in str(error) and "closing MCAP magic" in str(error)


def _corrupt_chunk(path, target, chunk: int):
    """A copy of ``path`` with 16 flipped bytes in the middle of its ``chunk``-th chunk."""
    start, end, _ = chunk_layout(path)[chunk]
    raw = bytearray(path.read_bytes())
    middle = (start + end) // 2
    raw[middle : middle + 16] = bytes(b ^ 0x5A for b in raw[middle : middle + 16])
    target.write_bytes(bytes(raw))
    return target, start


@pytest.mark.parametrize("summary", [True, False])
def test_a_corrupt_chunk_is_a_region_with_its_log_times_and_the_index_counts(tmp_path, summary):
    path = tmp_path / "full.mcap"
    written = write_chunked_bag(path, "zstd")
    damaged, bad_start = _corrupt_chunk(path, tmp_path / "corrupt.mcap", 2)
    if not summary:  # the data section only: the scan lists the chunks, counts from their indexes
        raw = damaged.read_bytes()
        data_end = chunk_layout(path)[-1][1]
        while raw[data_end] != 0x0F:  # past the last chunk's message index records
            data_end += 9 + int.from_bytes(raw[data_end + 1 : data_end + 9], "little")
        damaged.write_bytes(raw[:data_end])
    lost = [t for t, _ in written[2 * MESSAGES_PER_CHUNK : 3 * MESSAGES_PER_CHUNK]]
    with BagReader(damaged) as reader:

        def spans() -> list[DamagedRegion]:
            return [r for r in reader.damaged_regions if r.lost == "span"]

        # a chunk is read when its turn comes: before that nothing is known of it
        assert spans() == []
        messages = reader.messages()
        for _ in range(2 * MESSAGES_PER_CHUNK):
            next(messages)
        assert spans() == []
        next(messages)  # the next chunk's first message: the damaged one was tried before it
        (region,) = spans()
        with pytest.raises(BagCorruptError) as caught:
            list(messages)
        others = [r for r in reader.damaged_regions if r is not region]
    if summary:
        assert others == [] and str(caught.value) == str(region)
    else:  # the file also ends without its summary: nothing after its last message is known
        (cut,) = others
        assert cut.lost == "rest" and cut.start_ns == written[-1][0] and cut.offset > bad_start
        assert str(caught.value) == f"{region}; 1 more damaged region(s)"
    assert region.path == damaged and region.offset == bad_start
    assert region.file_size == damaged.stat().st_size
    assert region.lost == "span"
    assert (region.start_ns, region.end_ns) == (lost[0], lost[-1]) == (1100, 1140)
    assert region.lost_counts == {"/image": MESSAGES_PER_CHUNK}
    assert "chunk CRC mismatch" in region.reason or "decompress" in region.reason


def test_a_cut_is_a_region_open_after_the_last_message_read(tmp_path):
    path = tmp_path / "full.mcap"
    written = write_chunked_bag(path, "none")
    layout = chunk_layout(path)
    # inside the fourth chunk, past its first two whole messages (recovered from the cut chunk)
    cut = layout[3][0] + CHUNK_RECORDS_START + layout[3][2][2] + 1
    damaged = cut_copy(path, tmp_path / "cut.mcap", cut)
    got, error = read_until_error(damaged)
    assert len(got) == 3 * MESSAGES_PER_CHUNK + 2
    with BagReader(damaged) as reader:  # a cut is found at opening
        (region,) = reader.damaged_regions
    assert region.lost == "rest" and region.offset == layout[3][0]
    assert region.start_ns == got[-1][0] == written[3 * MESSAGES_PER_CHUNK + 1][0]
    assert region.end_ns is None and region.lost_counts is None
    assert str(error) == str(region)
    # at a record boundary: the file ends before its footer, after the last whole chunk
    damaged = cut_copy(path, tmp_path / "cut_at_chunk.mcap", layout[2][1])
    with BagReader(damaged) as reader:
        (region,) = reader.damaged_regions
    assert region.lost == "rest" and region.start_ns == written[3 * MESSAGES_PER_CHUNK - 1][0]
    assert "file ends before the MCAP footer" in region.reason
    # nothing read before the damage
    damaged = cut_copy(path, tmp_path / "magic.mcap", 5)
    with BagReader(damaged) as reader:
        (region,) = reader.damaged_regions
    assert region.lost == "rest" and region.start_ns is None


def test_a_cut_closing_magic_is_a_region_that_cost_no_message(tmp_path):
    path = tmp_path / "full.mcap"
    write_chunked_bag(path, "zstd")
    damaged = cut_copy(path, tmp_path / "cut.mcap", path.stat().st_size - 3)
    with BagReader(damaged) as reader:
        (region,) = reader.damaged_regions
    assert region.lost == "none" and region.start_ns is None and region.end_ns is None
    assert "closing MCAP magic" in region.reason


def test_a_split_bag_file_cut_before_any_message_loses_what_came_after_the_files_before(
    tmp_path,
):
    # Review, session 16: a recorder killed at a split's rollover leaves a last file with
    # nothing readable; its region had no log time, and endo-process placed it "inside"
    # the frames read, saying "the frames after them were processed".
    from endo_io.bag.repair import reindex

    directory = tmp_path / "split"
    directory.mkdir()
    written = write_chunked_bag(directory / "split_0.mcap", "none")
    (directory / "split_1.mcap").write_bytes(b"\x89MCAP")
    reindex(directory)
    with BagReader(directory) as reader:
        (region,) = reader.damaged_regions
    assert region.path.name == "split_1.mcap" and region.lost == "rest"
    assert region.start_ns == written[-1][0]  # the latest log time of the file before it
    with BagReader(directory / "split_1.mcap") as reader:  # alone, it has no time before
        (alone,) = reader.damaged_regions
    assert alone.start_ns is None
