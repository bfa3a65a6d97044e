"""A tracker source that reads on a thread of its own.

Network and serial trackers block while they wait for data, so each runs a
producer loop on a daemon thread. Raw items (a received OpenIGTLink frame, an
NDI tool reading, a log row) go into a bounded queue and the owner is woken
through ``notify``. The owner drains the queue on its own thread and converts
each item with :meth:`BackgroundSource.to_sample`, so that a bad item raises
inside the owner's input guard and is counted there, one item at a time.
"""

from __future__ import annotations

import abc
import collections
import threading
import time
from collections.abc import Callable
from typing import Any

from endo_tracker_bridge.sample import TrackerSample

#: Raw items kept when the owner falls behind; the oldest go first (a pose
#: that old is of no use to a live consumer anyway).
DEFAULT_QUEUE_LENGTH = 256
#: Shortest interval between two lines of one repeated message (s).
LOG_THROTTLE_S = 10.0


def _ignore(_: str) -> None:
    return None


class BackgroundSource(abc.ABC):
    """Base of the sources that read on their own thread.

    Subclasses implement :meth:`_run` (the producer loop, which calls
    :meth:`_emit` per raw item and returns when ``stop`` is set) and
    :meth:`to_sample`.
    """

    def __init__(
        self, log: Callable[[str], None] | None = None, queue_length: int = DEFAULT_QUEUE_LENGTH
    ) -> None:
        self._log = log or _ignore
        self._queue: collections.deque[Any] = collections.deque(maxlen=queue_length)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._notify: Callable[[], None] = lambda: None
        self._status: dict[str, str] = {}
        self._throttle: dict[str, tuple[float, int]] = {}
        self.overflowed = 0

    def start(self, notify: Callable[[], None]) -> None:
        """Start the producer thread; ``notify()`` is called after each new item."""
        if self._thread is not None:
            return
        self._notify = notify
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run_safely, name=type(self).__name__, daemon=True
        )
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Ask the producer loop to end and wait up to ``timeout_s`` for it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def drain(self) -> list[Any]:
        """Take every queued raw item, oldest first."""
        with self._lock:
            items = list(self._queue)
            self._queue.clear()
        return items

    def status(self) -> dict[str, str]:
        """Key/values describing the connection, for ``/diagnostics``."""
        with self._lock:
            status = dict(self._status)
        status["queue_overflows"] = str(self.overflowed)
        return status

    def _set_status(self, **values: object) -> None:
        with self._lock:
            self._status.update({k: str(v) for k, v in values.items()})

    def _log_throttled(self, key: str, text: str, interval_s: float = LOG_THROTTLE_S) -> None:
        """Log ``text`` at most once per ``interval_s`` for ``key``, saying how many were held back.

        For messages a broken peer repeats several times a second (a junk
        stream that is reconnected and fails again).
        """
        now = time.monotonic()
        last, held = self._throttle.get(key, (-float("inf"), 0))
        if now - last < interval_s:
            self._throttle[key] = (last, held + 1)
            return
        self._throttle[key] = (now, 0)
        self._log(text + (f" ({held} more like this in {now - last:.0f} s)" if held else ""))

    def _emit(self, item: Any) -> None:
        with self._lock:
            if len(self._queue) == self._queue.maxlen:
                self.overflowed += 1
            self._queue.append(item)
        self._notify()

    def _run_safely(self) -> None:
        # The producer must never die silently: a bug in one loop iteration is
        # logged and the loop restarts after a pause.
        while not self._stop.is_set():
            try:
                self._run(self._stop)
                return
            except Exception as error:
                self._log(f"{type(self).__name__} loop failed: {type(error).__name__}: {error}")
                self._stop.wait(1.0)

    @abc.abstractmethod
    def _run(self, stop: threading.Event) -> None:
        """Producer loop: read the tracker, call :meth:`_emit`, return once ``stop`` is set."""

    @abc.abstractmethod
    def to_sample(self, item: Any) -> TrackerSample:
        """Convert one raw item to a sample; raise a TrackerSampleError if it is bad."""
