"""``endo-record``: record live topics, raw, into a rosbag2-compatible MCAP file.

The node is a thin adapter around :mod:`endo_io.record`: a discovery timer
looks for the requested topics (or all of them) in the graph, subscribes to
each new one with a QoS that matches all its publishers, and stores their
offers as the topic's ``offered_qos_profiles``. Raw CDR bytes go straight
into :class:`~endo_io.bag.BagWriter` with the receive time as log time and,
as rosbag2 records it, the DDS source timestamp (when the publisher wrote
the message, its system clock) as publish time: a graph's latency can be
read from the recording alone, from each message's own publish. A message
taken in its own callback (``--take-period 0``), whose source time rclpy
does not give, has its receive time as publish time.

The messages are taken in batches (``--take-period``, 20 ms): the
subscriptions are never waited on by rclpy's executor
(:mod:`endo_io.taking`), a timer takes everything waiting in all of them,
and the batch is written in order of the middleware's receive time (the log
time), holding back what arrived after the batch began to the next batch
(:class:`ReceiveOrder`). One executor wake-up per batch instead of one per
message: a live graph's ~11 messages per frame woke the recorder ~330 times
a second, each rebuilding rclpy's whole wait set. ``--take-period 0`` takes
each message in its own callback, as before.

Log times never go back in the file: the hold-back alone does not ensure it
(a large fragmented image received before a batch began may become takeable
only after it was written; under ``use_sim_time`` the offset from the
middleware's system clock to the node clock moves by up to one /clock step
between batches), so a log time up to :data:`MAX_RAISE_NS` (1 s) before the
last one written is raised to it and counted (``reordered`` in the summary).
A larger step back is the node clock jumping (``use_sim_time`` over a looping
bag) and is written as it is, as a message taken in its own callback is.

At the end (SIGINT, SIGTERM, a limit) the messages still waiting are taken
once more, each subscription on its own: one that rclpy refuses (its context
or handle gone) is logged, the others and the held-back batch are written.

The node's thread only takes and queues; the messages are checked, framed,
compressed and written on a thread of its own
(:class:`endo_io.record_writer.BackgroundWriter`), at ``--writer-nice``
below the taking, through a queue bounded by ``--buffer-mb``: a disk or a
writer that falls behind no longer leaves them in the subscription
histories to overflow, and what the bound refuses is counted and reported
as lost, with the reason. The writer closes the current chunk about once a
second (``--flush-period``), so a recorder killed with SIGKILL leaves a file
that reads up to the last flush (and a bag directory whose metadata.yaml
counts it). SIGINT and SIGTERM end the
recording cleanly (summary and footer written), as do ``--max-messages`` and
``--max-duration``: SIGINT raises no KeyboardInterrupt inside the writer
(:func:`endo_io.process.run_node`'s own, for every node). A failed write
(a full disk) stops the recording with one line; the summary then counts
what the file holds and how many received messages were lost.

Each message is checked to decode as its topic's type
(:func:`endo_io.bag.serde.cdr_check`: images by :func:`endo_io.image.image_from_cdr`,
which checks every field and length without copying the pixels; other types by
rclpy's own deserialisation); one that does not is recorded all the same (the
bag keeps what was on the wire), logged once per topic and counted in the
summary.

The recorder deliberately publishes nothing but rclpy's own /rosout and
/parameter_events (no /diagnostics): a recorder must not add traffic to the
graph it records.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rclpy.exceptions import InvalidHandle
from rclpy.node import Node

from endo_io.bag import BagWriter, message_class
from endo_io.bag.qos_yaml import qos_profiles_to_yaml
from endo_io.bag.serde import cdr_check
from endo_io.bag.writer import COMPRESSIONS, OUTPUT_PATH_HELP
from endo_io.cli import exit_on_error
from endo_io.errors import BagError, Endo3dError
from endo_io.process import run_node, split_ros_args
from endo_io.record import (
    DEFAULT_QUEUE_DEPTH,
    Recording,
    RecordOptionError,
    adapt_request_to_offers,
    mixed_offer_warning,
    seconds_to_ns,
    topics_to_record,
)
from endo_io.record_writer import DEFAULT_BUFFER_BYTES, BackgroundWriter
from endo_io.stamp import NS_PER_S
from endo_io.taking import NeverExecutedGroup, take_waiting_timed

#: Largest step back of a log time that is raised to the last one written (see
#: the module docstring); a larger one is a clock jump, written as it is.
MAX_RAISE_NS = NS_PER_S

#: A message taken for the file: (log time ns, topic, CDR bytes, publish time ns or None).
Taken = tuple[int, str, bytes, int | None]


class ReceiveOrder:
    """Orders batches of taken messages by receive time so that log times never go back.

    Attributes:
        raised: log times raised to the last one given out (they were
            received earlier but became takeable later, or the clock offset
            moved between batches).
        last_ns: the last log time given out (None before the first).
    """

    def __init__(self, max_raise_ns: int = MAX_RAISE_NS) -> None:
        self._max_raise_ns = max_raise_ns
        self._held: list[Taken] = []
        self.raised = 0
        self.last_ns: int | None = None

    @property
    def held(self) -> int:
        """Messages held back for the next batch."""
        return len(self._held)

    def batch(self, taken: list[Taken], cut_ns: int | None) -> list[Taken]:
        """The messages to write now, in log-time order, none before the last given out.

        Args:
            taken: messages taken since the last batch, any order.
            cut_ns: messages received after this time (when the batch began)
                are held back for the next batch; None: none (the last batch).

        Returns:
            The held-back and ``taken`` messages received up to ``cut_ns``,
            sorted by log time, each raised to the last given out when it is
            at most ``max_raise_ns`` before it.
        """
        batch = sorted(self._held + taken, key=lambda item: item[0])
        cut = len(batch) if cut_ns is None else next(
            (i for i, item in enumerate(batch) if item[0] > cut_ns), len(batch))
        self._held = batch[cut:]
        out = []
        for item in batch[:cut]:
            log_ns = item[0]
            last = self.last_ns
            if last is not None and 0 < last - log_ns <= self._max_raise_ns:
                log_ns = last
                self.raised += 1
            self.last_ns = log_ns
            out.append((log_ns, *item[1:]))
        return out


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-record`` command line (ROS arguments after ``--ros-args`` are separate)."""
    parser = argparse.ArgumentParser(
        prog="endo-record",
        description="Record live ROS 2 topics, raw, into a rosbag2-compatible MCAP file.",
    )
    parser.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="topics to record")
    parser.add_argument(
        "-a",
        "--all",
        action="store_true",
        help="record every topic, discovering new ones as they appear "
        "(/rosout, /parameter_events and hidden topics only when given in --topics)",
    )
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="the bag to write, which must not exist (default "
        "endo_record_<date>_<time>.mcap); " + OUTPUT_PATH_HELP,
    )
    parser.add_argument(
        "--compression", choices=COMPRESSIONS, default="zstd",
        help="chunk compression (default zstd)",
    )
    parser.add_argument(
        "--direct",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="write the file with O_DIRECT, past the page cache (default; "
        "BagWriter(direct=True): a file system that refuses it is written as usual); "
        "--no-direct writes through the page cache",
    )
    parser.add_argument(
        "--max-duration", type=float, default=None, metavar="SECONDS", help="stop after this long"
    )
    parser.add_argument(
        "--max-messages",
        type=int,
        default=None,
        metavar="N",
        help="stop after N messages over all topics",
    )
    parser.add_argument(
        "--queue-depth",
        type=int,
        default=DEFAULT_QUEUE_DEPTH,
        metavar="N",
        help="subscription history depth per topic (default %(default)d)",
    )
    parser.add_argument(
        "--discovery-period",
        type=float,
        default=0.1,
        metavar="SECONDS",
        help="how often to look for new topics (default 0.1)",
    )
    parser.add_argument(
        "--take-period",
        type=float,
        default=0.02,
        metavar="SECONDS",
        help="how often the messages waiting in the subscriptions are taken and written "
        "(default 0.02; 0: one callback per message)",
    )
    parser.add_argument(
        "--flush-period",
        type=float,
        default=1.0,
        metavar="SECONDS",
        help="how often to write buffered messages out as a chunk (default 1)",
    )
    parser.add_argument(
        "--buffer-mb",
        type=float,
        default=DEFAULT_BUFFER_BYTES / 2**20,
        metavar="MB",
        help="bound of the messages taken but not yet written (MiB, default %(default)g); "
        "beyond it messages are refused and reported as lost",
    )
    parser.add_argument(
        "--writer-nice",
        type=int,
        default=0,
        metavar="N",
        help="niceness added to the writing thread only (0-19, default 0): taking the "
        "messages stays at the process's priority, so a busy machine delays the writing, not "
        "the taking",
    )
    return parser


