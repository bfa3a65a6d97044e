"""Whole streams out of a bag: messages per topic, a pose stream, depth frames.

The offline tools' one way to get these (the bringup's waits and scores,
``endo-handeye``): each reads through :class:`~endo_io.bag.BagReader` and
converts with endo_io's message converters (:func:`endo_io.pose.pose_to_matrix`,
:func:`endo_io.image.image_to_array`).

>>> counts = count_messages("run.mcap")            # Counter: topic -> messages
>>> growing = GrowingCounter("recording.mcap")     # a file still being written:
>>> counts = growing.count()                       # call again as it grows (cheap)
>>> stamps_ns, T = read_pose_stream("run.mcap", "/endoscope/pose")
>>> depth = read_depth_frames("run.mcap", "/endoscope/depth")  # stamp -> (H, W)
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import NamedTuple

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel, Message

from endo_io.bag.errors import BagError
from endo_io.bag.interfaces import BagMessage
from endo_io.bag.mcap_file import MCAP_MAGIC
from endo_io.bag.mcap_records import (
    RECORD_PREFIX,
    BoundedFile,
    RecordDamage,
    chunk_records,
    read_record,
)
from endo_io.bag.reader import BagReader
from endo_io.bag.serde import deserialize
from endo_io.image import image_to_array, image_to_irradiance
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


class GrowingCounter:
    """Messages per topic of one MCAP file that is still being written, read as it grows.

    For waiting on a recorder (:func:`endo_bringup.graph.wait_for_recording`):
    :func:`count_messages` decompresses every chunk at each call (4.8 CPU-s
    for a 60 s graph recording), this reads each record once, over all
    calls, and no chunk's data: a chunk counts from the message-index
    records that follow it (the writers of :mod:`endo_io.bag.writer` and of
    rosbag2 write them), and is decompressed only when it has none or
    declares a channel not seen before (the writer puts a channel's record
    in the chunk of its first message). Top-level message records count
    too. A record the file does not yet hold whole (the writer still at it)
    is read at the next call. The file's last chunk is counted again at the
    next call, until a record follows its indexes: the writer may still be
    writing them (:class:`~endo_io.bag.BagWriter` writes all of a chunk's
    indexes in one call right after the chunk), so until then the chunk
    counts as far as its indexes are in the file. Reading ends at the
    summary (``DataEnd``).

    So on a file whose chunks and indexes are all whole the counts equal
    :func:`count_messages`'s; on a file cut inside a chunk they are those of
    the complete chunks (``count_messages(partial=True)`` also recovers the
    whole messages at the head of the cut chunk), and never more than its.
    A damaged record stops the count where it is (:attr:`damage`), as
    ``partial`` does.

    Args:
        path: the ``.mcap`` file (it need not exist yet: it counts as empty).
    """

    def __init__(self, path: BagPath) -> None:
        self.path = Path(path)
        #: The reason the count stopped at a damaged record ("" while none).
        self.damage = ""
        self._offset = 0  # the next record to read; 0: the magic is not read yet
        self._topics: dict[int, str] = {}
        self._counts: Counter[int] = Counter()
        self._last_chunk: Counter[int] = Counter()  # counted again at the next call
        self._done = False

    def count(self) -> Counter[str]:
        """Topic -> messages in the file's complete chunks (every topic seen listed, 0 too).

        Raises:
            BagError: the file is not an MCAP file.
        """
        if not self._done and not self.damage:
            try:
                with self.path.open("rb") as raw:
                    self._read(BoundedFile(raw, os.fstat(raw.fileno()).st_size))
            except FileNotFoundError:
                pass
        counts: Counter[str] = Counter(dict.fromkeys(self._topics.values(), 0))
        for cid, n in (self._counts + self._last_chunk).items():
            counts[self._topics[cid]] += n
        return counts

    def _read(self, stream: BoundedFile) -> None:
        if self._offset == 0:
            if stream.size < len(MCAP_MAGIC):
                return
            head = stream.read(len(MCAP_MAGIC))
            if head != MCAP_MAGIC:
                raise BagError(f"{self.path}: not an MCAP file (bad magic {head!r})")
            self._offset = len(MCAP_MAGIC)
        chunk: int | None = None  # offset of the chunk whose message indexes are being read
        indexed: dict[int, int] = {}
        position = self._offset
        self._last_chunk = Counter()
        try:
            while position + RECORD_PREFIX <= stream.size:
                stream.seek(position)
                prefix = stream.read(RECORD_PREFIX)
                end = position + RECORD_PREFIX + int.from_bytes(prefix[1:], "little")
                if end > stream.size:
                    break  # not whole yet
                opcode = prefix[0]
                if opcode == Opcode.MESSAGE_INDEX:
                    if chunk is not None:
                        index, _ = read_record(stream, position)
                        indexed[index.channel_id] = len(index.records)  # type: ignore[union-attr]
                    position = end
                    continue
                if chunk is not None:
                    self._counts.update(self._count_chunk(stream, chunk, indexed))
                    chunk, indexed = None, {}
                self._offset = position  # everything before counted
                if opcode == Opcode.CHUNK:
                    chunk = position
                elif opcode == Opcode.CHANNEL:
                    channel, _ = read_record(stream, position)
                    assert isinstance(channel, Channel)
                    self._topics.setdefault(channel.id, channel.topic)
                elif opcode == Opcode.MESSAGE:
                    message, _ = read_record(stream, position)
                    assert isinstance(message, Message)
                    self._counts[message.channel_id] += 1
                elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                    self._done = True
                    return
                position = end
            if chunk is None:
                self._offset = position
            else:  # its indexes may be still coming: read them again next time
                self._last_chunk = self._count_chunk(stream, chunk, indexed)
        except RecordDamage as exc:
            self.damage = f"{self.path}: byte {position}: {exc}"

    def _count_chunk(
        self, stream: BoundedFile, offset: int, indexed: dict[int, int]
    ) -> Counter[int]:
        """Channel id -> messages of a whole chunk: its message indexes, else its records."""
        if indexed and all(cid in self._topics for cid in indexed):
            return Counter(indexed)
        chunk, _ = read_record(stream, offset)
        counts: Counter[int] = Counter()
        for record in chunk_records(chunk, validate_crc=False):  # type: ignore[arg-type]
            if isinstance(record, Channel):
                self._topics.setdefault(record.id, record.topic)
            elif isinstance(record, Message):
                counts[record.channel_id] += 1
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
        self.add_transform(stamp_ns, T)

    def add_transform(self, stamp_ns: int, T: np.ndarray) -> None:
        """Keep one pose already converted: (4, 4) float64 in the messages' units (scaled here).

        ``T`` is taken over (scaled in place when ``metres_per_unit`` != 1).
        """
        if self.metres_per_unit != 1.0:
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
    path: BagPath, topic: str, stamps: set[int] | None = None, *, irradiance: bool = False
) -> dict[int, np.ndarray]:
    """Header stamp (ns) -> (H, W) float32 depth image of the messages on ``topic``.

    Args:
        path: the bag.
        topic: a 32FC1 (or other single-channel) ``sensor_msgs/Image`` topic;
            a topic the bag lacks gives no frames.
        stamps: keep only frames with these header stamps (all when None), so
            that a long recording is not held in memory to score a few frames.
        irradiance: the topic is a corrected image (``image_corrected``):
            16UC1 fixed point or 32FC1, both given as float32 irradiance
            (:func:`endo_io.image.image_to_irradiance`).

    Raises:
        BagError: the bag is missing, unreadable or damaged.
        MessageConversionError: an image cannot be converted.
    """
    convert = image_to_irradiance if irradiance else image_to_array
    frames: dict[int, np.ndarray] = {}
    with BagReader(path) as reader:
        if topic not in reader.topics:
            return frames
        for message in reader.messages(topics=[topic]):
            msg = deserialize(message)
            stamp = stamp_to_ns(msg.header.stamp)
            if stamps is None or stamp in stamps:
                frames[stamp] = convert(msg)
    return frames
