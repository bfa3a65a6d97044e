"""The output's writer thread: calls reach the bag in order, and a writer error is raised."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from endo_io.bag import BagError, BagReader, BagWriter, deserialize
from endo_io.image import image_to_array
from endo_process.output import WRITE_QUEUE_CALLS, OutputBag


def test_writes_arrive_in_order_and_a_writer_error_is_raised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    output = OutputBag(tmp_path / "ok.mcap", "lz4")
    frames = [np.full((4, 5), k, np.float32) for k in range(3 * WRITE_QUEUE_CALLS)]
    for k, frame in enumerate(frames):
        output.write_image("/depth", frame, "32FC1", 1_000 + k, "optical")
    output.close()
    output.close()  # idempotent
    with BagReader(tmp_path / "ok.mcap") as reader:
        read = [image_to_array(deserialize(m)) for m in reader.messages(["/depth"])]
    assert len(read) == len(frames)
    assert all(np.array_equal(a, b) for a, b in zip(read, frames, strict=True))

    def full_disk(self: BagWriter, *args: object) -> None:
        raise BagError("no space left on device")

    failing = OutputBag(tmp_path / "fail.mcap", "lz4")
    monkeypatch.setattr(BagWriter, "write", full_disk)
    with pytest.raises(BagError, match="no space"):
        for k in range(3 * WRITE_QUEUE_CALLS):  # raised by a later call, once the thread met it
            failing.write_image("/depth", frames[0], "32FC1", 1_000 + k, "optical")
        failing.close()
    failing.close()  # the file closed; the error was raised already


@pytest.mark.parametrize("crcs", [False, True])
def test_chunk_crcs_only_when_asked_and_the_file_reads_back_the_same(
    tmp_path: Path, crcs: bool
) -> None:
    """endo-process stores no chunk CRCs by default (as rosbag2's MCAP writer); --chunk-crc does."""
    from endo_process.cli import build_parser
    from endo_process.runner import ProcessOptions

    assert ProcessOptions(Path("a"), Path("b"), Path("c"), Path("d")).chunk_crcs is False
    argv = ["in.mcap", "-o", "out.mcap", "--calibration", "p.yaml", "--handeye", "h.yaml"]
    assert build_parser().parse_args(argv).chunk_crc is False
    assert build_parser().parse_args([*argv, "--chunk-crc"]).chunk_crc is True
    # Nor compressed chunks (rosbag2's default too): lz4 and zstd on request.
    assert build_parser().parse_args(argv).compression == "none"
    assert build_parser().parse_args([*argv, "--compression", "lz4"]).compression == "lz4"

    for compression in ("lz4", "none"):
        _check_crcs(tmp_path / f"crc_{crcs}_{compression}.mcap", compression, crcs)


def _check_crcs(path: Path, compression: str, crcs: bool) -> None:
    """Write three images, check the chunks' CRCs are there exactly when asked, read them back."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    output = OutputBag(path, compression, crcs=crcs)
    frames = [np.linspace(0.0, 1.0, 640 * 480, dtype=np.float32).reshape(480, 640) * k
              for k in range(1, 4)]  # fmt: skip
    for k, frame in enumerate(frames):  # 1.2 MB each: a chunk per image
        output.write_image("/depth", frame, "32FC1", 1_000 + k, "optical")
    output.close()
    with path.open("rb") as stream:
        chunks = [r for r in StreamReader(stream, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) >= len(frames)
    assert all(chunk.compression == ("" if compression == "none" else compression)
               for chunk in chunks)  # fmt: skip
    assert all((chunk.uncompressed_crc != 0) == crcs for chunk in chunks)
    with BagReader(path) as reader:
        read = [image_to_array(deserialize(m)) for m in reader.messages(["/depth"])]
    assert all(np.array_equal(a, b) for a, b in zip(read, frames, strict=True))


def test_the_output_goes_past_the_page_cache_unless_told_not_to(tmp_path: Path) -> None:
    """--no-direct (review, session 14: slow or network storage) writes the same file."""
    from endo_process.cli import _options, build_parser
    from endo_process.runner import ProcessOptions

    assert ProcessOptions(Path("a"), Path("b"), Path("c"), Path("d")).direct is True
    for name in ("in.mcap", "p.yaml", "h.yaml"):
        (tmp_path / name).touch()
    argv = [str(tmp_path / "in.mcap"), "-o", str(tmp_path / "out.mcap"),
            "--calibration", str(tmp_path / "p.yaml"), "--handeye", str(tmp_path / "h.yaml")]
    assert _options(build_parser().parse_args(argv)).direct is True
    assert _options(build_parser().parse_args([*argv, "--no-direct"])).direct is False
    written = []
    for direct in (True, False):
        path = tmp_path / f"direct_{direct}.mcap"
        output = OutputBag(path, "none", crcs=False, direct=direct)
        for k in range(3):
            frame = np.linspace(0.0, k + 1.0, 640 * 480, dtype=np.float32).reshape(480, 640)
            output.write_image("/depth", frame, "32FC1", 1_000 + k, "optical")
        output.close()
        with BagReader(path) as reader:  # the same messages (the file's metadata holds times)
            assert reader.damage is None
            written.append([(m.topic, m.log_time_ns, bytes(m.data)) for m in reader.messages()])
    assert len(written[0]) == 3 and written[0] == written[1]


def test_jobs_1_solves_on_two_threads_unless_the_parameters_set_a_count() -> None:
    """--jobs 1's one chain has the process: the node's threads 0 is taken as 2 (review, s14)."""
    from endo_process.runner import one_chain_parameters

    assert one_chain_parameters({"threads": 0, "solve_scale": 0.5}) == {
        "threads": 2, "solve_scale": 0.5}
    assert one_chain_parameters({"solve_scale": 0.5})["threads"] == 2
    assert one_chain_parameters({"threads": 1})["threads"] == 1
    assert one_chain_parameters({"threads": 3})["threads"] == 3


def test_the_map_is_recorded_latched_so_that_a_replay_reaches_late_viewers(
    tmp_path: Path,
) -> None:
    """The map's offer is the flow node's (transient local); a replay publishes with it.

    Recorded without an offer, endo-replay published the map volatile, and
    endo-foxglove and the RViz config (transient-local subscriptions) got no map.
    """
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    from endo_io import topics
    from endo_io.bag.qos_yaml import qos_profiles_from_yaml
    from endo_io.pointcloud import xyz_to_pointcloud2
    from endo_io.replay import publisher_qos_for_topic

    xyz = np.arange(12, dtype=np.float32).reshape(4, 3) * 1e-3
    output = OutputBag(tmp_path / "map.mcap", "none")
    output.write_image(topics.DEPTH, np.ones((4, 5), np.float32), "32FC1", 1_000, "optical")
    output.write(topics.MAP, xyz_to_pointcloud2(xyz, 2_000, "world"), 2_000)
    output.close()
    with BagReader(tmp_path / "map.mcap") as reader:
        infos = reader.topics
    (offer,) = qos_profiles_from_yaml(infos[topics.MAP].offered_qos_profiles)
    assert offer.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert offer.reliability == ReliabilityPolicy.RELIABLE
    assert offer.depth == 1
    replayed, warning = publisher_qos_for_topic(
        topics.MAP, infos[topics.MAP].offered_qos_profiles, {}
    )
    assert (replayed.durability, replayed.reliability, warning) == (
        DurabilityPolicy.TRANSIENT_LOCAL, ReliabilityPolicy.RELIABLE, ""
    )
    # The other outputs keep rosbag2's default (reliable, volatile), as their publishers offer.
    assert infos[topics.DEPTH].offered_qos_profiles == ""
