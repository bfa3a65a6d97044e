"""Large frames between two node processes: how many arrive, and how late.

``python -m endo_bringup.frame_probe receive`` and ``... send`` are two endo3d
node processes (both through :func:`endo_io.process.run_node`, so each gets
the transport every node gets). The sender publishes ``--frames`` 32FC1
images of ``--width``×``--height`` at ``--rate`` Hz on a reliable publisher,
as the nodes do, once the receiver is matched; the receiver counts them on a
best-effort subscription, as the SFS node does (deep enough to hold every
frame, so that a stalled receiver's backlog is not counted), and prints one
JSON line: frames received from the first one that arrived on (what is lost
before is discovery, not transport), the sequence numbers lost, and the
latency (receive time − header stamp) median and 95th percentile in
milliseconds. The receiver takes the messages raw and reads only the header
(stamp, and the sequence number in frame_id), so that on a loaded machine
what is counted is the transport, not the receiver's Python.

``endo-doctor --check-frames`` runs the pair with the user's environment;
``bench/bench_dds_transport.py`` compares transports with it and
``tests/test_large_frames.py`` checks that nodes started with no profile
variables lose no frame.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image

from endo_io.image import array_to_image
from endo_io.process import run_node, split_ros_args
from endo_io.qos import SENSOR_DATA_QOS, best_effort_qos, create_reliable_publisher
from endo_io.serialized_stamp import serialized_header_stamp_ns
from endo_io.stamp import ns_to_stamp

#: The probe's topic (private to it; :func:`run_probe` adds its process id, so
#: that two probes on one domain do not count each other's frames).
TOPIC = "/endo3d_probe/frames"
#: What the sender prints on stderr when it first sees the receiver.
MATCHED_LINE = "endo3d_probe: receiver matched"


class ProbeSender(Node):
    """Publishes ``frames`` float images at ``rate_hz`` once a subscriber is matched."""

    def __init__(self, topic: str, frames: int, rate_hz: float, width: int, height: int) -> None:
        super().__init__("endo3d_probe_sender")
        self._publisher = create_reliable_publisher(self, Image, topic)
        rng = np.random.default_rng(0)
        self._image = array_to_image(
            rng.random((height, width), dtype=np.float32), "32FC1", frame_id="probe"
        )
        self._frames = frames
        self._sent = 0
        self._matched_at: float | None = None
        self.exit_code = 0
        self.create_timer(1.0 / rate_hz, self._tick)

    def _tick(self) -> None:
        if self._publisher.get_subscription_count() == 0:
            if self._matched_at is not None:
                self.context.try_shutdown()  # the receiver has left: nothing more to send
            return
        now = time.monotonic()
        if self._matched_at is None:
            self._matched_at = now
            print(MATCHED_LINE, file=sys.stderr, flush=True)
        if now - self._matched_at < 2.0:  # let discovery finish on both sides
            return
        if self._sent >= self._frames:
            self.context.try_shutdown()
            return
        self._image.header.stamp = ns_to_stamp(time.time_ns())
        self._image.header.frame_id = str(self._sent)
        self._publisher.publish(self._image)
        self._sent += 1


class ProbeReceiver(Node):
    """Counts frames on a best-effort subscription; stops ``idle_s`` after the last one."""

    def __init__(self, topic: str, expected: int, idle_s: float, timeout_s: float) -> None:
        super().__init__("endo3d_probe_receiver")
        # Best effort as the SFS node's input, but deep enough to hold every frame: a
        # receiver stalled by the machine's load must not count its own backlog as
        # frames lost in transport (4 in a row were, with depth 5, at load ~2).
        self.create_subscription(Image, topic, self._on_frame,
                                 best_effort_qos(max(expected, SENSOR_DATA_QOS.depth)), raw=True)
        self.sequence: list[int] = []
        self.latency_ms: list[float] = []
        self._expected = expected
        self._idle_s = idle_s
        self._started = time.monotonic()
        self._timeout_s = timeout_s
        self._last: float | None = None
        self.exit_code = 0
        self.create_timer(0.1, self._check_done)

    def _on_frame(self, data: bytes) -> None:
        stamp_ns = serialized_header_stamp_ns(data)
        if stamp_ns is not None:
            self.latency_ms.append((time.time_ns() - stamp_ns) / 1e6)
        # frame_id after the stamp: uint32 length (with its NUL), then the characters
        (length,) = struct.unpack_from("<I", data, 12)
        self.sequence.append(int(data[16 : 16 + length - 1]))
        self._last = time.monotonic()

    def _check_done(self) -> None:
        now = time.monotonic()
        done = bool(self.sequence) and self.sequence[-1] >= self._expected - 1
        idle = self._last is not None and now - self._last > self._idle_s
        if done or idle or now - self._started > self._timeout_s:
            self.context.try_shutdown()

    def close(self) -> None:
        """Print the result as one JSON line (run_node calls this on the way out)."""
        latency = np.asarray(self.latency_ms or [np.nan])
        first = min(self.sequence, default=self._expected)
        print(json.dumps({
            "first": first,
            "received": len(self.sequence),
            "expected": self._expected - first,
            "lost": sorted(set(range(first, self._expected)) - set(self.sequence)),
            "latency_median_ms": float(np.median(latency)),
            "latency_p95_ms": float(np.percentile(latency, 95)),
        }), flush=True)  # fmt: skip


@dataclass(frozen=True)
class ProbeResult:
    """One probe run: frames sent from the first received on, received, latency in ms."""

    first: int
    expected: int
    received: int
    lost: list[int]
    latency_median_ms: float
    latency_p95_ms: float

    @property
    def fraction(self) -> float:
        """Received / sent, from the first received frame on (0 when none arrived)."""
        return self.received / self.expected if self.expected else 0.0


class ProbeError(RuntimeError):
    """The probe's processes did not run to the end."""