class RecordNode(Node):
    """Subscribes to discovered topics and writes what arrives into a :class:`Recording`."""

    def __init__(self, recording: Recording, options: argparse.Namespace) -> None:
        super().__init__("endo_record")
        self._recording = recording
        self._options = options
        self._subscribed: set[str] = set()
        self._unrecordable: set[str] = set()
        self._stopping = False
        self.exit_code = 0
        self._taken_group = NeverExecutedGroup() if options.take_period > 0 else None
        self._taken_from: dict[str, Any] = {}
        self.order = ReceiveOrder()
        recording.start(self.get_clock().now().nanoseconds)
        self._writer = BackgroundWriter(recording, max_bytes=int(options.buffer_mb * 2**20),
                                        nice=options.writer_nice,
                                        flush_period_s=options.flush_period)
        self._refused_logged = 0
        self._undecodable_logged: set[str] = set()
        self.create_timer(options.discovery_period, self._discover)
        if options.take_period > 0:
            self.create_timer(options.take_period, self._take)
        what = "all topics" if options.all else ", ".join(options.topics)
        self.get_logger().info(f"recording {what} into {options.output}")
        self._discover()

    def _discover(self) -> None:
        if self._writer_stopped() or self._recording.limit_reached(
                self.get_clock().now().nanoseconds):
            self._stop()
            return
        self._log_refused()
        choices = topics_to_record(
            self.get_topic_names_and_types(),
            self._options.topics,
            record_all=self._options.all,
            already=self._subscribed | self._unrecordable,
        )
        for choice in choices:
            offers = [info.qos_profile for info in self.get_publishers_info_by_topic(choice.name)]
            if not offers:
                continue  # only subscribers so far; the type and QoS come with a publisher
            try:
                msg_class = message_class(choice.msgtype)
            except Endo3dError as error:
                self._unrecordable.add(choice.name)
                self.get_logger().warning(f"not recording {choice.name}: {error}")
                continue
            if choice.other_types:
                self.get_logger().warning(
                    f"{choice.name} is published with several types; recording "
                    f"{choice.msgtype}, ignoring {', '.join(choice.other_types)}"
                )
            warning = mixed_offer_warning(choice.name, offers)
            if warning:
                self.get_logger().warning(warning)
            self._writer.add_topic(  # written on the writer thread, in order with the messages
                choice.name,
                choice.msgtype,
                qos_profiles_to_yaml(offers),
                check=cdr_check(choice.msgtype, choice.name),
            )
            qos = adapt_request_to_offers(offers, self._options.queue_depth)
            self._taken_from[choice.name] = self.create_subscription(
                msg_class,
                choice.name,
                functools.partial(self._on_message, choice.name),
                qos,
                raw=True,
                callback_group=self._taken_group,
            )
            self._subscribed.add(choice.name)
            self.get_logger().info(f"subscribed to {choice.name} [{choice.msgtype}]")

    def _on_message(self, topic: str, data: bytes) -> None:
        if not self._stopping:
            self._write(topic, data, self.get_clock().now().nanoseconds)

    def _take(self, final: bool = False) -> None:
        """Write what waits in the subscriptions, in receive order (see the module docstring).

        ``final``: the last batch, nothing held back; a subscription rclpy
        refuses to take from is logged and the others are written.
        """
        if self._stopping and not final:
            return
        began = time.time_ns()
        # the middleware's receive times are on the system clock; the log time is on the
        # node's (use_sim_time applies), as for a message taken in its own callback
        offset = self.get_clock().now().nanoseconds - began
        taken: list[Taken] = []
        for topic, subscription in self._taken_from.items():
            try:
                waiting = take_waiting_timed(subscription)
            except (RuntimeError, InvalidHandle) as error:  # rclpy's: context or handle gone
                if not final:
                    raise
                self.get_logger().warning(
                    f"the messages still waiting on {topic} are not recorded: {error}")
                continue
            taken += [(max(received + offset, 0), topic, data, source)
                      for data, received, source in waiting]
        for log_ns, topic, data, source in self.order.batch(taken,
                                                            None if final else began + offset):
            if not self._write(topic, data, log_ns, source):
                return

    def _write(self, topic: str, data: bytes, receive_ns: int,
               publish_ns: int | None = None) -> bool:
        """Queue one message for the writer; False when the recording stopped.

        A message the full queue refuses is counted (and logged, see
        :meth:`_log_refused`); the recording goes on.
        """
        if self._writer.put(topic, data, receive_ns, publish_ns):
            return True
        return not self._writer_stopped()

    def _writer_stopped(self) -> bool:
        """Whether the writer stopped (a limit or a failed write); stops the node if so."""
        state = self._writer.state
        if state.error is not None:
            if not self._stopping:
                error = state.error
                self._write_failed(error if isinstance(error, (BagError, OSError)) else
                                   RuntimeError(f"the writer thread failed: "
                                                f"{type(error).__name__}: {error}"))
            return True
        if state.limit:
            self._stop()
            return True
        for topic, tally in tuple(self._recording.report.topics.items()):  # the writer adds
            if tally.undecodable and topic not in self._undecodable_logged:
                self._undecodable_logged.add(topic)
                self.get_logger().warning(
                    f"recording undecodable messages on {topic} as received, counting them: "
                    f"{tally.undecodable_reason}"
                )
        return False

    def _log_refused(self) -> None:
        """One line when the write queue starts refusing messages, and again every 100."""
        refused = sum(self._writer.refused.values())
        if refused > self._refused_logged and (self._refused_logged == 0
                                               or refused >= self._refused_logged + 100):
            self.get_logger().error(
                f"{refused} messages lost so far: the write queue is full "
                f"({self._options.buffer_mb:g} MB, --buffer-mb); the disk or the writer "
                f"thread is slower than the data ({dict(self._writer.refused)})"
            )
            self._refused_logged = refused

    def _write_failed(self, error: Exception) -> None:
        # A full disk or a vanished file: stop, keep what is on disk.
        self.get_logger().error(f"stopping: {error}")
        self.exit_code = 1
        self._stop()

    def _stop(self) -> None:
        # Ends spin() in run_node, which then calls close().
        self._stopping = True
        self.context.try_shutdown()

    def stop_writer(self) -> None:
        """Write what the writer thread still has queued and end it (idempotent)."""
        self._writer.close()

    def close(self) -> None:
        """Write what still waits, finalise the bag and print what was recorded."""
        if self._taken_group is not None and self.exit_code == 0:
            stopped = self._stopping
            self._take(final=True)
            self._stopping = stopped
        self.stop_writer()  # writes what is queued; every refusal counted into the report
        self._writer_stopped()  # a write that failed while draining: logged, exit code 1
        try:
            report = self._recording.close()
        except (BagError, OSError) as error:
            if self.exit_code == 0:  # not reported yet
                self.get_logger().error(f"cannot finalise {self._options.output}: {error}")
            self.exit_code = 1
            report = self._recording.report
        print(f"endo-record: wrote {self._options.output}", flush=True)
        for line in report.summary_lines():
            print(line, flush=True)
        if self.order.raised:
            print(f"  reordered: {self.order.raised} log times raised to the one written "
                  "before them (received earlier, takeable later)", flush=True)


