"""The output recording: the live graph's topics in one rosbag2 MCAP, in time order.

Every message is logged at its header stamp (the image's stamp for the
per-frame outputs, the camera-clock stamp for poses), so the file replays
on the recording's own timeline; ground truth is copied with its original
log time. Small streams (poses, ground truth) are held back and written
just before the first frame output that is later, so the file is in log-time
order as a recorder would write it.

The writer is flushed every ``flush_every`` frames: after a crash (SIGKILL,
power cut) every flushed chunk reads back. Ctrl-C and SIGTERM finalise the
file normally (:mod:`endo_process.cli`).

The file is written with ``O_DIRECT``, past the page cache (``BagWriter``'s
``direct``): the kernel's part of writing ~6 GB per minute of 640x480 video,
not the copy but filling, writing back and reclaiming the page cache, cost
~3-5 system-CPU ms per frame buffered against ~1 (docs/benchmarks.md,
"endo-process, session 14"); the file is the same byte for byte.

The :class:`BagWriter` runs in a thread of its own (:class:`_WriterThread`):
the frame loop serialises each message and hands the bytes over, and the
thread makes the chunks, compresses them and writes them, which is mostly
lz4, zlib's CRC and ``os.write``, all done without the GIL; so that work (~1 ms
per 640x480 float image) leaves the frame loop's thread and runs on whichever
core has time. The calls reach the writer in the order they are made, so the
file is the one a direct writer makes; a writer error is raised by the next
call (and by :meth:`OutputBag.close`). A write that fails (a full disk, a
file size limit) stops the writer: the file reads to its last complete chunk,
as endo-record's does (:attr:`OutputBag.failure`, :attr:`OutputBag.on_disk`).
"""

from __future__ import annotations

import contextlib
import heapq
import queue
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from endo_io import topics
from endo_io.bag import BagError, BagMessage, BagWriter, TopicInfo
from endo_io.bag.serde import msgtype_of, serialize
from endo_io.image import array_to_image_cdr
from endo_io.tf import StampedTransform, TransformError, add_tf_topic, serialize_tf_message

#: The ROS type of the image topics.
IMAGE_TYPE = "sensor_msgs/msg/Image"
#: The ROS type of the pose topics.
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
#: The ROS type of the point cloud topics.
POINTS_TYPE = "sensor_msgs/msg/PointCloud2"
#: Flush the writer (close the current chunk) every this many frames.
DEFAULT_FLUSH_EVERY = 30
#: Writer calls queued for the writer thread at most (a few frames' outputs).
WRITE_QUEUE_CALLS = 64


def offered_qos(topic: str) -> str:
    """The ``offered_qos_profiles`` recorded for an output topic ("" for rosbag2's default).

    The live publisher's offer where it is not the default a replay falls
    back to (reliable, volatile): the map's, transient local
    (:data:`endo_io.qos.MAP_QOS`). Recorded as volatile, a replayed map
    reached no transient-local subscriber (endo-foxglove, the RViz config).
    """
    if topic != topics.MAP:
        return ""
    from endo_io.bag.qos_yaml import qos_profiles_to_yaml  # rclpy: only where it is needed
    from endo_io.qos import MAP_QOS

    return qos_profiles_to_yaml([MAP_QOS])


