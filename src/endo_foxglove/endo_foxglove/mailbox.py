"""A newest-wins mailbox between the DDS callbacks and the bridge's sending thread.

Each topic holds at most one pending message. A message that arrives while
the previous one of its topic is still pending replaces it, and the replaced
one is counted as superseded: a viewer that cannot keep up sees the newest
frame, late, never a queue of old ones, and the DDS callbacks never wait.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Generic, TypeVar

T = TypeVar("T")


class NewestWins(Generic[T]):
    """Per-key single-slot mailbox; thread-safe.

    ``put`` never blocks; ``take`` waits for the pending items and empties
    the mailbox. ``superseded[key]`` counts the items replaced before they
    were taken.
    """

    def __init__(self) -> None:
        self._pending: dict[str, T] = {}
        self._condition = threading.Condition()
        self._closed = False
        self.superseded: Counter[str] = Counter()

    def put(self, key: str, item: T) -> None:
        """Leave ``item`` for ``key``, replacing (and counting) a pending one."""
        with self._condition:
            if key in self._pending:
                self.superseded[key] += 1
                del self._pending[key]  # re-insert: items are taken in arrival order
            self._pending[key] = item
            self._condition.notify()

    def take(self, timeout_s: float) -> list[tuple[str, T]]:
        """Every pending ``(key, item)`` in arrival order; [] after ``timeout_s`` or close."""
        with self._condition:
            if not self._pending and not self._closed:
                self._condition.wait(timeout_s)
            items = list(self._pending.items())
            self._pending.clear()
            return items

    def close(self) -> None:
        """Wake a waiting ``take``; later takes return at once."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` was called."""
        return self._closed