def default_output(now: float | None = None) -> Path:
    """``endo_record_<YYYYmmdd>_<HHMMSS>.mcap`` in the working directory."""
    stamp = time.strftime("%Y%m%d_%H%M%S", time.localtime(now))
    return Path(f"endo_record_{stamp}.mcap")


def _check_options(options: argparse.Namespace) -> None:
    if not options.all and not options.topics:
        raise RecordOptionError("give --topics TOPIC [TOPIC ...] or --all")
    # The recorder's namespace is "/", so a relative name means the absolute one.
    options.topics = ["/" + name.lstrip("/") for name in options.topics]
    if options.max_messages is not None and options.max_messages < 1:
        raise RecordOptionError(f"--max-messages must be >= 1, got {options.max_messages}")
    if options.queue_depth < 1:
        raise RecordOptionError(f"--queue-depth must be >= 1, got {options.queue_depth}")
    if not (math.isfinite(options.buffer_mb) and options.buffer_mb * 2**20 >= 1):
        raise RecordOptionError(
            f"--buffer-mb must be a finite size of at least one byte, got {options.buffer_mb}")
    if not 0 <= options.writer_nice <= 19:
        raise RecordOptionError(f"--writer-nice must be in 0-19, got {options.writer_nice}")
    if not (options.discovery_period > 0 and options.flush_period > 0):
        raise RecordOptionError("--discovery-period and --flush-period must be > 0")
    if options.take_period < 0:
        raise RecordOptionError(f"--take-period must be >= 0, got {options.take_period}")
    if options.output.exists():
        raise RecordOptionError(f"{options.output} exists; not overwriting it")


@exit_on_error("endo-record", errors=(Endo3dError, OSError), label="error")
def main(argv: Sequence[str] | None = None) -> int:
    """Run ``endo-record``; returns the process exit status (2: bad options or output)."""
    ours, ros_args = split_ros_args(list(sys.argv if argv is None else argv))
    options = build_parser().parse_args(ours)
    if options.output is None:
        options.output = default_output()
    _check_options(options)
    max_duration_ns = seconds_to_ns(options.max_duration)  # checked before a file exists
    recording = Recording(
        BagWriter(options.output, compression=options.compression, direct=options.direct),
        max_messages=options.max_messages,
        max_duration_ns=max_duration_ns,
    )
    nodes: list[RecordNode] = []

    def factory() -> RecordNode:
        nodes.append(RecordNode(recording, options))
        return nodes[0]

    try:
        code = run_node(factory, ros_args)
    finally:
        for node in nodes:  # the writer thread done before the recording closes (idempotent)
            node.stop_writer()
        recording.close()  # done by the node's close() unless it was never created (idempotent)
    return code


if __name__ == "__main__":
    sys.exit(main())