class _WriterThread:
    """A :class:`BagWriter` driven from one thread of its own, in call order.

    :meth:`call` queues ``writer.<method>(*args)`` (blocking while
    :data:`WRITE_QUEUE_CALLS` are queued); the first error the writer raises
    stops it: every later :meth:`call` raises it, and :meth:`close` closes
    the file and raises it if no call did.
    """

    def __init__(self, writer: BagWriter) -> None:
        self.writer = writer
        self._calls: queue.Queue[tuple[Callable[..., Any], tuple[Any, ...]] | None] = queue.Queue(
            WRITE_QUEUE_CALLS
        )
        self._error: BaseException | None = None
        self._raised = False
        self._thread = threading.Thread(target=self._run, name="endo-process writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self._calls.get()) is not None:
            if self._error is None:
                try:
                    item[0](*item[1])
                except BaseException as error:  # raised again in the caller
                    self._error = error

    def _check(self) -> None:
        if self._error is not None:
            self._raised = True
            raise self._error

    def call(self, method: Callable[..., Any], *args: Any) -> None:
        """Queue ``method(*args)`` (a bound method of :attr:`writer`)."""
        self._check()
        self._calls.put((method, args))

    def close(self) -> None:
        """Run what is queued, close the writer, end the thread; raise a writer error (once)."""
        if self._thread.is_alive():
            self._calls.put((self.writer.close, ()))
            self._calls.put(None)
            self._thread.join()
        error, self._error = self._error, None
        if error is not None:
            with contextlib.suppress(BagError):  # after a failed write: close the file only
                self.writer.close()
            if not self._raised:
                raise error


class _DirectWriter:
    """:class:`_WriterThread`'s interface, calling the writer at once in the caller's thread."""

    def __init__(self, writer: BagWriter) -> None:
        self.writer = writer

    def call(self, method: Callable[..., Any], *args: Any) -> None:
        """Call ``method(*args)`` now."""
        method(*args)

    def close(self) -> None:
        """Close the writer."""
        self.writer.close()


class OutputBag:
    """A :class:`BagWriter` with a merge of held-back small streams.

    Args:
        path: the output ``.mcap`` (never overwritten: BagError).
        compression: chunk compression, zstd | lz4 | none.
        copied_topics: topics copied from the input, name -> TopicInfo
            (their type and QoS offers are kept).
        threaded: write from a thread of its own (:class:`_WriterThread`),
            else in the caller's thread. With a worker process the runner
            writes directly: the main process waits for the worker anyway,
            and the thread's lz4 and CRC beside the worker slowed it
            (docs/benchmarks.md, "endo-process").
        crcs: store the chunks' CRC-32 (:class:`BagWriter`'s ``crcs``).
            ``endo-process`` leaves them out unless ``--chunk-crc`` is
            given, as rosbag2's MCAP plugin does by default (``noChunkCRC``):
            zlib's CRC over ~4 MB per 640×480 frame is CPU the two cores
            need for the solve (docs/process.md, "Output").
        direct: write with ``O_DIRECT`` (:class:`BagWriter`'s ``direct``);
            ``endo-process --no-direct`` turns it off.
        tap: called with (topic, CDR bytes) of every message as it is handed
            to the writer, in the file's order (``endo-process`` scores its
            output with it, :class:`endo_process.accuracy.RecordingScorer`,
            instead of reading the file back).
    """

    def __init__(
        self,
        path: Path,
        compression: str,
        copied_topics: dict[str, TopicInfo] | None = None,
        *,
        threaded: bool = True,
        crcs: bool = True,
        direct: bool = True,
        tap: Callable[[str, bytes], None] | None = None,
    ) -> None:
        writer = BagWriter(path, compression=compression, crcs=crcs, direct=direct)
        self.path = Path(path)
        self._tap = tap
        self.counts: Counter[str] = Counter()
        self._held: list[tuple[int, int, str, bytes]] = []
        self._order = 0
        for name, info in (copied_topics or {}).items():
            writer.add_topic(name, info.msgtype, info.offered_qos_profiles)
            self.counts[name] = 0
        self._writer = _WriterThread(writer) if threaded else _DirectWriter(writer)
        self._bag = writer  # its methods, called through the thread only

    @property
    def failure(self) -> str:
        """The writer's one-line error once a write failed (a full disk), "" while it works."""
        return self._bag.failure

    @property
    def on_disk(self) -> Counter[str]:
        """Messages per topic in complete chunks on disk (what a reader gets)."""
        return Counter({name: count for name, (count, _) in self._bag.written.items()})

    @property
    def lost(self) -> int:
        """Messages handed to the writer that a failed write kept off the disk."""
        return self._bag.lost

    def _declare(self, topic: str, msgtype: str) -> None:
        """Add an output topic to the file, with its live publisher's offered QoS."""
        self._writer.call(self._bag.add_topic, topic, msgtype, offered_qos(topic))
        self.counts[topic] = 0

    def hold(self, topic: str, message: Any, log_time_ns: int) -> None:
        """Queue a small message; it is written once frame outputs pass its time."""
        if topic not in self.counts:
            self._declare(topic, msgtype_of(message))
        heapq.heappush(self._held, (int(log_time_ns), self._order, topic, serialize(message)))
        self._order += 1

    def hold_cdr(self, topic: str, msgtype: str, data: bytes, log_time_ns: int) -> None:
        """Queue a small message already serialised (CDR bytes of ``msgtype``), as :meth:`hold`."""
        if topic not in self.counts:
            self._declare(topic, msgtype)
        heapq.heappush(self._held, (int(log_time_ns), self._order, topic, data))
        self._order += 1

    def hold_tf(self, topic: str, transforms: list[StampedTransform], log_time_ns: int) -> None:
        """Queue a ``tf2_msgs/msg/TFMessage`` on ``/tf`` or ``/tf_static`` (built by endo_io.tf)."""
        if not transforms:
            raise TransformError(f"{topic}: a tf message needs at least one transform")
        if topic not in self.counts:
            self._writer.call(add_tf_topic, self._bag, topic)
            self.counts[topic] = 0
        heapq.heappush(
            self._held, (int(log_time_ns), self._order, topic, serialize_tf_message(transforms))
        )
        self._order += 1

    def copy_until(
        self, messages: Iterator[BagMessage], pending: list[BagMessage], until_ns: int
    ) -> None:
        """Move copied messages with log time <= ``until_ns`` from the stream into the queue.

        ``pending`` holds the one message read past ``until_ns`` between calls.
        """
        while True:
            if not pending:
                message = next(messages, None)
                if message is None:
                    return
                pending.append(message)
            message = pending[0]
            if message.log_time_ns > until_ns:
                return
            pending.pop()
            heapq.heappush(
                self._held, (message.log_time_ns, self._order, message.topic, bytes(message.data))
            )
            self._order += 1

    def release(self, until_ns: int | None = None) -> None:
        """Write the held messages with log time <= ``until_ns`` (all when None)."""
        while self._held and (until_ns is None or self._held[0][0] <= until_ns):
            log_time, _, topic, data = heapq.heappop(self._held)
            self._hand(topic, data, log_time)

    def _hand(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """One message to the writer (and the tap)."""
        self._writer.call(self._bag.write, topic, data, log_time_ns)
        self.counts[topic] += 1
        if self._tap is not None:
            self._tap(topic, data)

    def write(self, topic: str, message: Any, log_time_ns: int) -> None:
        """Write one frame output now, after every held message that is not later."""
        if topic not in self.counts:
            self._declare(topic, msgtype_of(message))
        self.release(log_time_ns)
        self._hand(topic, serialize(message), log_time_ns)

    def write_cdr(self, topic: str, msgtype: str, data: bytes, log_time_ns: int) -> None:
        """Write one frame output given as CDR bytes of ``msgtype``, as :meth:`write` does."""
        if topic not in self.counts:
            self._declare(topic, msgtype)
        self.release(log_time_ns)
        self._hand(topic, data, log_time_ns)

    def write_image(
        self, topic: str, array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str
    ) -> None:
        """Write one ``sensor_msgs/Image`` now, encoded straight from ``array``.

        The bytes are those of ``array_to_image`` serialised
        (:func:`endo_io.image.array_to_image_cdr`), built with one copy of
        the pixels instead of five.
        """
        if topic not in self.counts:
            self._declare(topic, IMAGE_TYPE)
        self.release(stamp_ns)
        self._hand(topic, array_to_image_cdr(array, encoding, stamp_ns, frame_id), stamp_ns)

    def flush(self) -> None:
        """Close the current chunk so that it survives a crash (in the writer thread, in turn)."""
        self._writer.call(self._bag.flush)

    def close(self, until_ns: int | None = None) -> None:
        """Write what is held (up to ``until_ns``; the rest is dropped), then finalise the file.

        Idempotent. ``until_ns`` ends a partial run (``--max-frames``, a stop)
        at its last frame, so the file covers only the time processed.
        """
        try:
            self.release(until_ns)
        finally:
            self._held.clear()
            self._writer.close()
