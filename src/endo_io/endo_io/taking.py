"""Subscriptions whose messages a node takes when it wants them, not one callback each.

rclpy's executor wakes up for every message of every subscription, and each
wake-up rebuilds its whole wait set (every subscription, timer, service and
guard condition of the node): ~0.2–0.5 ms of Python here, more than the work
of a small message. A subscription in :class:`NeverExecutedGroup` is never
put in the wait set: its messages wait in its DDS history (its QoS depth)
until the node takes them with :func:`take_waiting`, e.g. the image of a
frame when its depth arrives (flow) or everything received since the last
tick of a timer (the recorder).

A subscription in an :class:`OnDemandGroup` is such a subscription, except
while the node asks to be woken by its next message (``waited``): e.g. the
poses, while a frame waits for the pose after its stamp (flow), so that the
frame goes as soon as that pose arrives, without a polling timer.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from rclpy.callback_groups import CallbackGroup
from rclpy.subscription import Subscription

_LOG = logging.getLogger(__name__)

#: Whether the missing receive time was said (once per process).
_warned_no_receive_time = False


class NeverExecutedGroup(CallbackGroup):
    """A callback group whose entities the executor never waits on nor runs."""

    def can_execute(self, entity: Any) -> bool:
        """Never: the node takes the messages itself (:func:`take_waiting`)."""
        return False

    def beginning_execution(self, entity: Any) -> bool:
        """Never (see :meth:`can_execute`)."""
        return False


class OnDemandGroup(CallbackGroup):
    """A callback group whose entities the executor waits on and runs only while ``waited``.

    Attributes:
        waited: whether the executor waits on the group's entities. Read at
            each rebuild of the executor's wait set (after every callback),
            so a change made in a callback applies from the next wait on.
    """

    def __init__(self) -> None:
        super().__init__()
        self.waited = False

    def can_execute(self, entity: Any) -> bool:
        """While :attr:`waited`."""
        return self.waited

    def beginning_execution(self, entity: Any) -> bool:
        """While :attr:`waited` (a message that came as it stopped stays for a take)."""
        return self.waited

    def ending_execution(self, entity: Any) -> None:
        """Nothing to release (callbacks of the group may run side by side)."""


def take_waiting(subscription: Subscription, raw: bool = True) -> list[tuple[Any, int]]:
    """Every message waiting in ``subscription``, oldest first.

    Args:
        subscription: any rclpy subscription (usually one of a
            :class:`NeverExecutedGroup`).
        raw: take the serialized bytes (True) or a deserialized message.

    Returns:
        (message, received_ns) pairs: the message (``bytes`` when ``raw``)
        and when the middleware received it, integer ns on the system clock
        (``time.time_ns``; the take time when the middleware does not say).
    """
    return [(data, received) for data, received, _ in take_waiting_timed(subscription, raw)]


def take_waiting_timed(subscription: Subscription,
                       raw: bool = True) -> list[tuple[Any, int, int | None]]:
    """:func:`take_waiting`, each message also with its DDS source timestamp.

    Returns:
        (message, received_ns, source_ns) triples: ``source_ns`` is when the
        publisher wrote it (DDS's source timestamp, integer ns on the
        publisher's system clock: rosbag2 records it as the publish time), or
        None when the middleware does not say.
    """
    found: list[tuple[Any, int, int | None]] = []
    handle = subscription.handle
    while True:
        with handle:
            taken = handle.take_message(subscription.msg_type, raw)
        if taken is None:
            return found
        data, info = taken
        received = source = None
        if isinstance(info, dict):
            received, source = info.get("received_timestamp"), info.get("source_timestamp")
        found.append((data, int(received) if received else _take_time(),
                      int(source) if source else None))


def _take_time() -> int:
    """Now, for a middleware that gives no receive time (said once: its order is the take's)."""
    global _warned_no_receive_time
    if not _warned_no_receive_time:
        _warned_no_receive_time = True
        _LOG.warning("the middleware gives no receive time (received_timestamp): messages "
                     "taken in batches are timed when taken, up to one take period late")
    return time.time_ns()


def system_to_monotonic_ns(system_ns: int) -> int:
    """A system-clock time (``time.time_ns``) on the monotonic clock, as of now."""
    return time.monotonic_ns() - max(time.time_ns() - system_ns, 0)
