"""endo-bag info / reindex / recover, checked against the mcap library's own reading."""

from __future__ import annotations

import re
import shutil
from collections import defaultdict
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from std_msgs.msg import Float32

from endo_io.bag import BagCorruptError, BagReader, BagWriter, serialize
from endo_io.bag.info import bag_info
from endo_io.bag.metadata import read_metadata_yaml, write_metadata_yaml
from endo_io.bag.repair import recover, reindex
from endo_io.bag_cli import main

T0 = 1_763_800_000_000_000_000
MS = 1_000_000
SAMPLE = Path(__file__).resolve().parents[3] / "bags" / "phantom_colon.mcap"
# (topic, period in ms, count)
STREAMS = [("/fast", 10, 50), ("/medium", 33, 20), ("/slow", 250, 3)]


def write_streams(path: Path, **writer_options) -> list[tuple[str, int, bytes]]:
    events = [
        (T0 + k * period * MS + offset, topic, serialize(Float32(data=float(k))))
        for offset, (topic, period, count) in enumerate(STREAMS)
        for k in range(count)
    ]
    events.sort()
    with BagWriter(path, **writer_options) as writer:
        for stamp, topic, data in events:
            if topic not in writer.written:
                writer.add_topic(topic, "std_msgs/msg/Float32")
            writer.write(topic, data, stamp)
    return [(topic, stamp, data) for stamp, topic, data in events]


