"""A simulated recording's frames by stamp: raw images, camera_info and true depth.

What the SFS benches (bench_sfs.py's phantom, eval_highlights.py's bags) read
before solving every frame in order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from endo_io.bag import BagReader, deserialize
from endo_io.stamp import stamp_to_ns
from endo_io.topics import CAMERA_INFO, IMAGE_RAW, TRUE_DEPTH


@dataclass(frozen=True)
class RecordedFrames:
    """Messages by stamp (integer ns); ``stamps``: those with an image and a camera_info, sorted."""

    images: dict[int, Any]
    infos: dict[int, Any]
    depths: dict[int, Any]
    stamps: list[int]


def read_recorded_frames(bag: str) -> RecordedFrames:
    """The raw images, camera_info and ground-truth depth of ``bag``, by header stamp."""
    topics: dict[str, dict[int, Any]] = {IMAGE_RAW: {}, CAMERA_INFO: {}, TRUE_DEPTH: {}}
    with BagReader(bag) as reader:
        for message in reader.messages(list(topics)):
            msg = deserialize(message)
            topics[message.topic][stamp_to_ns(msg.header.stamp)] = msg
    images, infos, depths = topics[IMAGE_RAW], topics[CAMERA_INFO], topics[TRUE_DEPTH]
    return RecordedFrames(images, infos, depths, sorted(set(images) & set(infos)))
