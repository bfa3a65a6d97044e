"""Bag directories whose metadata.yaml disagrees with the files in them.

Issue 16: a metadata.yaml listing a file twice played 69 of 60 messages, one
omitting a file played 45 of 60, and neither said a word. Now each file is
read once, a file in the directory that metadata.yaml does not list is read
too, and each discrepancy is one warning line (``BagReader.warnings``, logged
by endo-replay, printed by endo-bag info).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from std_msgs.msg import Float32

from endo_io.bag import BagNotFoundError, BagReader, BagWriter
from endo_io.bag.metadata import read_metadata_yaml, write_metadata_yaml

T0 = 1_700_000_000_000_000_000
MESSAGES = 60


def write_split_bag(path: Path) -> list[tuple[int, bytes]]:
    with BagWriter(path, chunk_size=200, split_size_bytes=1_500) as writer:
        for i in range(MESSAGES):
            writer.write_message("/value", Float32(data=float(i)), T0 + i * 1_000_000)
    with BagReader(path) as reader:
        assert len(reader.files) >= 3, "the test needs a bag split into at least 3 files"
        return [(m.log_time_ns, m.data) for m in reader.messages()]


def edit_metadata(path: Path, **changes) -> None:
    metadata = read_metadata_yaml(path)
    metadata.update(changes)
    write_metadata_yaml(path, metadata)


def read(path: Path) -> tuple[list[tuple[int, bytes]], list[str]]:
    with BagReader(path) as reader:
        return [(m.log_time_ns, m.data) for m in reader.messages()], reader.warnings


@pytest.fixture
def split_bag(tmp_path: Path) -> tuple[Path, list[tuple[int, bytes]], list[str]]:
    path = tmp_path / "split"
    written = write_split_bag(path)
    assert len(written) == MESSAGES
    return path, written, read_metadata_yaml(path)["relative_file_paths"]


def test_an_intact_directory_reads_without_warnings(split_bag):
    path, written, _ = split_bag
    assert read(path) == (written, [])


def test_a_file_listed_twice_is_read_once_with_one_warning(split_bag):
    path, written, files = split_bag
    edit_metadata(path, relative_file_paths=[files[0], *files, files[0]])
    got, warnings = read(path)
    assert got == written  # 60, not 60 + two copies of the first file
    assert len(warnings) == 1
    assert files[0] in warnings[0] and "more than once" in warnings[0]
    with BagReader(path) as reader:
        assert reader.message_count == MESSAGES
        assert len(reader.files) == len(files)


def test_a_file_metadata_does_not_list_is_read_with_one_warning(split_bag):
    path, written, files = split_bag
    edit_metadata(path, relative_file_paths=files[:-1])
    got, warnings = read(path)
    assert got == written  # 60, not the 40-odd of the listed files
    assert len(warnings) == 1
    assert files[-1] in warnings[0] and "does not list" in warnings[0]
    assert "endo-bag reindex" in warnings[0]


def test_a_stale_message_count_is_one_warning(split_bag):
    path, written, _ = split_bag
    edit_metadata(path, message_count=0)  # what a SIGKILLed writer used to leave
    got, warnings = read(path)
    assert got == written
    assert warnings == [
        f"{path}/metadata.yaml counts 0 messages, the files hold {MESSAGES}: it is stale "
        f"(endo-bag reindex {path} rewrites it)"
    ]


def test_a_missing_listed_file_is_refused_naming_it(split_bag):
    path, _, files = split_bag
    (path / files[1]).unlink()
    with pytest.raises(BagNotFoundError, match=rf"{files[1]}.*endo-bag reindex"):
        BagReader(path)


def test_old_style_paths_with_the_directory_name_are_the_same_file(split_bag):
    path, written, files = split_bag
    edit_metadata(path, relative_file_paths=[f"{path.name}/{name}" for name in files] + files)
    got, warnings = read(path)
    assert got == written
    assert len(warnings) == 1 and "more than once" in warnings[0]


def test_metadata_yaml_written_by_the_writer_parses_as_rosbag2(split_bag):
    path, _, files = split_bag
    loaded = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert loaded["relative_file_paths"] == files
    assert loaded["message_count"] == MESSAGES
    assert sum(f["message_count"] for f in loaded["files"]) == MESSAGES


@pytest.mark.ros
def test_replay_of_a_directory_listing_a_file_twice_plays_each_message_once(
    split_bag, capfd, fresh_default_context
):
    from endo_io.replay_node import main

    path, _, files = split_bag
    edit_metadata(path, relative_file_paths=[*files, files[0]])
    assert main(["endo-replay", str(path), "--rate", "inf"]) == 0
    out = capfd.readouterr()
    assert f"total: {MESSAGES} messages" in out.out
    warning = [line for line in out.err.splitlines() if "more than once" in line]
    assert len(warning) == 1 and files[0] in warning[0]


@pytest.fixture
def fresh_default_context():
    """main() runs a node in this process; leave rclpy's default context reusable."""
    import rclpy

    yield
    rclpy.try_shutdown()
