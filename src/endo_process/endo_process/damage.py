"""Where a damaged recording lost messages, relative to the frames a run processed.

The bag reader says, for each damaged region, which messages it cost by log
time (:class:`endo_io.bag.DamagedRegion`: a lost chunk's time range, or
everything after the last message read for a cut). :func:`place_damage`
puts each region against the log times of the images the run read, and
:func:`damage_line` says the most serious one in one line:

* ``before`` / ``inside``: messages lost before the first frame read, or
  between the first and what the last one needs (its log time plus the
  reach of its pose lookup, ``reach_ns``): a corrupt chunk in the middle
  (the frames after it were processed, the ones in it are missing), or one
  right after the last frame that held its tracker samples;
* ``end``: the run read every image that could be read and the messages
  lost come after what the last one needs (a cut: "cut short"; or a lost
  chunk at the end);
* ``after``: the run stopped (``--max-frames``, a stop request) before the
  damage and before what its frames need: it was not met;
* ``none``: the region cost no message (a metadata record, the closing
  magic).

Every class but ``after`` makes the run's exit status "damaged" (1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from endo_io.bag import DamagedRegion
from endo_io.stamp import NS_PER_S

#: Where a region lies relative to the frames processed (see the module docstring).
Placement = Literal["before", "inside", "end", "after", "none"]

#: The placements said first when a recording has several regions (most serious first).
_ORDER: tuple[Placement, ...] = ("inside", "before", "end", "none", "after")


@dataclass(frozen=True)
class PlacedDamage:
    """A damaged region of the input and where it lies against the frames processed.

    Attributes:
        region: The reader's region (file, byte offset, reason, log times lost).
        where: See :data:`Placement`.
        images_lost: Image messages it cost, as the file's message indexes
            count them; None when they do not say.
    """

    region: DamagedRegion
    where: Placement
    images_lost: int | None


def place_damage(
    regions: list[DamagedRegion],
    image_topic: str,
    frames_log_ns: tuple[int, int] | None,
    read_to_end: bool,
    *,
    reach_ns: int = 0,
) -> list[PlacedDamage]:
    """Place each region against the frames a run read.

    Args:
        regions: The damaged regions the run's readers found.
        image_topic: The image topic (its lost messages are counted).
        frames_log_ns: (first, last) log time in ns of the images read;
            None if none was.
        read_to_end: Whether the run read the image stream to its end (it
            did not stop at ``--max-frames`` or a stop request).
        reach_ns: How far past the last image's log time the frames read
            still need messages: a frame's pose is interpolated from tracker
            samples up to the pose buffer's gap (plus the hand-eye clock
            offset) after its stamp, so a chunk lost within it may have cost
            the last frames their poses and is not "after" them.

    Returns:
        One placement per region, in the order given.
    """
    placed = []
    for region in regions:
        counts = region.lost_counts
        images = None if counts is None else counts.get(image_topic, 0)
        where = _where(region, frames_log_ns, read_to_end, reach_ns)
        placed.append(PlacedDamage(region, where, images))
    return placed


def _where(
    region: DamagedRegion, frames_log_ns: tuple[int, int] | None, read_to_end: bool,
    reach_ns: int,
) -> Placement:
    if region.lost == "none":
        return "none"
    past: Placement = "end" if read_to_end else "after"
    if frames_log_ns is None:
        return past
    first, last = frames_log_ns
    start = region.start_ns
    if region.lost == "rest":
        # A cut strictly before the last frame: another file of a split bag
        # went on past it, so messages among the frames were lost.
        if start is None or start < last:
            return "inside"
        if read_to_end:
            return "end"
        return "after" if start > last + reach_ns else "inside"
    if start is None or region.end_ns is None:  # a chunk whose header's times are damaged
        return "inside" if read_to_end else "after"
    if start > last + reach_ns:  # beyond what the frames read need (their poses included)
        return past
    return "before" if region.end_ns < first else "inside"


def most_serious(placed: list[PlacedDamage]) -> PlacedDamage | None:
    """The placement said in the run's one line: inside, before, end, none, after; None if none."""
    for where in _ORDER:
        for item in placed:
            if item.where == where:
                return item
    return None


def _seconds(ns: int, origin_ns: int) -> str:
    return f"{(ns - origin_ns) / NS_PER_S:.3f} s"


def _lost_what(item: PlacedDamage, origin_ns: int) -> str:
    """``logged 0.400-0.533 s into the recording, 4 images by its index``."""
    region = item.region
    if region.start_ns is None:
        when = "at log times the file does not say"
    elif region.end_ns is None:
        when = f"logged from {_seconds(region.start_ns, origin_ns)} into the recording on"
    else:
        when = (f"logged {_seconds(region.start_ns, origin_ns)} to "
                f"{_seconds(region.end_ns, origin_ns)} into the recording")  # fmt: skip
    if item.images_lost is None:
        images = "how many images, the file's index does not say"
    else:
        plural = "" if item.images_lost == 1 else "s"
        images = f"{item.images_lost} image{plural} by the file's index"
    return f"{when}, {images}"


def damage_line(
    placed: list[PlacedDamage], frames_read: int, origin_ns: int, stopped_by: str
) -> str:
    """The one line a run says about its input's damage ("" when there is none).

    Args:
        placed: :func:`place_damage`'s placements.
        frames_read: Images the run read.
        origin_ns: The recording's first log time (times are said from it).
        stopped_by: Why the run stopped early (``--max-frames``,
            ``interrupted``), for damage after the frames processed.
    """
    item = most_serious(placed)
    if item is None:
        return ""
    region = item.region
    others = len(placed) - 1
    more = f"; {others} more damaged region{'' if others == 1 else 's'}" if others else ""
    frames = f"{frames_read} image{'' if frames_read == 1 else 's'}"
    if item.where == "inside":
        return (f"error: the input lost messages that the {frames} read needed "
                f"({_lost_what(item, origin_ns)}): {region}{more}")  # fmt: skip
    if item.where == "before":
        return (f"error: the input lost messages before the first of the {frames} read "
                f"({_lost_what(item, origin_ns)}): {region}{more}")  # fmt: skip
    if item.where == "end" and region.lost == "rest":
        return f"input cut short, processed up to the damage: {region}{more}"
    if item.where == "end":
        return (f"error: the input lost messages after the last of the {frames} read "
                f"({_lost_what(item, origin_ns)}): {region}{more}")  # fmt: skip
    if item.where == "none":
        return f"error: the input is damaged where it lost no message: {region}{more}"
    return f"note: the input is damaged after the {frames} read ({stopped_by}): {region}{more}"


def damage_document(placed: list[PlacedDamage], origin_ns: int) -> list[dict[str, Any]]:
    """The placements as plain JSON-able data (``--summary-json``'s ``input_damage``).

    Log times in integer ns, and in seconds from the recording's first log
    time (``origin_ns``); None where unknown (``log_time_end_ns`` None for a
    cut: open to the end).
    """
    document = []
    for item in placed:
        region = item.region
        start, end = region.start_ns, region.end_ns
        document.append({
            "file": str(region.path), "byte": region.offset, "file_size": region.file_size,
            "reason": region.reason, "where": item.where, "lost": region.lost,
            "log_time_start_ns": start, "log_time_end_ns": end,
            "start_s": None if start is None else (start - origin_ns) / NS_PER_S,
            "end_s": None if end is None else (end - origin_ns) / NS_PER_S,
            "lost_messages": region.lost_counts, "images_lost": item.images_lost,
        })  # fmt: skip
    return document
