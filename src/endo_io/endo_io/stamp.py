"""Conversions between ``builtin_interfaces/Time`` stamps and integer nanoseconds.

Integer nanoseconds are the one time representation inside endo3d: they are
what MCAP stores, they compare exactly, and they never lose precision the way
float seconds do after a few days of epoch time.
"""

from __future__ import annotations

from builtin_interfaces.msg import Time

NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp: Time) -> int:
    """Return a ``builtin_interfaces/Time`` as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Return integer nanoseconds (>= 0) as a ``builtin_interfaces/Time``."""
    if ns < 0:
        raise ValueError(f"stamp must be non-negative, got {ns} ns")
    sec, nanosec = divmod(int(ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)
