"""endo-process on bad input: one line and exit 2, a cut bag to the cut, no poses, signals."""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import json
import os
import pty
import re
import signal
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from endo_io import topics
from endo_io.bag import BagReader, BagWriter
from endo_process.cli import EXIT_DAMAGED, EXIT_INPUT, EXIT_INTERRUPTED, EXIT_OK, main
from endo_process.runner import ProcessOptions, process_bag

from .conftest import BAGS, PHANTOM
from .test_phantom_run import read_ply_vertices


def _subset(path: Path, keep: set[str], images: int, tracker_until_s: float = 1e9) -> Path:
    """The phantom's first ``images`` frames (and what goes with them) on the ``keep`` topics."""
    with BagReader(PHANTOM) as reader, BagWriter(path) as writer:
        start = reader.time_range_ns[0]  # type: ignore[index]
        seen = 0
        for name in sorted(keep & set(reader.topics)):
            writer.add_topic(name, reader.topics[name].msgtype)
        for message in reader.messages(sorted(keep)):
            if message.topic == topics.IMAGE_RAW:
                seen += 1
                if seen > images:
                    break
            if message.topic == topics.TRACKER_POSE and (
                message.log_time_ns - start > tracker_until_s * 1e9
            ):
                continue
            writer.write(message.topic, message.data, message.log_time_ns)
    return path


ALL = {topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE}


def _argv(bag: Path, out: Path, calibrations: tuple[Path, Path], *extra: str) -> list[str]:
    return [str(bag), "-o", str(out), "--calibration", str(calibrations[0]),
            "--handeye", str(calibrations[1]), "--solve-scale", "0.5", "--jobs", "1", "-q",
            *extra]  # fmt: skip


@pytest.mark.parametrize("missing", [topics.TRACKER_POSE, topics.IMAGE_RAW, topics.CAMERA_INFO])
def test_a_missing_topic_is_one_line_naming_it_and_exit_2(
    missing: str, calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    bag = _subset(tmp_path / "cut.mcap", ALL - {missing}, images=2)
    out = tmp_path / "out.mcap"
    assert main(_argv(bag, out, calibrations)) == EXIT_INPUT
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and missing in error, error
    assert not out.exists()


def _retyped(path: Path, topic: str) -> Path:
    """The phantom's first 2 frames with ``topic`` recorded as std_msgs/String."""
    from std_msgs.msg import String

    from endo_io.bag import serialize

    source = _subset(path.with_suffix(".src.mcap"), ALL, images=2)
    with BagReader(source) as reader, BagWriter(path) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, "std_msgs/msg/String" if name == topic else info.msgtype)
        for message in reader.messages():
            data = serialize(String(data="x")) if message.topic == topic else message.data
            writer.write(message.topic, data, message.log_time_ns)
    return path


