"""endo-replay and endo-record as separate OS processes, talking only over DDS.

A small bag (images, camera info, poses, a scalar) is played by ``endo-replay``
in one process and recorded by ``endo-record`` in another; the recording must
equal the input message for message, byte for byte. Further tests kill the
recorder with SIGKILL (the file must still read up to its last flushed chunk)
and check ``--clock``. Every process gets loopback-only discovery and the test
run's ROS_DOMAIN_ID.
"""

from __future__ import annotations

import itertools
import os
import re
import resource
import signal
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float32

from endo_io.bag import BagMessage, BagReader, BagWriter, deserialize, serialize
from endo_io.bag.qos_yaml import qos_profiles_from_yaml, qos_profiles_to_yaml
from endo_io.errors import BagCorruptError, BagError
from endo_io.stamp import ns_to_stamp, stamp_to_ns

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
T0 = 1_763_800_000_000_000_000
MS = 1_000_000
IMAGE, INFO, POSE, LEVEL = (
    "/endoscope/image_raw",
    "/endoscope/camera_info",
    "/tool/pose",
    "/light/level",
)
FRAME = "endoscope_optical_frame"


def _qos(reliability: ReliabilityPolicy, durability: DurabilityPolicy) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=reliability, durability=durability
    )


RELIABLE = _qos(ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)
LATCHED = _qos(ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)


def write_input_bag(path: Path) -> None:
    """One second of data.

    30 rgb8 64x48 frames and camera infos at 30 Hz, poses at 60 Hz, a scalar at 10 Hz.
    """
    rng = np.random.default_rng(7)
    with BagWriter(path) as writer:
        writer.add_topic(IMAGE, "sensor_msgs/msg/Image", qos_profiles_to_yaml([RELIABLE]))
        writer.add_topic(INFO, "sensor_msgs/msg/CameraInfo", qos_profiles_to_yaml([LATCHED]))
        writer.add_topic(POSE, "geometry_msgs/msg/PoseStamped", qos_profiles_to_yaml([RELIABLE]))
        writer.add_topic(LEVEL, "std_msgs/msg/Float32", qos_profiles_to_yaml([RELIABLE]))
        events: list[tuple[int, str, object]] = []
        for i in range(30):
            t = T0 + round(i * 1e9 / 30)
            image = Image(height=48, width=64, encoding="rgb8", step=64 * 3)
            image.header.stamp, image.header.frame_id = ns_to_stamp(t), FRAME
            image.data = rng.integers(0, 256, 48 * 64 * 3, dtype=np.uint8).tobytes()
            events.append((t, IMAGE, image))
            info = CameraInfo(height=48, width=64, distortion_model="plumb_bob")
            info.header.stamp, info.header.frame_id = ns_to_stamp(t), FRAME
            info.k = [50.0, 0.0, 32.0, 0.0, 50.0, 24.0, 0.0, 0.0, 1.0]
            info.d = [0.01 * i, 0.0, 0.0, 0.0, 0.0]
            events.append((t + 1 * MS, INFO, info))
        for i in range(60):
            t = T0 + round(i * 1e9 / 60) + 2 * MS
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = ns_to_stamp(t), "tracker"
            pose.pose.position.x, pose.pose.position.y = 0.001 * i, -0.002 * i
            pose.pose.orientation.w = 1.0
            events.append((t, POSE, pose))
        for i in range(10):
            events.append((T0 + i * 100 * MS + 3 * MS, LEVEL, Float32(data=0.5 + 0.01 * i)))
        # Stored as ros2 bag record stores them: the payload padded to 4-byte
        # alignment, as DDS delivers it (rclpy's serialisation is unpadded;
        # CameraInfo ends in a bool and needs 3 bytes of padding).
        for t, topic, msg in sorted(events, key=lambda e: e[0]):
            writer.write(topic, serialize(msg), t)


def read_all(path: Path) -> tuple[list[BagMessage], bool]:
    """Every readable message of a bag, and whether reading ended at damage."""
    messages: list[BagMessage] = []
    try:
        with BagReader(path) as reader:
            messages.extend(reader.messages())
    except BagCorruptError:
        return messages, True
    return messages, False


