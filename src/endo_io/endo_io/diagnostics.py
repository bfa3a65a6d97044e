"""Per-node input health: drop bad messages, log one line, count in /diagnostics.

Every endo3d node wraps its subscription callbacks with
:meth:`InputHealth.guard`. A callback that raises is not allowed to take the
node down: the message is dropped, the cause (the exception class name) and
its one-line message are logged (throttled, so a stream of bad frames does
not flood the console), and the per-cause counters are published on
``/diagnostics`` as a ``diagnostic_msgs/DiagnosticArray`` once per period,
where ``rqt_runtime_monitor`` and Foxglove's diagnostics panel show them.
"""

from __future__ import annotations

import functools
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, TypeVar

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from endo_io.errors import Endo3dError
from endo_io.qos import reliable_qos

F = TypeVar("F", bound=Callable[..., Any])

DIAGNOSTICS_TOPIC = "/diagnostics"


class InputHealth:
    """Counts processed and dropped messages of one node and reports them.

    Args:
        node: The node that owns the counters; its name prefixes the status name.
        name: What is being monitored, e.g. ``"image input"``.
        period_s: Publishing period of ``/diagnostics`` in seconds.
        log_throttle_s: Minimum interval between two log lines of the same cause.
    """

    def __init__(
        self,
        node: Node,
        name: str = "input",
        period_s: float = 1.0,
        log_throttle_s: float = 1.0,
    ) -> None:
        self._node = node
        self._name = f"{node.get_name()}: {name}"
        self._log_throttle_s = log_throttle_s
        self.processed = 0
        self.dropped: Counter[str] = Counter()
        self.last_error = ""
        self._last_log: dict[str, float] = {}
        self._extra: dict[str, str] = {}
        self._publisher = node.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, reliable_qos(10)
        )
        self._timer = node.create_timer(period_s, self.publish)

    def ok(self) -> None:
        """Count one message processed successfully."""
        self.processed += 1

    def set_value(self, key: str, value: object) -> None:
        """Report an extra key/value (e.g. a latency figure) with the next status."""
        self._extra[key] = str(value)

    def drop(self, cause: str, message: str) -> None:
        """Count one dropped message under ``cause`` and log ``message`` (throttled)."""
        self.dropped[cause] += 1
        self.last_error = f"{cause}: {message}"
        now = time.monotonic()
        if now - self._last_log.get(cause, -1e18) >= self._log_throttle_s:
            self._last_log[cause] = now
            total = self.dropped[cause]
            self._node.get_logger().error(f"dropped message ({total} so far): {self.last_error}")

    def guard(self, callback: F) -> F:
        """Wrap a callback so that any exception drops that message only.

        Named :class:`~endo_io.errors.Endo3dError` subclasses are expected bad
        input; any other exception is a bug, but a bug on one frame must not
        stop a node beside a surgery either, so it is counted the same way
        under its class name.
        """

        @functools.wraps(callback)
        def guarded(*args: Any, **kwargs: Any) -> Any:
            try:
                result = callback(*args, **kwargs)
            except Endo3dError as error:
                self.drop(type(error).__name__, str(error))
                return None
            except Exception as error:  # the node must keep running
                self.drop(type(error).__name__, f"unexpected: {error}")
                return None
            self.ok()
            return result

        return guarded  # type: ignore[return-value]

    def status(self) -> DiagnosticStatus:
        """The current counters as one ``DiagnosticStatus``."""
        total_dropped = sum(self.dropped.values())
        level = DiagnosticStatus.OK if total_dropped == 0 else DiagnosticStatus.WARN
        message = "ok" if total_dropped == 0 else f"{total_dropped} dropped; last {self.last_error}"
        values = [KeyValue(key="processed", value=str(self.processed))]
        values.append(KeyValue(key="dropped", value=str(total_dropped)))
        values += [
            KeyValue(key=f"dropped.{cause}", value=str(count))
            for cause, count in sorted(self.dropped.items())
        ]
        values += [KeyValue(key=k, value=v) for k, v in sorted(self._extra.items())]
        return DiagnosticStatus(
            level=level,
            name=self._name,
            message=message[:512],
            hardware_id=self._node.get_fully_qualified_name(),
            values=values,
        )

    def publish(self) -> None:
        """Publish the current status on ``/diagnostics``."""
        array = DiagnosticArray()
        array.header.stamp = self._node.get_clock().now().to_msg()
        array.status = [self.status()]
        self._publisher.publish(array)