class ProbeDiscoveryError(ProbeError):
    """The sender never saw the receiver: DDS discovery, not the transport, failed."""


def run_probe(
    env: dict[str, str],
    *,
    frames: int = 60,
    rate_hz: float = 30.0,
    width: int = 640,
    height: int = 480,
    timeout_s: float = 60.0,
    topic_suffix: str = "",
) -> ProbeResult:
    """Run a receiver and a sender process with ``env``; what the receiver got.

    ``topic_suffix`` is added to the probe's topic (after this process's id), so
    that a second probe from the same process does not meet the first's frames.

    Raises:
        ProbeDiscoveryError: the sender saw no receiver within ``timeout_s``, or
            the receiver took no frame although the sender saw it.
        ProbeError: a process failed or printed no result within ``timeout_s``.
    """
    command = [sys.executable, "-m", "endo_bringup.frame_probe"]
    shape = ["--frames", str(frames), "--width", str(width), "--height", str(height),
             "--topic", f"{TOPIC}_{os.getpid()}{topic_suffix}"]  # fmt: skip
    # The receiver gives up first, so that a sender whose frames never arrive sees
    # it leave and stops (rather than both waiting out the whole timeout).
    receiver = subprocess.Popen(
        [*command, "receive", *shape, "--timeout", str(0.8 * timeout_s)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        try:
            sender = subprocess.run(
                [*command, "send", *shape, "--rate", str(rate_hz)],
                env=env, capture_output=True, text=True, timeout=timeout_s, check=False,
            )  # fmt: skip
        except subprocess.TimeoutExpired as error:
            said = error.stderr or b""
            text = said.decode(errors="replace") if isinstance(said, bytes) else said
            if MATCHED_LINE in text:
                raise
            raise ProbeDiscoveryError(
                f"the sender saw no receiver in {timeout_s:g} s (DDS discovery failed: "
                f"domain {env.get('ROS_DOMAIN_ID', '0')}, "
                f"ROS_AUTOMATIC_DISCOVERY_RANGE={env.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '')!r})"
            ) from error
        out, err = receiver.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired as error:
        raise ProbeError(f"the probe did not finish in {timeout_s:g} s") from error
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait()
    if sender.returncode != 0 or receiver.returncode != 0:
        raise ProbeError(f"probe failed: sender {sender.stderr[-2000:]} receiver {err[-2000:]}")
    line = next((x for x in out.splitlines() if x.startswith("{")), None)
    if line is None:
        raise ProbeError(f"the receiver printed no result: {err[-2000:]}")
    result = ProbeResult(**json.loads(line))
    if result.received == 0:
        # The sender saw the receiver, the receiver never took a frame: it never
        # matched the sender (discovery one way only), which is not a transport loss.
        raise ProbeDiscoveryError(
            f"the receiver got no frame in {0.8 * timeout_s:g} s although the sender saw it "
            f"(DDS discovery one way only: domain {env.get('ROS_DOMAIN_ID', '0')})"
        )
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """``receive`` or ``send`` (see the module docstring)."""
    args = list(sys.argv if argv is None else argv)
    ours, ros = split_ros_args(args)
    parser = argparse.ArgumentParser(prog="frame_probe")
    parser.add_argument("role", choices=("send", "receive"))
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--rate", type=float, default=30.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--timeout", type=float, default=60.0)
    parser.add_argument("--topic", default=TOPIC)
    options = parser.parse_args(ours)
    os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "0")
    if options.role == "send":
        return run_node(
            lambda: ProbeSender(
                options.topic, options.frames, options.rate, options.width, options.height
            ),
            ros,
        )
    return run_node(lambda: ProbeReceiver(options.topic, options.frames, 2.0, options.timeout), ros)


if __name__ == "__main__":
    sys.exit(main())
