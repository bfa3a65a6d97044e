"""``endo-demo``: send a bag through real ROS 2 topics and record it back.

Until the full endo3d graph exists, the demo exercises its spine: a bag is
played by ``endo-replay`` in one OS process and recorded by ``endo-record``
in another, over loopback DDS, and the recording is compared with the input
message for message. The bag is ``bags/phantom_*.mcap`` if there is one, else
the first ``bags/*.mcap``, else a small synthetic bag written here (two
seconds of 160x120 rgb8 endoscope frames with camera info, a tracked tool
pose and a light level). Outputs go to a new temporary directory (or
``--output-dir``), never into the repository.

Exit status 0 when every played message came back with the same bytes, 1
when the round trip differs or a process failed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from std_msgs.msg import Float32

from endo_io.bag import BagReader, BagWriter, message_class, msgtype_of, serialize
from endo_io.bag.serde import dds_aligned
from endo_io.camera import CameraModel
from endo_io.errors import BagError, Endo3dError
from endo_io.image import array_to_image
from endo_io.pose import matrix_to_pose

#: DDS domain of the demo when the environment gives none (as in the Makefile).
DEMO_DOMAIN_ID = "41"
SYNTHETIC_START_NS = 1_763_800_000_000_000_000
REPO_ROOT = Path(__file__).resolve().parents[3]


# --------------------------------------------------------------------------
# The input bag


def find_bag(search_dirs: list[Path]) -> Path | None:
    """``phantom_*.mcap`` in the first directory that has one, else the first ``*.mcap``."""
    for pattern in ("phantom_*.mcap", "*.mcap"):
        for directory in search_dirs:
            found = sorted(directory.glob(pattern))
            if found:
                return found[0]
    return None


def write_synthetic_bag(path: Path, seconds: float = 2.0) -> None:
    """A small endoscope-like recording.

    160x120 rgb8 frames at 30 Hz (a lit, vignetted tissue-like texture drifting
    across the view), the matching CameraInfo, a tool PoseStamped at 60 Hz on a
    helix, and a std_msgs/Float32 light level at 10 Hz. Payloads are stored as
    ``ros2 bag record`` stores them (padded to 4 bytes, as DDS delivers them).
    """
    width, height = 160, 120
    camera = CameraModel.pinhole(width, height, fx=140.0, fy=140.0, cx=79.5, cy=59.5)
    rng = np.random.default_rng(3)
    noise = rng.random((height * 2, width * 2)).astype(np.float32)
    blurred = cv2.blur(noise, (9, 9))  # smoother, tissue-like
    texture = (blurred - blurred.min()) / (blurred.max() - blurred.min())
    y, x = np.mgrid[0:height, 0:width]
    vignette = np.clip(1.0 - ((x - 79.5) ** 2 + (y - 59.5) ** 2) / 90.0**2, 0.0, 1.0)
    tint = np.array([1.0, 0.55, 0.45], np.float32)
    events: list[tuple[int, str, object]] = []
    for i in range(round(30 * seconds)):
        t = SYNTHETIC_START_NS + round(i * 1e9 / 30)
        patch = texture[i : i + height, 2 * i % width : 2 * i % width + width]
        shade = (0.35 + 0.65 * patch) * vignette
        pixels = (255 * np.clip(shade[..., None] * tint, 0, 1)).astype(np.uint8)
        events.append(
            (t, "/endoscope/image_raw", array_to_image(pixels, "rgb8", t, camera.frame_id))
        )
        events.append((t + 1_000_000, "/endoscope/camera_info", camera.to_camera_info(t)))
    for i in range(round(60 * seconds)):
        t = SYNTHETIC_START_NS + round(i * 1e9 / 60) + 2_000_000
        angle = 0.1 * i
        transform = np.eye(4)
        transform[:3, :3] = [
            [np.cos(angle), -np.sin(angle), 0],
            [np.sin(angle), np.cos(angle), 0],
            [0, 0, 1],
        ]
        transform[:3, 3] = [0.01 * np.cos(angle), 0.01 * np.sin(angle), 0.0005 * i]
        events.append((t, "/tool/pose", matrix_to_pose(transform, t, "tracker")))
    for i in range(round(10 * seconds)):
        t = SYNTHETIC_START_NS + i * 100_000_000 + 3_000_000
        events.append((t, "/light/level", Float32(data=0.6 + 0.02 * np.sin(i))))
    added: set[str] = set()
    with BagWriter(path) as writer:
        for t, topic, msg in sorted(events, key=lambda e: e[0]):
            if topic not in added:
                writer.add_topic(topic, msgtype_of(msg))
                added.add(topic)
            writer.write(topic, serialize(msg), t)


# --------------------------------------------------------------------------
# Comparison


@dataclass
class TopicComparison:
    """One topic of the round trip."""

    msgtype: str
    sent: int = 0
    received: int = 0
    identical: int = 0
    padding_only: int = 0
    sent_bytes: int = 0

    @property
    def equal(self) -> bool:
        """Every message came back, in order, with the same bytes (up to DDS padding)."""
        return self.sent == self.received == self.identical + self.padding_only


@dataclass
class RoundTrip:
    """Result of comparing a recording with the bag that was played."""

    topics: dict[str, TopicComparison] = field(default_factory=dict)
    extra_topics: list[str] = field(default_factory=list)

    @property
    def equal(self) -> bool:
        """True when every topic is equal and nothing else was recorded."""
        return not self.extra_topics and all(t.equal for t in self.topics.values())


def compare_bags(sent_path: Path, received_path: Path, topics: list[str]) -> RoundTrip:
    """Compare, per topic and in order, the messages of ``topics`` in two bags.

    A message is identical when its bytes are; ``padding_only`` counts those
    that differ only by the zero padding DDS adds up to a 4-byte boundary
    (bags written by rclpy serialisation rather than recorded lack it).
    """
    sent: dict[str, list[bytes]] = defaultdict(list)
    received: dict[str, list[bytes]] = defaultdict(list)
    result = RoundTrip()
    with BagReader(sent_path) as reader:
        for name in topics:
            result.topics[name] = TopicComparison(reader.topics[name].msgtype)
        for message in reader.messages(topics=topics):
            sent[message.topic].append(message.data)
    with BagReader(received_path) as reader:
        result.extra_topics = sorted(set(reader.topics) - set(topics))
        for message in reader.messages(topics=topics):
            received[message.topic].append(message.data)
    for name, comparison in result.topics.items():
        comparison.sent, comparison.received = len(sent[name]), len(received[name])
        comparison.sent_bytes = sum(map(len, sent[name]))
        for a, b in zip(sent[name], received[name], strict=False):
            if a == b:
                comparison.identical += 1
            elif dds_aligned(a) == dds_aligned(b):
                comparison.padding_only += 1
    return result


# --------------------------------------------------------------------------
# Running the two processes


def _script(name: str) -> str:
    beside = Path(sys.executable).parent / name
    if beside.exists():
        return str(beside)
    found = shutil.which(name)
    if found is None:
        raise FileNotFoundError(f"{name} is not installed (pip install -e src/endo_io)")
    return found


def _count_readable(path: Path) -> int:
    try:
        with BagReader(path) as reader:
            count = 0
            try:
                for _ in reader.messages():
                    count += 1
            except BagError:
                pass
            return count
    except BagError:
        return 0


def playable_topics(bag: Path) -> tuple[list[str], list[str]]:
    """(topics whose type is installed, topics that cannot be published here)."""
    playable, skipped = [], []
    with BagReader(bag) as reader:
        for name, info in sorted(reader.topics.items()):
            try:
                message_class(info.msgtype)
            except Endo3dError:
                skipped.append(name)
                continue
            playable.append(name)
    return playable, skipped


def run_round_trip(
    bag: Path, output: Path, rate: float, env: dict[str, str]
) -> tuple[int, int, str]:
    """Record ``bag`` played over DDS into ``output``; returns (replay rc, record rc, logs)."""
    topics, _ = playable_topics(bag)
    with BagReader(bag) as reader:
        expected = sum(reader.topics[t].message_count for t in topics)
    record_log = output.with_suffix(".record.log")
    with record_log.open("wb") as log:
        recorder = subprocess.Popen(
            [
                _script("endo-record"),
                "--topics",
                *topics,
                "-o",
                str(output),
                "--flush-period",
                "0.2",
            ],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            replay = subprocess.run(
                [
                    _script("endo-replay"),
                    str(bag),
                    "--topics",
                    *topics,
                    "--rate",
                    str(rate),
                    "--wait-for-subscribers",
                    "1",
                ],
                env=env,
                capture_output=True,
                text=True,
                check=False,
            )
            # Delivered is not yet written: wait until the (flushed, still open)
            # recording holds everything, then let SIGINT finalise it.
            deadline = time.monotonic() + 15.0
            while _count_readable(output) < expected and time.monotonic() < deadline:
                if recorder.poll() is not None:
                    break
                time.sleep(0.2)
            recorder.send_signal(signal.SIGINT)
            record_rc = recorder.wait(30)
        finally:
            if recorder.poll() is None:
                recorder.kill()
                recorder.wait()
    logs = replay.stdout + replay.stderr + record_log.read_text()
    return replay.returncode, record_rc, logs


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-demo`` command line."""
    parser = argparse.ArgumentParser(
        prog="endo-demo",
        description="Play a bag with endo-replay, record it with endo-record, compare.",
    )
    parser.add_argument("--bag", type=Path, default=None, help="bag to play (default: see above)")
    parser.add_argument(
        "--output-dir", type=Path, default=None, help="where to write (default: a new temp dir)"
    )
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the demo; returns the exit status."""
    options = build_parser().parse_args(argv)
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", DEMO_DOMAIN_ID)
    out_dir = options.output_dir or Path(tempfile.mkdtemp(prefix="endo_demo_"))
    out_dir.mkdir(parents=True, exist_ok=True)
    bag = options.bag or find_bag(list(dict.fromkeys([Path.cwd() / "bags", REPO_ROOT / "bags"])))
    if bag is None:
        bag = out_dir / "synthetic_input.mcap"
        write_synthetic_bag(bag)
        print(f"endo-demo: no bag in bags/, wrote a synthetic one: {bag}")
    output = out_dir / "round_trip.mcap"
    if output.exists():
        print(f"endo-demo: error: {output} exists", file=sys.stderr)
        return 1
    topics, skipped = playable_topics(bag)
    print(
        f"endo-demo: playing {bag} at {options.rate:g}x over DDS (domain {env['ROS_DOMAIN_ID']}, "
        f"discovery {env['ROS_AUTOMATIC_DISCOVERY_RANGE']}), recording into {output}"
    )
    for name in skipped:
        print(f"  {name}: type not installed here, not played")
    started = time.monotonic()
    replay_rc, record_rc, logs = run_round_trip(bag, output, options.rate, env)
    elapsed = time.monotonic() - started
    if replay_rc != 0 or record_rc != 0 or not output.exists():
        print(logs)
        print(f"endo-demo: FAILED (endo-replay exit {replay_rc}, endo-record exit {record_rc})")
        return 1
    result = compare_bags(bag, output, topics)
    print(f"  {'topic':<28} {'type':<32} {'sent':>6} {'recorded':>9} {'bytes':>11}  result")
    for name, t in result.topics.items():
        if t.identical == t.sent == t.received:
            verdict = "identical"
        elif t.equal:
            verdict = f"equal up to DDS 4-byte padding ({t.padding_only} padded in transit)"
        else:
            verdict = "DIFFERENT"
        counts = f"{t.sent:>6} {t.received:>9} {t.sent_bytes:>11}"
        print(f"  {name:<28} {t.msgtype:<32} {counts}  {verdict}")
    for name in result.extra_topics:
        print(f"  {name}: recorded but not played (DIFFERENT)")
    total = sum(t.sent for t in result.topics.values())
    print(f"  {total} messages in {elapsed:.1f} s; recording kept in {out_dir}")
    if not result.equal:
        print("endo-demo: FAILED: the recording differs from the bag")
        return 1
    print("endo-demo: OK: the recording equals the bag, message for message")
    return 0


if __name__ == "__main__":
    sys.exit(main())