@pytest.mark.parametrize("topic", [topics.TRACKER_POSE, topics.IMAGE_RAW, topics.CAMERA_INFO])
def test_a_topic_of_another_type_is_one_line_naming_it_and_exit_2(
    topic: str, calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # It used to end in an AttributeError traceback ('String' object has no attribute 'header').
    bag = _retyped(tmp_path / "retyped.mcap", topic)
    out = tmp_path / "out.mcap"
    assert main(_argv(bag, out, calibrations)) == EXIT_INPUT
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1, error
    assert f"TopicTypeError: {bag}: {topic} holds std_msgs/msg/String, not " in error, error
    assert not out.exists()


def test_camera_info_from_a_yaml_replaces_the_topic(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    bag = _subset(tmp_path / "noinfo.mcap", ALL - {topics.CAMERA_INFO}, images=2)
    out = tmp_path / "out.mcap"
    camera = BAGS / "phantom_colon.camera.yaml"
    assert main(_argv(bag, out, calibrations, "--camera-info", str(camera))) == EXIT_OK
    with BagReader(out) as reader:
        assert reader.topics[topics.CAMERA_INFO].message_count == 2
        assert reader.topics[topics.DEPTH_RELATIVE].message_count == 2


def test_a_missing_file_is_one_line_and_exit_2(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    argv = _argv(PHANTOM, tmp_path / "out.mcap", (tmp_path / "nope.yaml", calibrations[1]))
    assert main(argv) == EXIT_INPUT
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "nope.yaml" in error


def test_a_truncated_bag_is_processed_up_to_the_cut(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    data = PHANTOM.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 5])  # the first ~18 frames' chunks
    out = tmp_path / "out.mcap"
    assert main(_argv(cut, out, calibrations)) == EXIT_DAMAGED
    captured = capsys.readouterr()
    assert "cut short" in captured.err and "cut.mcap" in captured.err
    with BagReader(out) as reader:  # a complete file: reading it raises nothing
        depth = reader.topics[topics.DEPTH_RELATIVE].message_count
        assert sum(1 for _ in reader.messages([topics.DEPTH_RELATIVE])) == depth
    with BagReader(cut) as reader:
        readable = sum(1 for m in _intact(reader) if m.topic == topics.IMAGE_RAW)
    assert 5 <= depth == readable < 90
    # --max-frames short of the cut does not meet it: exit 0, and a note, not "cut short"
    out = tmp_path / "out3.mcap"
    assert main(_argv(cut, out, calibrations, "--max-frames", "3")) == EXIT_OK
    err = capsys.readouterr().err
    assert "cut short" not in err, err
    assert "note: the input is damaged after the 3 images read (--max-frames): " in err, err


def test_a_cut_is_in_the_summary_as_everything_after_the_last_message_read(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    data = PHANTOM.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 5])
    summary = tmp_path / "summary.json"
    argv = _argv(cut, tmp_path / "out.mcap", calibrations, "--summary-json", str(summary))
    assert main(argv) == EXIT_DAMAGED
    err = capsys.readouterr().err
    assert "endo-process: input cut short, processed up to the damage: " in err, err
    with BagReader(cut) as reader:
        last = max(m.log_time_ns for m in _intact(reader))
        start = reader.time_range_ns[0]  # type: ignore[index]
    document = json.loads(summary.read_text())
    (damage,) = document["input_damage"]
    assert damage["where"] == "end" and damage["lost"] == "rest"
    assert damage["log_time_start_ns"] == last and damage["log_time_end_ns"] is None
    assert damage["start_s"] == pytest.approx((last - start) / 1e9)
    assert damage["file"] == str(cut) and f"at byte {damage['byte']} of" in document["damage"]
    assert document["damage_after_max_frames"] is None


def _corrupt_chunk(target: Path, chunk: int) -> tuple[int, int, int]:
    """The phantom with 16 flipped bytes in the middle of its ``chunk``-th chunk (a whole file).

    Returns the chunk's byte offset and the first and last log time of its messages.
    """
    with PHANTOM.open("rb") as stream:
        index = make_reader(stream).get_summary().chunk_indexes[chunk]  # type: ignore[union-attr]
    raw = bytearray(PHANTOM.read_bytes())
    middle = index.chunk_start_offset + index.chunk_length // 2
    raw[middle : middle + 16] = bytes(b ^ 0x5A for b in raw[middle : middle + 16])
    target.write_bytes(bytes(raw))
    return index.chunk_start_offset, index.message_start_time, index.message_end_time


@pytest.fixture(scope="module")
def lost_chunk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, int, int]:
    """The phantom, its fifth chunk corrupt (frames 14-17): bag, offset, first and last log time."""
    bag = tmp_path_factory.mktemp("lost_chunk") / "lost_chunk.mcap"
    return bag, *_corrupt_chunk(bag, 4)


