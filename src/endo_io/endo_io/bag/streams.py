"""Whole streams out of a bag: messages per topic, a pose stream, depth frames.

The offline tools' one way to get these (the bringup's waits and scores,
``endo-handeye``): each reads through :class:`~endo_io.bag.BagReader` and
converts with endo_io's message converters (:func:`endo_io.pose.pose_to_matrix`,
:func:`endo_io.image.image_to_array`).

>>> counts = count_messages("run.mcap")            # Counter: topic -> messages
>>> stamps_ns, T = read_pose_stream("run.mcap", "/endoscope/pose")
>>> depth = read_depth_frames("run.mcap", "/endoscope/depth")  # stamp -> (H, W)
"""

from __future__ import annotations

import os
from collections import Counter
from typing import NamedTuple

import numpy as np

from endo_io.bag.errors import BagError
from endo_io.bag.interfaces import BagMessage
from endo_io.bag.reader import BagReader
from endo_io.bag.serde import deserialize
from endo_io.image import image_to_array
from endo_io.pose import pose_to_matrix
from endo_io.stamp import stamp_to_ns

BagPath = str | os.PathLike[str]


def count_messages(path: BagPath, *, partial: bool = False) -> Counter[str]:
    """Messages per topic in a bag, every topic listed (0 for a topic without any).

    Args:
        path: the bag (an ``.mcap`` file or a rosbag2 directory).
        partial: the bag may still be being written (a recorder's flushed,
            unfinished file): a bag that cannot be opened yet counts as empty,
            and a damaged or unfinished tail ends the count instead of raising.

    Returns:
        Counter of topic name -> messages readable.

    Raises:
        BagError: (only without ``partial``) the bag is missing, unreadable
            or damaged.
    """
    counts: Counter[str] = Counter()
    try:
        with BagReader(path) as reader:
            counts.update(dict.fromkeys(reader.topics, 0))
            try:
                for message in reader.messages():
                    counts[message.topic] += 1
            except BagError:
                if not partial:
                    raise
    except BagError:
        if not partial:
            raise
    return counts


class PoseStream(NamedTuple):
    """A stamped stream of rigid transforms (unpacks as ``stamps_ns, poses``).

    stamps_ns: (N,) int64 header stamps, ns, sorted (stable: equal stamps
    keep bag order). poses: (N, 4, 4) float64 transforms, metres.
    """

    stamps_ns: np.ndarray
    poses: np.ndarray


class PoseStreamCollector:
    """Collects ``geometry_msgs/PoseStamped`` bag messages into a :class:`PoseStream`.

    For a reader that goes through the bag once for several topics (feed it
    the pose messages as they come); :func:`read_pose_stream` is the one-call
    form.

    Args:
        metres_per_unit: scale of the messages' positions (0.001 for a
            tracker driver publishing millimetres).
    """

    def __init__(self, *, metres_per_unit: float = 1.0) -> None:
        self.metres_per_unit = metres_per_unit
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []

    def add(self, message: BagMessage) -> None:
        """Convert and keep one PoseStamped message.

        Raises:
            PoseError: a non-finite position or a non-unit quaternion.
            MessageDeserializationError: the payload is not a PoseStamped.
        """
        T, stamp_ns = pose_to_matrix(deserialize(message))
        T[:3, 3] *= self.metres_per_unit
        self._stamps.append(stamp_ns)
        self._poses.append(T)

    def stream(self) -> PoseStream:
        """Everything added so far, sorted by stamp."""
        stamps = np.asarray(self._stamps, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        poses = np.asarray(self._poses, dtype=np.float64).reshape(-1, 4, 4)
        return PoseStream(stamps[order], poses[order])


def read_pose_stream(path: BagPath, topic: str, *, metres_per_unit: float = 1.0) -> PoseStream:
    """Every ``PoseStamped`` on ``topic``, as arrays sorted by header stamp.

    Args:
        path: the bag.
        topic: a PoseStamped topic; a topic the bag lacks gives an empty stream.
        metres_per_unit: scale of the positions (see :class:`PoseStreamCollector`).

    Returns:
        The :class:`PoseStream` ((N,) int64 ns, (N, 4, 4) float64 metres).

    Raises:
        BagError: the bag is missing, unreadable or damaged.
        PoseError: a pose is not finite or its quaternion not unit.
    """
    collector = PoseStreamCollector(metres_per_unit=metres_per_unit)
    with BagReader(path) as reader:
        if topic in reader.topics:
            for message in reader.messages(topics=[topic]):
                collector.add(message)
    return collector.stream()


def read_depth_frames(
    path: BagPath, topic: str, stamps: set[int] | None = None
) -> dict[int, np.ndarray]:
    """Header stamp (ns) -> (H, W) float32 depth image of the messages on ``topic``.

    Args:
        path: the bag.
        topic: a 32FC1 (or other single-channel) ``sensor_msgs/Image`` topic;
            a topic the bag lacks gives no frames.
        stamps: keep only frames with these header stamps (all when None), so
            that a long recording is not held in memory to score a few frames.

    Raises:
        BagError: the bag is missing, unreadable or damaged.
        MessageConversionError: an image cannot be converted.
    """
    frames: dict[int, np.ndarray] = {}
    with BagReader(path) as reader:
        if topic not in reader.topics:
            return frames
        for message in reader.messages(topics=[topic]):
            msg = deserialize(message)
            stamp = stamp_to_ns(msg.header.stamp)
            if stamps is None or stamp in stamps:
                frames[stamp] = image_to_array(msg)
    return frames
