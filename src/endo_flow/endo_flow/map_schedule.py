"""When the live map may go while frames come: a period that grows with its size.

The map message is the whole map (PointCloud2, 32 bytes per voxel): ~24 MB
after a minute of colon video, 64 MB at ``map_max_voxels`` 2 M. Sent every
``map_period_s`` it crossed DDS and the recorder at ~12 MB/s, and each send
held the flow node's thread (~15 ms for 24 MB: the records, the CDR, the
copy into DDS) and the recorder, bursts that made the graph skip frames
(docs/flow.md, "The map's publishing budget"). A byte budget bounds that
cost whatever the map's size: after a message of B bytes the next waits
B / ``bandwidth`` seconds, and at least the period.

ROS-free: the flow node asks :meth:`MapPublishSchedule.due` after each frame
and calls :meth:`MapPublishSchedule.published` after each send. While the
frames have stopped the node publishes a changed map every period without
asking (nothing competes with it then, and viewers and recorders get the
final map promptly).
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
        bandwidth_mb_s: the budget, megabytes (1e6 bytes) per second; 0
            means none (every ``period_s``).
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
        """Seconds a message of ``n_bytes`` holds the next one back."""
        if self.bandwidth_mb_s == 0:
            return self.period_s
        return max(self.period_s, n_bytes / (self.bandwidth_mb_s * BYTES_PER_MB))

    def due(self, now_s: float) -> bool:
        """Whether the map may go at ``now_s`` (a monotonic clock, seconds)."""
        return now_s >= self._next_s

    def reset(self) -> None:
        """Let the next message go at once (the map was emptied: no budget to wait out)."""
        self._next_s = float("-inf")

    def published(self, now_s: float, n_bytes: int) -> None:
        """Record a message of ``n_bytes`` sent at ``now_s``."""
        self._next_s = now_s + self.interval_s(n_bytes)