# Review of session 15: a chunk lost inside the first --max-frames frames went unsaid (exit 0),
# and without --max-frames the same bag said "input cut short" though every frame after the
# lost chunk was processed.
@pytest.mark.parametrize("max_frames", [None, 20])
def test_a_chunk_lost_inside_the_frames_processed_is_named_with_its_log_times(
    max_frames: int | None,
    lost_chunk: tuple[Path, int, int, int],
    calibrations: tuple[Path, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture,
) -> None:
    bag, offset, first_ns, last_ns = lost_chunk
    with BagReader(bag) as reader:
        readable = sum(1 for m in _intact(reader) if m.topic == topics.IMAGE_RAW)
        origin = reader.time_range_ns[0]  # type: ignore[index]
    assert readable == 86  # the chunk held 4 of the 90 images
    frames = readable if max_frames is None else max_frames
    summary = tmp_path / "summary.json"
    extra = [] if max_frames is None else ["--max-frames", str(max_frames)]
    argv = _argv(bag, tmp_path / "out.mcap", calibrations, "--summary-json", str(summary), *extra)
    assert main(argv) == EXIT_DAMAGED
    err = capsys.readouterr().err
    assert "cut short" not in err and "note:" not in err, err
    span = f"{(first_ns - origin) / 1e9:.3f} s to {(last_ns - origin) / 1e9:.3f} s"
    assert (f"endo-process: error: the input lost messages that the {frames} images read needed "
            f"(logged {span} into the recording, 4 images by the file's index): {bag}: "
            f"truncated or corrupt at byte {offset} of ") in err, err
    document = json.loads(summary.read_text())
    assert document["frames"]["read"] == frames
    assert document["frames"]["with_relative_depth"] == frames
    (damage,) = document["input_damage"]
    assert damage["where"] == "inside" and damage["lost"] == "span"
    assert damage["byte"] == offset and damage["images_lost"] == 4
    assert (damage["log_time_start_ns"], damage["log_time_end_ns"]) == (first_ns, last_ns)
    assert damage["lost_messages"][topics.IMAGE_RAW] == 4
    assert f"at byte {offset} of" in document["damage"]
    assert document["damage_after_max_frames"] is None
    with BagReader(tmp_path / "out.mcap") as reader:  # the frames on both sides of the loss
        stamps = [m.log_time_ns for m in reader.messages([topics.DEPTH_RELATIVE])]
    assert len(stamps) == frames
    gaps = [round((b - a) * 30 / 1e9, 3) for a, b in itertools.pairwise(stamps)]
    assert gaps == [1.0] * 12 + [5.0] + [1.0] * (frames - 14)  # frames 14-17 are missing


def test_a_chunk_lost_right_after_the_frames_max_frames_processed_is_what_they_needed(
    lost_chunk: tuple[Path, int, int, int],
    calibrations: tuple[Path, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture,
) -> None:
    # Review, session 16: the lost chunk starts with the 13th frame's camera_info and holds
    # the tracker samples after it, so the 13th frame lost its pose; the run called the
    # damage "after the 13 frames processed" and exited 0.
    bag, offset, first_ns, _ = lost_chunk
    summary = tmp_path / "summary.json"
    # the 13 frames before the lost chunk: the run reads on to the next image, past the chunk
    argv = _argv(bag, tmp_path / "out.mcap", calibrations, "--summary-json", str(summary),
                 "--max-frames", "13")  # fmt: skip
    assert main(argv) == EXIT_DAMAGED
    err = capsys.readouterr().err
    assert "note:" not in err and "cut short" not in err, err
    assert ("endo-process: error: the input lost messages that the 13 images read needed "
            "(logged ") in err, err
    document = json.loads(summary.read_text())
    (damage,) = document["input_damage"]
    assert damage["where"] == "inside" and damage["log_time_start_ns"] == first_ns
    assert f"at byte {offset} of" in document["damage"]
    assert document["damage_after_max_frames"] is None


def _intact(reader: BagReader):  # type: ignore[no-untyped-def]
    try:
        yield from reader.messages()
    except Exception:
        return


def test_frames_without_a_pose_are_counted_and_skipped(
    calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    bag = _subset(tmp_path / "nopose.mcap", ALL, images=12, tracker_until_s=0.2)
    report = process_bag(ProcessOptions(
        bag=bag, output=tmp_path / "out.mcap", calibration=calibrations[0],
        handeye=calibrations[1], solve_scale=0.5, jobs=1, progress=False,
    ))  # fmt: skip
    # Tracker poses cover 0.2 s of the 0.4 s; their camera-clock stamps are 25 ms earlier.
    assert report.frames_shaded == 12
    assert report.frames_with_pose + sum(report.without_pose.values()) == 12
    assert 4 <= report.frames_with_pose <= 7
    assert report.without_pose["PoseNotYetError"] >= 5


def test_a_tracker_in_millimetres_read_as_metres_is_named_and_set_by_ros_unit(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # an NDI driver's PoseStamped in mm, processed with the bridge's default ros_unit m
    from endo_io.bag import deserialize, serialize

    source = _subset(tmp_path / "m.mcap", ALL, images=4)
    bag = tmp_path / "mm.mcap"
    with BagReader(source) as reader, BagWriter(bag) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        for message in reader.messages():
            data = message.data
            if message.topic == topics.TRACKER_POSE:
                pose = deserialize(message)
                position = pose.pose.position
                position.x, position.y, position.z = (1e3 * position.x, 1e3 * position.y,
                                                      1e3 * position.z)  # fmt: skip
                data = serialize(pose)
            writer.write(message.topic, data, message.log_time_ns)
    assert main(_argv(bag, tmp_path / "out.mcap", calibrations)) == EXIT_OK
    err = capsys.readouterr().err
    assert "millimetres read as metres? (the bridge's ros_unit" in err, err
    assert "none of the 4 frames with a relative depth had a camera pose" in err, err
    params = tmp_path / "mm.yaml"
    params.write_text("/**/tracker_bridge:\n  ros__parameters:\n    ros_unit: mm\n")
    assert main(_argv(bag, tmp_path / "out2.mcap", calibrations, "--params", str(params))) == 0
    err = capsys.readouterr().err
    assert "millimetres" not in err and "camera pose" not in err, err


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_finalises_the_output(
    signum: int, calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    out = tmp_path / "out.mcap"
    command = [sys.executable, "-m", "endo_process.cli",
               *_argv(PHANTOM, out, calibrations)[:-1], "--solve-scale", "1"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=dict(os.environ))  # fmt: skip
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out.exists() and out.stat().st_size > 1 << 20):
        time.sleep(0.2)  # the first frames are written
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == EXIT_INTERRUPTED, stderr
    assert "interrupted" in stderr
    assert "frame/s" not in stderr  # without -q, but stderr is a pipe: no progress bar
    with BagReader(out) as reader:
        assert reader.damage is None
        frames = reader.topics[topics.DEPTH_RELATIVE].message_count
        assert sum(1 for _ in reader.messages([topics.DEPTH_RELATIVE])) == frames
    assert 1 <= frames < 90


def test_frames_in_flight_at_an_interrupt_are_counted_in_the_summary(
    calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    # With worker processes, up to 16 frames are read and in the workers when Ctrl-C comes:
    # the summary counted them nowhere (images read 33, with a relative depth 18, none dropped).
    out, summary = tmp_path / "out.mcap", tmp_path / "summary.json"
    argv = _argv(PHANTOM, out, calibrations, "--summary-json", str(summary))
    jobs = argv.index("--jobs")
    argv[jobs + 1] = "2"
    command = [sys.executable, "-m", "endo_process.cli", *argv, "--solve-scale", "1"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=dict(os.environ))  # fmt: skip
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (out.exists() and out.stat().st_size > 1 << 20):
        time.sleep(0.2)  # the first frames are written
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == EXIT_INTERRUPTED, stderr
    frames = json.loads(summary.read_text())["frames"]
    in_flight = frames["in_flight_not_written"]
    assert frames["dropped"] == {} and frames["read"] < 90, frames
    assert in_flight > 0 and frames["read"] == frames["with_relative_depth"] + in_flight
    assert (f"interrupted; {out} holds the {frames['with_relative_depth']} frames processed; "
            f"{in_flight} frames in flight at the interrupt were not written") in stderr, stderr
    row = re.search(r"^frames in flight at the stop, not written +(\d+)$", stdout, re.MULTILINE)
    assert row is not None and int(row.group(1)) == in_flight, stdout
    with BagReader(out) as reader:
        assert reader.topics[topics.DEPTH_RELATIVE].message_count == frames["with_relative_depth"]


def test_the_progress_bar_shows_on_a_terminal_only(
    calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    bag = _subset(tmp_path / "short.mcap", ALL, images=3)
    argv = [sys.executable, "-m", "endo_process.cli",
            *_argv(bag, tmp_path / "tty.mcap", calibrations)[:-1]]  # without --quiet
    main_fd, terminal = pty.openpty()
    # A real terminal's size (a fresh pty is 0 columns wide: tqdm would draw nothing).
    fcntl.ioctl(terminal, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    with os.fdopen(main_fd, "rb", buffering=0) as reader:
        process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=terminal)
        os.close(terminal)
        chunks = []
        with contextlib.suppress(OSError):  # EIO once the child closed the terminal
            while chunk := reader.read(4096):
                chunks.append(chunk)
        assert process.wait(timeout=120) == EXIT_OK
    shown = b"".join(chunks).decode(errors="replace")
    assert "endo-process" in shown and "3/3" in shown and "frame/s" in shown, shown
    # Not a terminal (a pipe): no bar at all (test_a_signal_finalises_the_output).


def _with_garbage(path: Path, topic: str, every: int) -> tuple[Path, int]:
    """The phantom's first 6 frames with every ``every``-th message of ``topic`` undecodable.

    Returns the bag and how many messages were made undecodable.
    """
    source = _subset(path.with_suffix(".src.mcap"), ALL, images=6)
    with BagReader(source) as reader, BagWriter(path) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        seen = spoilt = 0
        for message in reader.messages():
            data = message.data
            if message.topic == topic:
                seen += 1
                if seen % every == 0:
                    data, spoilt = b"\x00\x01\x00\x00garbage", spoilt + 1
            writer.write(message.topic, data, message.log_time_ns)
    return path, spoilt


@pytest.mark.parametrize(("topic", "every"), [(topics.IMAGE_RAW, 3), (topics.TRACKER_POSE, 1)])
def test_undecodable_messages_are_skipped_counted_and_named(
    topic: str, every: int, calibrations: tuple[Path, Path], tmp_path: Path,
    capsys: pytest.CaptureFixture,
) -> None:
    # One undecodable message used to end the run with exit 2 (and, on the tracker topic,
    # a 40-byte output without a footer that no reader opens).
    bag, skipped = _with_garbage(tmp_path / "garbage.mcap", topic, every)
    assert skipped == (2 if topic == topics.IMAGE_RAW else 11)
    out = tmp_path / "out.mcap"
    assert main(_argv(bag, out, calibrations)) == EXIT_DAMAGED
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1, errors
    assert f"skipped {skipped} on {topic}, undecodable; the first: " in errors[0], errors
    with BagReader(out) as reader:
        assert reader.damage is None
        depth = sum(1 for _ in reader.messages([topics.DEPTH_RELATIVE]))
    assert depth == (6 - skipped if topic == topics.IMAGE_RAW else 6)


def test_each_cause_of_dropped_frames_is_one_line_with_its_message(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # A 3-channel recording against the sample's mono calibration: every frame dropped. The
    # table counted "3 CalibrationMismatchError" and the run exited 0 without saying why.
    import numpy as np

    from endo_io.bag import deserialize, serialize

    source = _subset(tmp_path / "mono.mcap", ALL, images=3)
    bag = tmp_path / "bgr.mcap"
    with BagReader(source) as reader, BagWriter(bag) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        for message in reader.messages():
            data = message.data
            if message.topic == topics.IMAGE_RAW:
                image = deserialize(message)
                mono = np.frombuffer(bytes(image.data), np.uint8)
                image.encoding, image.step = "bgr8", image.width * 3
                image.data = np.repeat(mono, 3).tobytes()
                data = serialize(image)
            writer.write(message.topic, data, message.log_time_ns)
    out = tmp_path / "out.mcap"
    assert main(_argv(bag, out, calibrations)) == EXIT_DAMAGED
    lines = capsys.readouterr().err.splitlines()
    dropped = [line for line in lines if "frames dropped" in line]
    assert len(dropped) == 1, lines
    warning = "endo-process: warning: 3 frames dropped, CalibrationMismatchError: "
    assert dropped[0].startswith(warning), dropped
    assert dropped[0].endswith(", 3) does not fit a mono calibration; the stream is colour and"
                               " the calibration mono: fit one on this camera's colour gray-card"
                               " images (endo-calibrate keeps their red, green and blue)"), dropped
    assert lines[-1] == ("endo-process: error: none of the 3 frames read gave a relative depth "
                         "(the causes above)")  # fmt: skip


@pytest.mark.parametrize(("extra", "error"), [
    (("--max-frames", "-3"), "Endo3dError: --max-frames must be >= 1, got -3"),
    (("--solve-scale", "0"), "ParameterFileError: the nodes' defaults with --solve-scale 0: sfs: "
     "solve_scale must be in (0, 1], got 0.0"),
])  # fmt: skip
def test_options_out_of_range_are_one_line_and_exit_2(
    extra: tuple[str, ...], error: str, calibrations: tuple[Path, Path], tmp_path: Path,
    capsys: pytest.CaptureFixture,
) -> None:
    # --max-frames -3 used to run nothing and exit 0; --solve-scale 0 named the file "None".
    out = tmp_path / "out.mcap"
    assert main(_argv(PHANTOM, out, calibrations, *extra)) == EXIT_INPUT
    assert capsys.readouterr().err.strip() == f"endo-process: {error}"
    assert not out.exists()


def test_overwrite_keeps_the_old_output_when_an_input_is_bad(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # --overwrite used to delete the old output before the inputs were read: a wrong
    # --calibration (here the hand-eye file) cost the previous run's result.
    out = tmp_path / "out.mcap"
    out.write_bytes(b"the previous run")
    argv = _argv(PHANTOM, out, (calibrations[1], calibrations[1]), "--overwrite")
    assert main(argv) == EXIT_INPUT
    assert "is not an endo3d photometric calibration" in capsys.readouterr().err
    assert out.read_bytes() == b"the previous run"


@pytest.mark.parametrize("option", ["--report", "--summary-json", "--ply", "-o"])
def test_an_output_path_in_a_missing_directory_is_refused_before_the_run(
    option: str, calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # --report there ended the run in a FileNotFoundError traceback after every frame; --ply
    # there ended it with exit 2 after every frame, the output MCAP left without its footer
    # (the PLY is now also written after the output is finalised).
    bag = _subset(tmp_path / "short.mcap", ALL, images=2)
    out, missing = tmp_path / "out.mcap", tmp_path / "nowhere" / "file.mcap"
    argv = _argv(bag, missing if option == "-o" else out, calibrations)
    if option != "-o":
        argv += [option, str(missing)]
    assert main(argv) == EXIT_INPUT
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and f"{missing}: parent directory does not exist" in error
    assert not out.exists()


def test_a_directory_as_output_is_one_line_and_exit_2(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # With --overwrite it was an IsADirectoryError traceback.
    argv = _argv(PHANTOM, tmp_path, calibrations, "--overwrite")
    assert main(argv) == EXIT_INPUT
    error = capsys.readouterr().err.strip()
    assert error == (
        f"endo-process: Endo3dError: {tmp_path} is a directory (-o names a new bag: "
        f"{tmp_path}.mcap, or a directory that does not exist yet)"
    )


@pytest.mark.parametrize("option", ["--params", "--handeye", "--camera-info"])
def test_a_file_that_is_not_yaml_is_one_line_naming_where(
    option: str, calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # PyYAML's error text spans five lines (context, the line, a caret); it was printed whole.
    broken = tmp_path / "broken.yaml"
    broken.write_text("a: [1, 2\n")
    handeye = broken if option == "--handeye" else calibrations[1]
    argv = _argv(PHANTOM, tmp_path / "out.mcap", (calibrations[0], handeye))
    if option != "--handeye":
        argv += [option, str(broken)]
    assert main(argv) == EXIT_INPUT
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1, error
    assert error.endswith(
        "line 2, column 1: expected ',' or ']', but got '<stream end>' (while parsing a flow "
        "sequence)" + (")" if option != "--handeye" else "")
    ), error


def test_stamps_going_back_are_named_counted_and_one_line_each(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # An image stamped 2 s back was dropped as 'NoCameraInfoError: no camera_info at or
    # before the image stamped ...' (the camera_info stream had moved past it), and a
    # tracker pose stamped 2 s back reset the pose buffer (ClockJumpError) without a line.
    from endo_io.bag import deserialize, serialize
    from endo_io.stamp import ns_to_stamp, stamp_to_ns

    source = _subset(tmp_path / "src.mcap", ALL, images=6)
    bag = tmp_path / "back.mcap"
    back_ns = 2_000_000_000
    image_stamps: list[int] = []
    seen = {topics.IMAGE_RAW: 0, topics.TRACKER_POSE: 0}
    with BagReader(source) as reader, BagWriter(bag) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        for message in reader.messages():
            data = message.data
            if message.topic in seen:
                seen[message.topic] += 1
                decoded = deserialize(message)
                stamp = stamp_to_ns(decoded.header.stamp)
                if (message.topic, seen[message.topic]) in {(topics.IMAGE_RAW, 4),
                                                            (topics.TRACKER_POSE, 5)}:
                    stamp -= back_ns
                    decoded.header.stamp = ns_to_stamp(stamp)
                    data = serialize(decoded)
                if message.topic == topics.IMAGE_RAW:
                    image_stamps.append(stamp)
            writer.write(message.topic, data, message.log_time_ns)
    assert main(_argv(bag, tmp_path / "out.mcap", calibrations)) == EXIT_OK
    lines = capsys.readouterr().err.strip().splitlines()
    newest, back = image_stamps[2], image_stamps[3]
    assert (
        f"endo-process: warning: 1 frames dropped, ImageStampBackError: image stamp went back "
        f"{(newest - back) / 1e9:.3f} s, from {newest} to {back} ns (a clock jump, or frames "
        "out of order)"
    ) in lines, lines
    jumps = [line for line in lines if "pose buffer, ClockJumpError" in line]
    assert len(jumps) == 1, lines
    assert jumps[0].startswith(
        "endo-process: warning: 1 poses refused or reset by the pose buffer, ClockJumpError: "
        "pose time jumped back 1.98"
    ) and jumps[0].endswith("ns); pose buffer reset"), jumps
    assert not any("NoCameraInfoError" in line for line in lines), lines


def test_a_full_disk_stops_the_run_with_the_summary_and_a_readable_output(
    calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    # It was exit 2 with one BagError line and no summary. A file size limit
    # stands in for a full disk (EFBIG as ENOSPC: a short write, then an error).
    import re
    import resource

    limit = 12_000_000

    def limited() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = tmp_path / "out.mcap"
    argv = _argv(PHANTOM, out, calibrations, "--max-frames", "12")
    done = subprocess.run([str(Path(sys.executable).parent / "endo-process"), *argv],
                          capture_output=True, text=True, timeout=300, preexec_fn=limited,
                          check=False)  # fmt: skip
    assert done.returncode == EXIT_DAMAGED, done.stderr
    errors = done.stderr.strip().splitlines()
    assert len(errors) == 1, errors
    assert re.fullmatch(
        rf"endo-process: error: writing stopped after \d+ of 90 frames: {re.escape(str(out))}: "
        r"cannot write \(file size limit: File too large\); the bag holds the \d+ messages "
        r"written before, \d+ not yet on disk are lost", errors[0]
    ), errors[0]
    assert "endo-process summary" in done.stdout and "output write failed" in done.stdout
    said = re.search(r"output\s+\S+ \((\d+) messages\)", done.stdout)
    assert said is not None, done.stdout
    from endo_io.bag import BagCorruptError

    held: dict[str, int] = {}
    # what was written reads back, every message counted (BagCorruptError after the last)
    with BagReader(out) as reader, contextlib.suppress(BagCorruptError):
        for message in reader.messages():
            held[message.topic] = held.get(message.topic, 0) + 1
    assert sum(held.values()) == int(said.group(1)) and held[topics.DEPTH_RELATIVE] >= 1
    assert out.stat().st_size <= limit


@pytest.mark.parametrize(("limit", "frames"), [(12_000_000, 12), (60_000_000, 60)])
def test_a_full_disk_still_writes_the_ply_from_the_map_in_memory(
    calibrations: tuple[Path, Path], tmp_path: Path, limit: int, frames: int
) -> None:
    # The review: after a failed output write, --ply was not even tried, though it may
    # name another disk and the map is in memory. Here the same file size limit applies
    # to the PLY, which is smaller than it.
    import re
    import resource

    def limited() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out, ply = tmp_path / "out.mcap", tmp_path / "map.ply"
    argv = _argv(PHANTOM, out, calibrations, "--max-frames", str(frames), "--ply", str(ply))
    done = subprocess.run([str(Path(sys.executable).parent / "endo-process"), *argv],
                          capture_output=True, text=True, timeout=300, preexec_fn=limited,
                          check=False)  # fmt: skip
    assert done.returncode == EXIT_DAMAGED, done.stderr
    error = done.stderr.strip().splitlines()[-1]
    assert "writing stopped after" in error, error
    written = re.search(r"--ply \S+ written from the map in memory \((\d+) vertices", error)
    if limit > 50_000_000:  # past the frames the map fuses first: a map to write
        assert written is not None, error
    if written is not None:
        assert len(read_ply_vertices(ply)) == int(written.group(1)) > 1000
    else:
        assert error.endswith(f"--ply {ply} not written (the map was empty)"), error
        assert not ply.exists()


def test_an_output_name_without_mcap_is_a_rosbag2_directory(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # What `ros2 bag record -o NAME` makes: NAME/NAME_0.mcap and metadata.yaml (--help says so).
    import yaml

    out = tmp_path / "run"
    assert main(_argv(PHANTOM, out, calibrations, "--max-frames", "2")) == EXIT_OK
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "run_0.mcap"]
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == ["run_0.mcap"]
    with BagReader(out) as reader:
        assert reader.topics[topics.DEPTH_RELATIVE].message_count == 2
        assert info["message_count"] == sum(t.message_count for t in reader.topics.values())
    assert f"{out} (" in capsys.readouterr().out  # the summary's output row


def test_a_summary_json_that_cannot_be_written_is_not_a_failure_of_the_output(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # The review: it set the output's write failure, so the run then said "writing stopped
    # after 2 of 2 frames ...; --ply not written" of a complete output.
    bag = _subset(tmp_path / "short.mcap", ALL, images=2)
    out = tmp_path / "out.mcap"
    argv = _argv(bag, out, calibrations, "--summary-json", "/proc/version", "--overwrite")
    assert main(argv) == 1
    error = capsys.readouterr().err
    assert "cannot write /proc/version" in error
    assert "writing stopped" not in error and "not written" not in error
    assert out.exists() and out.stat().st_size > 0


def test_a_ply_that_cannot_be_written_after_a_full_disk_is_reported_not_raised(
    tmp_path: Path,
) -> None:
    # Review, session 13: write_ply's MapExportError escaped _export_ply after a full
    # disk (--ply on the same disk), and the run lost its summary and exit status.
    from types import SimpleNamespace

    import numpy as np

    from endo_flow.voxel_map import VoxelMap
    from endo_process.runner import ProcessReport, _export_ply

    voxel_map = VoxelMap(1e-3)
    voxel_map.insert(np.random.default_rng(0).uniform(0.0, 0.05, (1000, 3)), np.zeros(1000))
    flow = SimpleNamespace(pipeline=SimpleNamespace(voxel_map=voxel_map))
    ply = tmp_path / "missing_dir" / "map.ply"
    report = ProcessReport()
    report.write_failure = "out.mcap: cannot write (disk full)"
    _export_ply(flow, SimpleNamespace(ply=ply), report)  # type: ignore[arg-type]
    assert report.ply_vertices == 0 and f"cannot write {ply}" in report.ply_error
    assert not ply.exists()


def test_a_ply_that_cannot_be_written_or_has_nothing_costs_only_itself(
    calibrations: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # A probe, session 15: `--ply /unwritable/map.ply` after 40 frames ended in
    # "MapExportError: cannot write ..." with exit 2 and no summary; `--ply` of a run
    # whose map stayed empty wrote nothing and said nothing.
    from types import SimpleNamespace

    import numpy as np

    from endo_flow.voxel_map import VoxelMap
    from endo_process.runner import ProcessReport, _export_ply

    voxel_map = VoxelMap(1e-3)
    voxel_map.insert(np.random.default_rng(0).uniform(0.0, 0.05, (1000, 3)), np.zeros(1000))
    flow = SimpleNamespace(pipeline=SimpleNamespace(voxel_map=voxel_map))
    ply = tmp_path / "missing_dir" / "map.ply"  # as a directory removed during the run
    report = ProcessReport(map_points=len(voxel_map))
    _export_ply(flow, SimpleNamespace(ply=ply), report)  # type: ignore[arg-type]
    assert report.ply_vertices == 0 and f"cannot write {ply}" in report.ply_error
    empty = SimpleNamespace(pipeline=SimpleNamespace(voxel_map=VoxelMap(1e-3)))
    report = ProcessReport()
    _export_ply(empty, SimpleNamespace(ply=ply), report)  # type: ignore[arg-type]
    assert report.ply_error == "the map was empty"
    # the command: 3 frames make no map; the summary says so, a warning line too, exit 0
    ply = tmp_path / "map.ply"
    argv = _argv(PHANTOM, tmp_path / "out.mcap", calibrations, "--max-frames", "3",
                 "--ply", str(ply))  # fmt: skip
    assert main(argv) == EXIT_OK
    captured = capsys.readouterr()
    assert "PLY                    " in captured.out and "not written (the map was empty)" in (
        captured.out)
    assert f"endo-process: warning: --ply {ply} not written (the map was empty)" in captured.err
    assert not ply.exists()


def test_real_time_of_a_re_recorded_loop_counts_the_recording_not_its_stamps(
    calibrations: tuple[Path, Path], tmp_path: Path
) -> None:
    # Probe, session 16: a looping replay re-recorded (endo-replay --loop beside endo-record)
    # has stamps that go back at each loop; the stamps' span gave "0.04x real time" for a
    # run at ~0.8x. Two passes of the phantom's first 30 frames, logged one after the other.
    one = _subset(tmp_path / "one.mcap", ALL, images=30)
    bag = tmp_path / "looped.mcap"
    with BagReader(one) as reader, BagWriter(bag) as writer:
        first, last = reader.time_range_ns  # type: ignore[misc]
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        for loop in range(2):
            for message in reader.messages():
                writer.write(message.topic, message.data,
                             message.log_time_ns + loop * (last - first + 33_333_333))
    summary = tmp_path / "summary.json"
    assert main(_argv(bag, tmp_path / "out.mcap", calibrations, "--summary-json",
                      str(summary))) in (EXIT_OK, EXIT_DAMAGED)  # fmt: skip
    document = json.loads(summary.read_text())
    assert document["frames"]["read"] == 60
    with BagReader(bag) as reader:
        logged = [m.log_time_ns for m in reader.messages([topics.IMAGE_RAW])]
    # the 60 images' log times span ~2 s of recording (plus one frame), whatever the stamps did
    covered = (logged[-1] - logged[0]) * 60 / 59 / 1e9
    assert covered > 1.9
    assert document["speed"]["recording_seconds"] == pytest.approx(covered, rel=1e-9)
