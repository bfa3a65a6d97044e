"""A recording written on a thread of its own, so taking messages never waits for the disk.

``endo-record`` takes what waits in its subscriptions every ``--take-period``
(:mod:`endo_io.record_node`). When writing ran in that same thread, a write
that waited for the disk, or a recorder starved of CPU while it compressed a
chunk, left the messages in the middleware's subscription histories
(``--queue-depth``, 100 per topic: ~3 s of images at 30 Hz, ~1.7 s of
250 Hz poses), and what overflowed them was lost without a trace.

:class:`BackgroundWriter` splits the two: the node's thread only takes the
bytes and queues them; a writer thread checks, frames, compresses and writes
them into the :class:`~endo_io.record.Recording`, and flushes a chunk every
flush period. The queue is bounded in payload bytes (``--buffer-mb``): a
message that would exceed it is refused, counted per topic and reported as
lost with the reason, never dropped silently. The writer thread can run at a
lower priority than the taking (``--writer-nice``; Linux sets niceness per
thread), so that in a graph on a busy machine the frames' path gets the CPU
first and the recorder keeps taking: the graph runs of ``endo-demo`` and the
benches niced the whole recorder process before, and under sustained load
its subscriptions overflowed (docs/benchmarks.md, "Session 13").

Every call that writes through the :class:`~endo_io.record.Recording`
happens on the writer thread while it runs, a new topic's declaration
included (:meth:`BackgroundWriter.add_topic` queues it in order with the
messages: the schema and channel records go into the chunk being filled,
and a bag directory's metadata.yaml is rewritten; from two threads at once
that corrupted bags, found in review); :meth:`BackgroundWriter.close`
drains the queue and joins it, after which the caller closes the recording.
Any exception on the writer thread stops it with that error, as a failed
write does: the thread never ends unseen.
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

from endo_io.errors import BagError
from endo_io.record import CdrCheck, RecordedTopic, Recording

__all__ = ["BackgroundWriter", "WriterState"]

#: Default bound of the queue's payload bytes (``--buffer-mb``): ~4 s of a live
#: graph's topics at 30 Hz (raw, corrected, relative and metric depth, cloud).
DEFAULT_BUFFER_BYTES = 512 * 1024 * 1024


@dataclass(frozen=True)
class WriterState:
    """Why the writer stopped taking messages (both empty: it has not).

    limit: the recording's stop reason (a message or duration limit);
    error: what stopped the writer thread: a failed write (a full disk, a
    vanished file) or any other exception raised on it.
    """

    limit: str = ""
    error: BaseException | None = None


class BackgroundWriter:
    """Queue messages for a :class:`~endo_io.record.Recording` written on its own thread.

    Args:
        recording: the recording to write; every call on it happens on the
            writer thread until :meth:`close` returns.
        max_bytes: bound of the queued payload bytes (> 0); a message that
            would exceed it is refused and counted (:attr:`refused`).
        nice: added to the writer thread's niceness (>= 0; Linux: per thread,
            elsewhere ignored).
        flush_period_s: the writer closes the current chunk this often (> 0),
            so that a killed recorder leaves a file that reads up to it.
    """

    def __init__(self, recording: Recording, *, max_bytes: int = DEFAULT_BUFFER_BYTES,
                 nice: int = 0, flush_period_s: float = 1.0) -> None:
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be > 0, got {max_bytes}")
        if nice < 0:
            raise ValueError(f"nice must be >= 0, got {nice}")
        if not flush_period_s > 0:
            raise ValueError(f"flush_period_s must be > 0, got {flush_period_s}")
        self._recording = recording
        self._max_bytes = max_bytes
        self._nice = nice
        self._flush_period_s = flush_period_s
        # messages (topic, data, log time, publish time) and topic declarations, in order
        self._queue: deque[tuple[str, bytes, int, int | None] | Callable[[], None]] = deque()
        self._msgtypes: dict[str, str] = {}
        self._queued_bytes = 0
        self._lock = threading.Condition()
        self._closing = False
        self._state = WriterState()
        #: messages refused per topic because the queue was full
        self.refused: Counter[str] = Counter()
        self._unwritten: Counter[str] = Counter()  # queued when a write failed
        #: the most bytes the queue held at once
        self.peak_bytes = 0
        self.thread_nice: int | None = None  # the writer thread's niceness, once it runs
        self._thread = threading.Thread(target=self._run, name="endo_record_writer",
                                        daemon=True)
        self._thread.start()

    @property
    def state(self) -> WriterState:
        """Whether the writer stopped (a limit, a failed write); read by the taking thread."""
        return self._state

    def add_topic(self, name: str, msgtype: str, offered_qos_profiles: str,
                  check: CdrCheck | None = None) -> None:
        """Declare a topic (:meth:`Recording.add_topic`) on the writer thread, before its data."""
        with self._lock:
            self._msgtypes[name] = msgtype
            self._queue.append(lambda: self._recording.add_topic(name, msgtype,
                                                                 offered_qos_profiles, check))
            self._lock.notify()

    def put(self, topic: str, data: bytes, log_ns: int, publish_ns: int | None = None) -> bool:
        """Queue one message; False when it is refused (queue full) or the writer stopped.

        A message larger than the whole bound is taken only when nothing at
        all is held (queued or being written), so the bound is exceeded by
        at most that one message.
        """
        with self._lock:
            if self._closing or self._state.limit or self._state.error is not None:
                return False
            if self._queued_bytes + len(data) > self._max_bytes and self._queued_bytes > 0:
                self.refused[topic] += 1
                return False
            self._queue.append((topic, data, log_ns, publish_ns))
            self._queued_bytes += len(data)
            self.peak_bytes = max(self.peak_bytes, self._queued_bytes)
            self._lock.notify()
        return True

    def close(self) -> None:
        """Write everything queued, flush, and stop the thread (idempotent).

        The refused messages are then counted into the recording's report as
        received and lost, with the reason.
        """
        with self._lock:
            if self._closing:
                return
            self._closing = True
            self._lock.notify()
        self._thread.join()
        report = self._recording.report
        for topic, count in (self._unwritten + self.refused).items():
            # a topic whose declaration the stopped writer never reached is counted too
            tally = report.topics.setdefault(topic, RecordedTopic(self._msgtypes.get(topic, "")))
            tally.received += count
        error = self._state.error
        if error is not None and not isinstance(error, (BagError, OSError)):
            report.write_error = report.write_error or (
                f"the writer thread failed: {type(error).__name__}: {error}")
        if self.refused:
            reason = (f"{sum(self.refused.values())} refused: the write queue held "
                      f"{self._max_bytes / 2**20:.0f} MB (--buffer-mb) while the disk or "
                      "the writer thread fell behind")
            report.write_error = "; ".join(r for r in (report.write_error, reason) if r)

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as error:
            with self._lock:
                self._state = WriterState(error=error)
                self._drop_queued()

    def _loop(self) -> None:
        self.thread_nice = _lower_thread_priority(self._nice)
        next_flush = time.monotonic() + self._flush_period_s
        while True:
            with self._lock:
                while not self._queue and not self._closing:
                    if not self._lock.wait(max(0.0, next_flush - time.monotonic())):
                        break  # the flush period passed with nothing to write
                batch = list(self._queue)
                self._queue.clear()
                closing = self._closing
            stopped = self._write(batch)
            with self._lock:
                self._queued_bytes -= sum(len(m[1]) for m in batch if isinstance(m, tuple))
            if not stopped and time.monotonic() >= next_flush:
                stopped = self._flush()
                next_flush = time.monotonic() + self._flush_period_s
            if stopped:
                with self._lock:
                    self._drop_queued()
                return
            if closing:
                return

    def _write(self, batch: list[tuple[str, bytes, int, int | None] | Callable[[], None]]
               ) -> bool:
        """Write a batch; True when the recording stopped (a limit or a failed write)."""
        for k, item in enumerate(batch):
            if not isinstance(item, tuple):
                item()  # a topic's declaration
                continue
            topic, data, log_ns, publish_ns = item
            try:
                if self._recording.write(topic, data, log_ns, publish_ns):
                    self._state = WriterState(limit=self._recording.report.stop_reason
                                              or "limit reached")
                    return True
            except BaseException as error:
                # the failed message is counted by the recording; the batch's rest here
                self._unwritten.update(m[0] for m in batch[k + 1:] if isinstance(m, tuple))
                self._state = WriterState(error=error)
                return True
        return False

    def _flush(self) -> bool:
        try:
            self._recording.flush()
        except (BagError, OSError) as error:
            self._state = WriterState(error=error)
            return True
        return False

    def _drop_queued(self) -> None:
        """Drop what is still queued once the writer stopped.

        After a failed write it counts as refused (received, not in the
        file); after a limit it is what the limit leaves out, as before the
        limit: not counted.
        """
        if self._state.error is not None:
            for item in self._queue:
                if isinstance(item, tuple):
                    self._unwritten[item[0]] += 1
        self._queue.clear()
        self._queued_bytes = 0


def _lower_thread_priority(nice: int) -> int | None:
    """Add ``nice`` to the calling thread's niceness; returns it (None: not supported)."""
    if not hasattr(os, "setpriority"):
        return None
    tid = threading.get_native_id()
    current = os.getpriority(os.PRIO_PROCESS, tid)
    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, tid, min(current + nice, 19))
        except OSError:
            return current
    return os.getpriority(os.PRIO_PROCESS, tid)
