"""When the live map is published: a period that grows with the map's size.

The map message is the whole map (PointCloud2, 32 bytes per voxel): ~24 MB
after a minute of colon video, 64 MB at ``map_max_voxels`` 2 M. Sent every
``map_period_s`` it crossed DDS and the recorder at ~12 MB/s, and each send
cost the flow node's thread and the recorder a burst that made the graph
skip frames (docs/flow.md, "The map's publishing budget"). A byte budget
bounds that cost whatever the map's size: after a message of B bytes the
next waits B / ``bandwidth`` seconds (and at least the period). While the
frames have stopped (a bag's end, a paused camera) the map goes at the
period: nothing competes with it then, and a viewer or recorder gets the
final map promptly.

ROS-free: the node calls :meth:`MapPublishSchedule.due` from a timer of
period ``period_s`` and :meth:`MapPublishSchedule.published` after each send.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["MapPublishSchedule"]

BYTES_PER_MB = 1e6


@dataclass
class MapPublishSchedule:
    """The next time the map may go, from the bytes of the last message sent.

    Args:
        period_s: the shortest interval between two messages, seconds (> 0).
        bandwidth_mb_s: the budget, megabytes (1e6 bytes) per second while
            frames come; 0 means none (every ``period_s``).
    """

    period_s: float
    bandwidth_mb_s: float
    _next_s: float = field(default=float("-inf"), init=False)

    def __post_init__(self) -> None:
        if not self.period_s > 0:
            raise ValueError(f"period_s must be > 0, got {self.period_s}")
        if not self.bandwidth_mb_s >= 0:
            raise ValueError(f"bandwidth_mb_s must be >= 0, got {self.bandwidth_mb_s}")

    def interval_s(self, n_bytes: int) -> float:
        """Seconds a message of ``n_bytes`` holds the next one back while frames come."""
        if self.bandwidth_mb_s == 0:
            return self.period_s
        return max(self.period_s, n_bytes / (self.bandwidth_mb_s * BYTES_PER_MB))

    def due(self, now_s: float, *, frames_paused: bool) -> bool:
        """Whether the map may go at ``now_s`` (a monotonic clock, seconds).

        ``frames_paused``: no frame has come for a while; the budget is then
        not applied (the period still is, by the caller's timer).
        """
        # half a period of slack: the caller's timer ticks every period_s, and a
        # tick a hair early must not hold the map back a whole period more
        return frames_paused or now_s >= self._next_s - 0.5 * self.period_s

    def published(self, now_s: float, n_bytes: int) -> None:
        """Record a message of ``n_bytes`` sent at ``now_s``."""
        self._next_s = now_s + self.interval_s(n_bytes)
