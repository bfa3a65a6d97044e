"""Damaged regions placed against the frames a run read, and the one line said about them."""

from __future__ import annotations

from pathlib import Path

from endo_io.bag import DamagedRegion
from endo_process.damage import damage_line, place_damage

IMAGE = "/endoscope/image_raw"
S = 1_000_000_000  # ns per s
ORIGIN = 100 * S  # the recording's first log time
FRAMES = (ORIGIN, ORIGIN + 3 * S)  # the images read: 0 s to 3 s into the recording


def _chunk(start_s: float, end_s: float, images: int | None = 4) -> DamagedRegion:
    counts = None if images is None else {IMAGE: images, "/tracker/pose": 8}
    return DamagedRegion(Path("a.mcap"), 4096, 10**6, "chunk CRC mismatch", "span",
                         ORIGIN + round(start_s * S), ORIGIN + round(end_s * S),
                         counts)  # fmt: skip


def _where(region: DamagedRegion, read_to_end: bool = True, reach_s: float = 0.0) -> str:
    (placed,) = place_damage([region], IMAGE, FRAMES, read_to_end, reach_ns=round(reach_s * S))
    return placed.where


def test_a_lost_chunk_is_placed_by_its_log_times_against_the_frames_read() -> None:
    assert _where(_chunk(1.0, 1.2)) == "inside"
    assert _where(_chunk(1.0, 1.2), read_to_end=False) == "inside"
    assert _where(_chunk(-0.5, -0.1)) == "before"
    # messages logged with the last frame read (its camera_info) are among what it needs
    assert _where(_chunk(3.0, 3.2)) == "inside"
    assert _where(_chunk(3.0, 3.2), read_to_end=False) == "inside"
    # after the last frame read: none lost among the frames...
    assert _where(_chunk(3.05, 3.2)) == "end"
    assert _where(_chunk(3.05, 3.2), read_to_end=False) == "after"
    # ...unless its pose lookup reaches there (review, session 16: a chunk of the tracker
    # samples right after the last --max-frames frame cost it its pose, and the run said 0)
    assert _where(_chunk(3.05, 3.2), reach_s=0.1) == "inside"
    assert _where(_chunk(3.05, 3.2), read_to_end=False, reach_s=0.1) == "inside"
    assert _where(_chunk(3.15, 3.2), read_to_end=False, reach_s=0.1) == "after"
    # a chunk whose header's times are damaged: somewhere in what was read
    unknown = DamagedRegion(Path("a.mcap"), 4096, 10**6, "bad", "span")
    assert _where(unknown) == "inside" and _where(unknown, read_to_end=False) == "after"


def test_a_cut_is_the_end_unless_another_file_went_on_past_it() -> None:
    cut = DamagedRegion(Path("a.mcap"), 4096, 10**6, "file ends inside a chunk record",
                        "rest", FRAMES[1])  # fmt: skip
    # the messages logged with the last frame read may be cut: what it needed
    assert _where(cut) == "end" and _where(cut, read_to_end=False) == "inside"
    later = DamagedRegion(Path("a.mcap"), 4096, 10**6, "file ends inside a chunk record",
                          "rest", FRAMES[1] + S // 2)  # fmt: skip
    assert _where(later, read_to_end=False) == "after"
    assert _where(later, read_to_end=False, reach_s=0.6) == "inside"
    # a split bag: this file cut at 1 s, images of the next file read to 3 s
    early = DamagedRegion(Path("a_0.mcap"), 4096, 10**6, "cut", "rest", ORIGIN + S)
    assert _where(early) == "inside"
    assert _where(DamagedRegion(Path("a_0.mcap"), 5, 5, "cut", "rest")) == "inside"
    magic = DamagedRegion(Path("a.mcap"), 999, 1000, "closing magic", "none")
    assert _where(magic) == "none" and _where(magic, read_to_end=False) == "none"
    (nothing_read,) = place_damage([cut], IMAGE, None, True)
    assert nothing_read.where == "end"


def test_the_line_says_the_most_serious_region_and_counts_the_others() -> None:
    regions = [_chunk(3.5, 3.6), _chunk(1.0, 1.25, images=None), _chunk(2.0, 2.1)]
    placed = place_damage(regions, IMAGE, FRAMES, read_to_end=False)
    assert [p.where for p in placed] == ["after", "inside", "inside"]
    assert [p.images_lost for p in placed] == [4, None, 4]
    assert damage_line(placed, 91, ORIGIN, "--max-frames") == (
        "error: the input lost messages that the 91 images read needed (logged 1.000 s to "
        "1.250 s into the recording, how many images, the file's index does not say): "
        "a.mcap: truncated or corrupt at byte 4096 of 1000000 (chunk CRC mismatch); 2 more "
        "damaged regions"
    )
    after = place_damage(regions[:1], IMAGE, FRAMES, read_to_end=False)
    assert damage_line(after, 1, ORIGIN, "interrupted") == (
        "note: the input is damaged after the 1 image read (interrupted): a.mcap: "
        "truncated or corrupt at byte 4096 of 1000000 (chunk CRC mismatch)"
    )
    end = place_damage(regions[:1], IMAGE, FRAMES, read_to_end=True)
    assert damage_line(end, 90, ORIGIN, "--max-frames").startswith(
        "error: the input lost messages after the last of the 90 images read (logged "
        "3.500 s to 3.600 s into the recording, 4 images by the file's index): a.mcap: "
    )
    assert damage_line([], 90, ORIGIN, "--max-frames") == ""