def mcap_truth(path: Path) -> dict:
    """What the mcap library reads from one complete file."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        times: dict[str, list[int]] = defaultdict(list)
        for _, channel, message in reader.iter_messages():
            times[channel.topic].append(message.log_time)
    stats = summary.statistics
    counts: dict[str, int] = defaultdict(int)
    types = {}
    for cid, n in stats.channel_message_counts.items():
        channel = summary.channels[cid]
        counts[channel.topic] += n
        types[channel.topic] = summary.schemas[channel.schema_id].name
    return {
        "count": stats.message_count,
        "start": stats.message_start_time,
        "end": stats.message_end_time,
        "topics": dict(counts),
        "types": types,
        "compression": {c.compression for c in summary.chunk_indexes},
        "chunks": len(summary.chunk_indexes),
        "hz": {t: (len(v) - 1) * 1e9 / (max(v) - min(v)) for t, v in times.items() if len(v) > 1},
    }


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["endo-bag", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


def parse_topics(text: str) -> dict[str, tuple[str, int, str]]:
    found = re.findall(r"Topic: (\S+)\s*\| Type: (\S+)\s*\| Count: (\d+) \| Frequency: (\S+)", text)
    return {name: (msgtype, int(count), hz) for name, msgtype, count, hz in found}


@pytest.mark.parametrize("bag", ["generated", "sample"])
def test_info_matches_the_mcap_librarys_summary(tmp_path, capsys, bag):
    if bag == "sample":
        path = SAMPLE
    else:
        path = tmp_path / "streams.mcap"
        write_streams(path, compression="lz4", chunk_size=300)
    truth = mcap_truth(path)
    code, out, err = run(capsys, "info", path)
    assert code == 0 and err == ""
    assert f"Messages:          {truth['count']}\n" in out
    duration = truth["end"] - truth["start"]
    assert f"Duration:          {duration // 10**9}.{duration % 10**9:09d}s" in out
    assert f"({truth['start'] // 10**9}.{truth['start'] % 10**9:09d})" in out
    assert f"({truth['end'] // 10**9}.{truth['end'] % 10**9:09d})" in out
    (compression,) = truth["compression"]
    assert f"Compression:       {compression}; {truth['chunks']} chunks" in out
    assert f"Bag size:          {path.stat().st_size / 2**20:.1f} MiB" in out or bag != "sample"
    topics = parse_topics(out)
    assert {t: n for t, (_, n, _) in topics.items()} == truth["topics"]
    assert {t: m for t, (m, _, _) in topics.items()} == truth["types"]
    for topic, hz in truth["hz"].items():
        assert topics[topic][2] == f"{hz:.2f}", topic
    if bag == "generated":  # and the rates written: 100, 30.3 and 4 Hz
        assert [topics[t][2] for t, _, _ in STREAMS] == ["100.00", "30.30", "4.00"]


def test_info_of_a_split_directory_sums_its_files(tmp_path, capsys):
    path = tmp_path / "split"
    written = write_streams(path, chunk_size=200, split_size_bytes=1_500)
    files = read_metadata_yaml(path)["relative_file_paths"]
    assert len(files) >= 3
    truths = [mcap_truth(path / name) for name in files]
    info = bag_info(path)
    assert info.message_count == sum(t["count"] for t in truths) == len(written)
    assert info.start_ns == min(t["start"] for t in truths)
    assert info.end_ns == max(t["end"] for t in truths)
    assert info.chunks.count == sum(t["chunks"] for t in truths)
    code, out, _ = run(capsys, "info", path)
    assert code == 0
    assert all(name in out for name in files)
    assert {t: n for t, (_, n, _) in parse_topics(out).items()} == {
        topic: count for topic, _, count in STREAMS
    }


def test_info_of_a_damaged_bag_summarises_the_intact_part_and_exits_1(tmp_path, capsys):
    path = tmp_path / "streams.mcap"
    write_streams(path, compression="zstd", chunk_size=300)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    intact = []
    with BagReader(cut) as reader, pytest.raises(BagCorruptError):
        intact.extend(reader.messages())
    code, out, err = run(capsys, "info", cut)
    assert code == 1
    assert f"Messages:          {len(intact)}\n" in out
    assert err.startswith("endo-bag: damaged: ") and len(err.splitlines()) == 1


def test_cli_errors_are_one_line_and_exit_2(tmp_path, capsys):
    notes = tmp_path / "notes.mcap"
    notes.write_text("not a bag\n")
    existing = tmp_path / "existing.mcap"
    write_streams(existing)
    cases = [
        ("info", tmp_path / "missing.mcap"),
        ("info", notes),
        ("reindex", tmp_path / "missing_dir"),
        ("reindex", existing),
        ("recover", tmp_path / "missing.mcap", tmp_path / "out.mcap"),
        ("recover", existing, existing),
        ("frobnicate",),
        ("info",),
    ]
    for args in cases:
        code, _, err = run(capsys, *args)
        assert code == 2, args
        assert re.match(r"endo-bag( \w+)?: error: ", err), (args, err)
        assert len(err.splitlines()) == 1, (args, err)
    assert not (tmp_path / "out.mcap").exists()


def test_reindex_rewrites_stale_duplicate_and_incomplete_metadata(tmp_path, capsys):
    path = tmp_path / "split"
    written = write_streams(path, chunk_size=200, split_size_bytes=1_500)
    metadata = read_metadata_yaml(path)
    files = metadata["relative_file_paths"]
    metadata.update(message_count=0, relative_file_paths=[files[0], files[0]])
    write_metadata_yaml(path, metadata)
    with BagReader(path) as reader:
        assert len(reader.warnings) == 3  # listed twice, files unlisted, stale count
    code, out, err = run(capsys, "reindex", path)
    assert code == 0 and err == ""
    assert f"{len(files)} file(s)" in out and f"{len(written)} messages" in out
    assert "the previous metadata.yaml counted 0" in out
    with BagReader(path) as reader:
        assert reader.warnings == []
        assert [(m.topic, m.log_time_ns, m.data) for m in reader.messages()] == written
    fresh = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert fresh["relative_file_paths"] == files
    assert fresh["message_count"] == len(written)
    assert {
        t["topic_metadata"]["name"]: t["message_count"] for t in fresh["topics_with_message_count"]
    } == {topic: count for topic, _, count in STREAMS}
    per_file = [mcap_truth(path / name)["count"] for name in files]
    assert [f["message_count"] for f in fresh["files"]] == per_file
    # A directory without metadata.yaml (a SIGKILLed ros2 bag record) becomes a bag again.
    (path / "metadata.yaml").unlink()
    assert run(capsys, "reindex", path)[0] == 0
    assert bag_info(path).message_count == len(written)


def test_recover_makes_a_complete_file_of_a_damaged_one(tmp_path, capsys):
    path = tmp_path / "streams.mcap"
    written = write_streams(path, compression="zstd", chunk_size=300)
    with path.open("rb") as stream:
        chunks = sorted(
            make_reader(stream).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )
    raw = bytearray(path.read_bytes())
    bad = chunks[2]
    middle = bad.chunk_start_offset + bad.chunk_length // 2
    raw[middle : middle + 8] = bytes(b ^ 0xFF for b in raw[middle : middle + 8])
    cut = chunks[-2].chunk_start_offset + chunks[-2].chunk_length + 5  # drop the last chunk
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(raw[:cut]))
    readable = []
    with BagReader(damaged) as reader, pytest.raises(BagCorruptError):
        readable.extend((m.topic, m.log_time_ns, m.data) for m in reader.messages())
    in_bad_chunk = sum(
        1 for _, t, _ in written if bad.message_start_time <= t <= bad.message_end_time
    )
    out_path = tmp_path / "recovered.mcap"
    code, out, err = run(capsys, "recover", damaged, out_path)
    assert code == 0 and err == ""
    assert f"total: kept {len(readable)} messages, lost {in_bad_chunk} " in out
    assert "damage: " in out
    # The new file is complete: the mcap library finds its summary, and it reads without damage.
    truth = mcap_truth(out_path)
    assert truth["count"] == len(readable) and truth["compression"] == {"zstd"}
    with BagReader(out_path) as reader:
        assert reader.damage is None
        assert [(m.topic, m.log_time_ns, m.data) for m in reader.messages()] == readable
        assert reader.topics["/fast"].msgtype == "std_msgs/msg/Float32"
    with BagReader(path) as original, BagReader(out_path) as copy:
        for name, info in original.topics.items():
            assert copy.topics[name].type_description_hash == info.type_description_hash
        assert copy.definitions() == original.definitions()


def test_recover_of_an_intact_bag_is_a_faithful_copy(tmp_path):
    path = tmp_path / "dir_bag"
    written = write_streams(path, compression="lz4", chunk_size=250, split_size_bytes=1_200)
    report = recover(path, tmp_path / "copy.mcap")
    assert report.damage is None and report.lost_total == 0
    assert report.kept_total == len(written)
    with BagReader(tmp_path / "copy.mcap") as reader:
        assert [(m.topic, m.log_time_ns, m.data) for m in reader.messages()] == written
        assert reader.chunk_stats.compression.keys() == {"lz4"}
    shutil.rmtree(path)
    with pytest.raises(Exception, match="no such bag"):
        reindex(path)