def readable_count(path: Path) -> int:
    """Messages readable so far from a bag that is still being written (0 before its header)."""
    try:
        return len(read_all(path)[0])
    except BagError:
        return 0


def by_topic(messages: list[BagMessage]) -> dict[str, list[bytes]]:
    grouped: dict[str, list[bytes]] = defaultdict(list)
    for m in messages:
        grouped[m.topic].append(m.data)
    return dict(grouped)


@pytest.fixture(scope="module")
def input_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("input") / "input.mcap"
    write_input_bag(path)
    return path


@pytest.fixture(scope="module")
def dds_env() -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = os.environ["ROS_DOMAIN_ID"]  # the test run's domain, never hard-coded
    env["PYTHONUNBUFFERED"] = "1"
    return env


class Processes:
    """Starts console scripts and makes sure none outlives the test."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = env
        self.log_dir = log_dir
        self.started: list[subprocess.Popen[bytes]] = []

    def start(
        self, script: str, *args: str | Path, preexec_fn: Callable[[], None] | None = None
    ) -> subprocess.Popen[bytes]:
        log = (self.log_dir / f"{script}-{len(self.started)}.log").open("wb")
        process = subprocess.Popen(
            [str(BIN / script), *map(str, args)],
            env=self.env,
            stdout=log,
            stderr=subprocess.STDOUT,
            preexec_fn=preexec_fn,
        )
        self.started.append(process)
        return process

    def output(self, process: subprocess.Popen[bytes]) -> str:
        index = self.started.index(process)
        script = Path(str(process.args[0])).name  # type: ignore[index]
        return (self.log_dir / f"{script}-{index}.log").read_text()

    def stop_all(self) -> None:
        for process in self.started:
            if process.poll() is None:
                process.kill()
                process.wait(5)


@pytest.fixture
def processes(dds_env: dict[str, str], tmp_path: Path) -> Iterator[Processes]:
    procs = Processes(dds_env, tmp_path)
    yield procs
    procs.stop_all()


def wait_until(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.1)


def test_replay_then_record_over_dds_reproduces_the_bag_byte_for_byte(
    input_bag: Path, processes: Processes, tmp_path: Path
):
    expected, _ = read_all(input_bag)
    output = tmp_path / "recorded.mcap"
    recorder = processes.start("endo-record", "--all", "-o", output, "--flush-period", "0.2")
    replay = processes.start("endo-replay", input_bag, "--wait-for-subscribers", "1")
    assert replay.wait(30) == 0, processes.output(replay)
    # Acknowledged by the recorder's reader is not yet written by its callback:
    # wait until the flushed (still open) file holds every message.
    wait_until(
        lambda: len(read_all(output)[0]) >= len(expected), 10, "all messages in the recording"
    )
    recorder.send_signal(signal.SIGINT)
    assert recorder.wait(10) == 0, processes.output(recorder)

    recorded, damaged = read_all(output)
    assert not damaged  # SIGINT finalised the file
    assert len(recorded) == len(expected) == 130
    assert by_topic(recorded) == by_topic(expected)  # same topics, counts, order and raw CDR
    # taken in batches, written in receive order: log times never go back in the file
    with output.open("rb") as file:
        times = [m.log_time for _, _, m in make_reader(file).iter_messages(log_time_order=False)]
    assert len(times) == 130 and times == sorted(times)
    with BagReader(output) as out, BagReader(input_bag) as inp:
        assert {t: i.msgtype for t, i in out.topics.items()} == {
            t: i.msgtype for t, i in inp.topics.items()
        }
        assert {t: i.message_count for t, i in out.topics.items()} == {
            IMAGE: 30,
            INFO: 30,
            POSE: 60,
            LEVEL: 10,
        }
        offers = {t: qos_profiles_from_yaml(i.offered_qos_profiles) for t, i in out.topics.items()}
    # The recorder stored what the replay offered, which is what the input recorded.
    assert all(len(o) == 1 for o in offers.values()), offers
    assert offers[INFO][0].durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert offers[IMAGE][0].durability == DurabilityPolicy.VOLATILE
    assert all(o[0].reliability == ReliabilityPolicy.RELIABLE for o in offers.values())
    # The decoded content survived too (not only the bytes).
    first_image = deserialize(next(m for m in recorded if m.topic == IMAGE))
    assert (first_image.width, first_image.height, first_image.encoding) == (64, 48, "rgb8")
    assert stamp_to_ns(first_image.header.stamp) == T0
    replay_out = processes.output(replay)
    assert "130 messages" in replay_out, replay_out
    assert "130 messages" in processes.output(recorder)


def test_recorder_killed_with_sigkill_leaves_a_readable_file(
    input_bag: Path, processes: Processes, tmp_path: Path
):
    expected = by_topic(read_all(input_bag)[0])
    output = tmp_path / "killed.mcap"
    recorder = processes.start(
        "endo-record", "--topics", IMAGE, POSE, "-o", output, "--flush-period", "0.2"
    )
    replay = processes.start(
        "endo-replay", input_bag, "--loop", "--topics", IMAGE, POSE, "--wait-for-subscribers", "1"
    )
    wait_until(lambda: readable_count(output) >= 100, 20, "a flushed part of the recording")
    recorder.kill()
    recorder.wait(5)
    replay.send_signal(signal.SIGINT)
    assert replay.wait(10) == 0, processes.output(replay)

    recorded, _ = read_all(output)
    assert len(recorded) >= 100
    got = by_topic(recorded)
    assert set(got) == {IMAGE, POSE}
    for topic, data in got.items():
        # Looped playback: the recording is the input sequence over and over, cut anywhere.
        cycle = expected[topic]
        assert data == [cycle[i % len(cycle)] for i in range(len(data))], topic


def test_clock_start_offset_remap_and_qos_override(
    input_bag: Path, processes: Processes, tmp_path: Path
):
    output = tmp_path / "clock.mcap"
    offset_ns = 250 * MS
    renamed = "/tool/pose_replayed"
    overrides = tmp_path / "qos.yaml"
    overrides.write_text(f"{renamed}:\n  durability: transient_local\n")  # recorded: volatile
    recorder = processes.start(
        "endo-record", "--topics", "/clock", renamed, "-o", output, "--flush-period", "0.2"
    )
    replay = processes.start(
        "endo-replay", input_bag, "--clock", "100", "--topics", POSE,
        "--start-offset", str(offset_ns / 1e9), "--remap", f"{POSE}:={renamed}",
        "--qos-profile-overrides-path", overrides, "--wait-for-subscribers", "1",
    )  # fmt: skip
    assert replay.wait(30) == 0, processes.output(replay)
    poses = [
        m for m in read_all(input_bag)[0] if m.topic == POSE and m.log_time_ns >= T0 + offset_ns
    ]
    last = poses[-1].log_time_ns

    def final_clock_recorded() -> bool:
        try:
            clocks = [m for m in read_all(output)[0] if m.topic == "/clock"]
        except BagError:
            return False
        return bool(clocks) and stamp_to_ns(deserialize(clocks[-1]).clock) == last

    wait_until(final_clock_recorded, 10, "the final /clock value in the recording")
    recorder.send_signal(signal.SIGTERM)
    assert recorder.wait(10) == 0, processes.output(recorder)

    recorded, damaged = read_all(output)
    assert not damaged  # SIGTERM finalised the file
    clock = [stamp_to_ns(deserialize(m).clock) for m in recorded if m.topic == "/clock"]
    assert isinstance(deserialize(next(m for m in recorded if m.topic == "/clock")), Clock)
    # Paused at the start offset until playback starts, then running with the
    # bag, ending at the last message played.
    assert clock[0] == T0 + offset_ns
    assert clock[-1] == last
    assert all(a <= b for a, b in itertools.pairwise(clock))
    assert any(T0 + offset_ns < c < last for c in clock)
    # Only the poses from the offset on, published under the new name, with
    # the overridden QoS offered.
    assert [m.data for m in recorded if m.topic == renamed] == [m.data for m in poses]
    with BagReader(output) as reader:
        assert set(reader.topics) == {"/clock", renamed}
        (offer,) = qos_profiles_from_yaml(reader.topics[renamed].offered_qos_profiles)
    assert offer.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert offer.reliability == ReliabilityPolicy.RELIABLE


# ----------------------------------------------------------------- faults (issue 16)


@pytest.mark.parametrize("output_name", ["killed.mcap", "killed_dir"])
def test_a_sigkilled_recording_is_recovered_message_for_message(
    input_bag: Path, processes: Processes, tmp_path: Path, output_name: str
):
    expected, _ = read_all(input_bag)
    output = tmp_path / output_name
    recorder = processes.start("endo-record", "--all", "-o", output, "--flush-period", "0.2")
    replay = processes.start("endo-replay", input_bag, "--wait-for-subscribers", "1")
    assert replay.wait(30) == 0, processes.output(replay)
    wait_until(
        lambda: readable_count(output) >= len(expected), 10, "all messages in the recording"
    )
    if output.suffix != ".mcap":
        # metadata.yaml is rewritten at each flush: it counts what the files hold.
        def metadata_count() -> int:
            text = (output / "metadata.yaml").read_text()
            return int(re.search(r"^  message_count: (\d+)$", text, re.M).group(1))

        wait_until(lambda: metadata_count() == len(expected), 5, "metadata.yaml to count them")
    recorder.kill()
    assert recorder.wait(5) == -signal.SIGKILL
    killed, damaged = read_all(output)
    assert damaged and len(killed) == len(expected)  # no summary, every chunk readable
    if output.suffix != ".mcap":
        assert metadata_count() == len(expected)  # not the 0 it used to keep

    recovered = tmp_path / "recovered.mcap"
    tool = processes.start("endo-bag", "recover", output, recovered)
    assert tool.wait(30) == 0, processes.output(tool)
    report = processes.output(tool)
    assert f"total: kept {len(expected)} messages, lost 0" in report, report
    messages, damaged = read_all(recovered)
    assert not damaged  # a complete file: summary and footer
    assert by_topic(messages) == by_topic(expected)  # every message published, byte for byte
    with BagReader(recovered) as reader:
        assert {t: i.msgtype for t, i in reader.topics.items()} == {
            IMAGE: "sensor_msgs/msg/Image",
            INFO: "sensor_msgs/msg/CameraInfo",
            POSE: "geometry_msgs/msg/PoseStamped",
            LEVEL: "std_msgs/msg/Float32",
        }
        offers = qos_profiles_from_yaml(reader.topics[INFO].offered_qos_profiles)
    assert offers[0].durability == DurabilityPolicy.TRANSIENT_LOCAL  # the recorded offers kept


def _large_frames_bag(path: Path) -> None:
    """40 rgb8 320x240 frames (230 KB each) at 30 Hz and 80 poses at 60 Hz."""
    rng = np.random.default_rng(3)
    with BagWriter(path, compression="none") as writer:
        writer.add_topic(IMAGE, "sensor_msgs/msg/Image", qos_profiles_to_yaml([RELIABLE]))
        writer.add_topic(POSE, "geometry_msgs/msg/PoseStamped", qos_profiles_to_yaml([RELIABLE]))
        events = []
        for i in range(40):
            image = Image(height=240, width=320, encoding="rgb8", step=960)
            image.header.stamp, image.header.frame_id = ns_to_stamp(T0 + i * 33 * MS), FRAME
            image.data = rng.integers(0, 256, 240 * 960, dtype=np.uint8).tobytes()
            events.append((T0 + i * 33 * MS, IMAGE, image))
        for i in range(80):
            pose = PoseStamped()
            pose.header.stamp = ns_to_stamp(T0 + i * 16 * MS + MS)
            pose.pose.position.x, pose.pose.orientation.w = 0.001 * i, 1.0
            events.append((T0 + i * 16 * MS + MS, POSE, pose))
        for t, topic, msg in sorted(events, key=lambda e: e[0]):
            writer.write(topic, serialize(msg), t)


FILE_LIMIT = 2_000_000


def _limit_file_size() -> None:
    # A full disk without root: writes past the limit fail with EFBIG, as they
    # would with ENOSPC (a short write, then an error); SIGXFSZ is ignored.
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_LIMIT, FILE_LIMIT))


def test_a_recording_that_fills_the_disk_reports_what_the_file_holds(
    processes: Processes, tmp_path: Path
):
    source = tmp_path / "large.mcap"
    _large_frames_bag(source)
    sent = by_topic(read_all(source)[0])
    output = tmp_path / "full.mcap"
    recorder = processes.start(
        "endo-record", "--topics", IMAGE, POSE, "-o", output, "--flush-period", "0.2",
        preexec_fn=_limit_file_size,
    )  # fmt: skip
    replay = processes.start(
        "endo-replay", source, "--wait-for-subscribers", "1", "--ack-timeout", "1"
    )
    assert recorder.wait(60) == 1, processes.output(recorder)
    replay.wait(30)
    log = processes.output(recorder)
    errors = [line for line in log.splitlines() if "stopping: " in line]
    assert len(errors) == 1 and "cannot write (file size limit: File too large)" in errors[0], log
    got = by_topic(read_all(output)[0])
    assert output.stat().st_size <= FILE_LIMIT
    lost = 0
    for topic in (IMAGE, POSE):
        match = re.search(rf"{re.escape(topic)} \[[^]]+\]: (\d+) messages, (\d+) bytes", log)
        assert match is not None, log
        # The summary counts exactly what the file holds, a prefix of what was sent.
        assert int(match.group(1)) == len(got.get(topic, [])), (topic, log)
        assert int(match.group(2)) == sum(len(d) for d in got.get(topic, []))
        assert got.get(topic, []) == sent[topic][: len(got.get(topic, []))]
        lost_match = re.search(rf"{re.escape(topic)} .*, (\d+) received but lost", log)
        lost += int(lost_match.group(1)) if lost_match else 0
    assert 0 < len(got[IMAGE]) < len(sent[IMAGE])
    assert lost > 0 and f"lost: {lost} of " in log, log


def test_the_recorder_counts_undecodable_messages_and_keeps_their_bytes(
    processes: Processes, tmp_path: Path
):
    import rclpy

    output = tmp_path / "garbled.mcap"
    recorder = processes.start(
        "endo-record", "--topics", "/garbled", "-o", output, "--max-messages", "10"
    )
    good = Image(height=2, width=2, encoding="mono8", step=2, data=bytes(4))
    # The frame_id length says 2 GiB: no subscriber can decode this.
    garbled = b"\x00\x01\x00\x00" + bytes(8) + b"\xff\xff\xff\x7f" + bytes(36)
    payloads = [garbled if i % 3 == 0 else serialize(good) for i in range(10)]
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("garbler", context=context)
        publisher = node.create_publisher(Image, "/garbled", RELIABLE)
        wait_until(lambda: publisher.get_subscription_count() >= 1, 20, "the recorder")
        time.sleep(0.5)
        for data in payloads:
            publisher.publish(data)  # raw bytes, sent as they are
            time.sleep(0.02)
        assert recorder.wait(20) == 0, processes.output(recorder)
    finally:
        rclpy.shutdown(context=context)
    log = processes.output(recorder)
    assert "/garbled [sensor_msgs/msg/Image]: 10 messages" in log, log
    assert ", 4 undecodable (recorded as received; first: /garbled: 52 bytes are not a valid" in log
    warnings = [line for line in log.splitlines() if "recording undecodable messages" in line]
    assert len(warnings) == 1, log
    recorded, damaged = read_all(output)
    assert not damaged and [m.data for m in recorded] == payloads
