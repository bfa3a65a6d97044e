"""What ``endo-process`` reads from a recording: images, camera_info, tracker poses, truth.

A real rig records the camera driver's ``/endoscope/image_raw`` with its
``/endoscope/camera_info`` and the tracker driver's PoseStamped marker poses
on ``/tracker/pose``; endo_sim's bags add ``/ground_truth/*``. Every stream
is read lazily, as far as the frame being
processed needs: memory does not grow with the recording's length (an hour
of tracker poses and camera_infos held as messages took ~1 GB;
docs/benchmarks.md, "endo-process"). The streams share one pass over the
file (:class:`RecordingStreams`): each chunk is decompressed and parsed
once, not once per stream.

An image pairs with the newest camera_info stamped at or before it
(:class:`CameraInfoPairing`): the same message when the driver stamps both
alike, and a driver that stamps its camera_info on its own clock works too.

A truncated or damaged bag yields every intact message, then
:class:`endo_io.bag.BagCorruptError`; each stream here ends there, and the
readers keep each damaged region with the log times of the messages it cost
(:meth:`RecordingStreams.damaged_regions`), so that the run can say where
its input lost messages relative to the frames it processed
(:mod:`endo_process.damage`).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from endo_io import topics
from endo_io.bag import (
    BagCorruptError,
    BagMessage,
    BagReader,
    DamagedRegion,
    MessageDeserializationError,
    deserialize,
    msgtype_of,
)
from endo_io.camera import CameraInfoCache, CameraModel
from endo_io.errors import CameraModelError
from endo_io.stamp import stamp_to_ns
from endo_process.errors import MissingCameraInfoError, MissingTopicError, ProcessInputError

#: Topics copied from the input to the output unchanged.
GROUND_TRUTH_PREFIX = "/ground_truth/"


@dataclass(frozen=True)
class InputTopics:
    """The input topics (defaults: endo_io.topics)."""

    image: str = topics.IMAGE_RAW
    camera_info: str = topics.CAMERA_INFO
    tracker: str = topics.TRACKER_POSE


@dataclass
class RecordingInputs:
    """The small streams of a recording, read once before the frames.

    Attributes:
        path: the bag.
        topics: the input topic names.
        frame_count: messages on the image topic (the intact part).
        fixed_camera: the ``--camera-info`` model, used for every frame, or None.
        ground_truth: the ``/ground_truth/*`` topics (name -> type).
        time_range_ns: (first, last) log time of the bag.
        damage_at_open: the damaged regions found when the bag was opened
            (a cut; a damaged chunk is found when the reading gets to it:
            :meth:`RecordingStreams.damaged_regions` has them all).
        undecodable: messages skipped because their bytes do not decode as
            their topic's type, per topic.
        first_undecodable: the first such message's one-line error, or None.
    """

    path: Path
    topics: InputTopics
    frame_count: int
    fixed_camera: CameraModel | None
    ground_truth: dict[str, str]
    time_range_ns: tuple[int, int]
    damage_at_open: list[DamagedRegion] = field(default_factory=list)
    undecodable: Counter[str] = field(default_factory=Counter)
    first_undecodable: str | None = None


def _read(reader: BagReader, topic_names: list[str]) -> Iterator[BagMessage]:
    """Messages of ``topic_names``; damage ends the stream (``reader.damaged_regions``: where)."""
    with contextlib.suppress(BagCorruptError):
        yield from reader.messages(topics=topic_names)


def open_recording(
    path: Path, names: InputTopics, camera_info_yaml: Path | None = None
) -> RecordingInputs:
    """Check that the recording has what the run needs (its streams are read later, lazily).

    Raises:
        MissingTopicError: no image or no tracker message (naming the topic
            and listing the bag's topics).
        MissingCameraInfoError: no camera_info message and no ``--camera-info``.
        ProcessInputError: the ``--camera-info`` file cannot be read.
        TopicTypeError: the image, camera_info or tracker topic holds another
            type than Image, CameraInfo or PoseStamped.
        BagError: the bag cannot be opened at all.
    """
    fixed: CameraModel | None = None
    if camera_info_yaml is not None:
        try:
            fixed = CameraModel.load_yaml(camera_info_yaml)
        except (OSError, CameraModelError, ValueError, KeyError) as error:
            raise ProcessInputError(f"--camera-info {camera_info_yaml}: {error}") from None
    with BagReader(path) as reader:
        expected = {names.image: msgtype_of(Image), names.tracker: msgtype_of(PoseStamped)}
        if fixed is None:
            expected[names.camera_info] = msgtype_of(CameraInfo)
        reader.check_types(expected)
        available = {name: info.message_count for name, info in reader.topics.items()}
        listed = ", ".join(sorted(available)) or "none"
        for topic in (names.image, names.tracker):
            if available.get(topic, 0) == 0:
                raise MissingTopicError(f"{path}: no messages on {topic} (topics: {listed})")
        if fixed is None and available.get(names.camera_info, 0) == 0:
            raise MissingCameraInfoError(
                f"{path}: no messages on {names.camera_info} and no --camera-info YAML given"
            )
        span = reader.time_range_ns or (0, 0)
        return RecordingInputs(
            path=Path(path),
            topics=names,
            frame_count=available[names.image],
            fixed_camera=fixed,
            ground_truth={
                name: info.msgtype
                for name, info in reader.topics.items()
                if name.startswith(GROUND_TRUTH_PREFIX)
            },
            time_range_ns=span,
            damage_at_open=reader.damaged_regions,
        )


#: A stream that would make the shared pass hold more than this many bytes
#: (or messages) queued for the other streams reads on with a reader of its own.
MAX_QUEUED_BYTES = 64 << 20
MAX_QUEUED_MESSAGES = 20_000


class RecordingStreams:
    """The recording's streams (images, camera_info, tracker, ground truth) from one pass.

    One reader goes through the file once, in log order, and hands each
    message to the queue of the stream it belongs to; a stream's iterator
    takes from its queue and advances the shared pass only when the queue is
    empty. The streams advance together (each frame needs its image, its
    camera_info, the poses up to just past it and the truth up to it), so
    the queues hold a frame's worth of messages. A stream that would run far
    ahead of the others (a camera_info published once, a tracker recorded
    long after the last image) would make the pass queue everything in
    between: once the queues would exceed :data:`MAX_QUEUED_BYTES` or
    :data:`MAX_QUEUED_MESSAGES`, that stream goes on with a reader of its own
    from where it was (as every stream did before: memory stays bounded, and
    each stream yields exactly the messages, in the order, that a reader of
    its topics alone gives).

    Args:
        inputs: the recording.
        streams: stream name -> its topics (disjoint).
    """

    def __init__(self, inputs: RecordingInputs, streams: dict[str, list[str]]) -> None:
        self._inputs = inputs
        self._topics = {name: list(names) for name, names in streams.items()}
        self._owner = {topic: name for name, names in streams.items() for topic in names}
        self._queues: dict[str, deque[BagMessage]] = {name: deque() for name in streams}
        self._delivered = dict.fromkeys(streams, 0)
        self._detached: set[str] = set()
        self._queued_bytes = 0
        self._queued_messages = 0
        self._reader: BagReader | None = None
        self._pass: Iterator[BagMessage] | None = None
        self._readers: list[BagReader] = []  # every reader opened, for the damage each found

    def _open(self) -> BagReader:
        reader = BagReader(self._inputs.path)
        self._readers.append(reader)
        return reader

    def _shared(self) -> Iterator[BagMessage]:
        if self._pass is None:
            self._reader = self._open()
            self._pass = _read(self._reader, list(self._owner))
        return self._pass

    def _next_of(self, name: str) -> BagMessage | None:
        """The next message of stream ``name`` from the shared pass, or None at its end."""
        queue = self._queues[name]
        while not queue:
            message = next(self._shared(), None)
            if message is None:
                return None
            owner = self._owner[message.topic]
            if owner in self._detached:
                continue
            self._queues[owner].append(message)
            self._queued_bytes += len(message.data)
            self._queued_messages += 1
            if owner != name and (
                self._queued_bytes > MAX_QUEUED_BYTES or self._queued_messages > MAX_QUEUED_MESSAGES
            ):
                self._detached.add(name)
                raise _DetachedError
        message = queue.popleft()
        self._queued_bytes -= len(message.data)
        self._queued_messages -= 1
        return message

    @property
    def inputs(self) -> RecordingInputs:
        """The recording these streams read."""
        return self._inputs

    def __contains__(self, name: object) -> bool:
        return name in self._topics

    def messages(self, name: str) -> Iterator[BagMessage]:
        """Stream ``name``'s messages in log order, raw; damage ends it (damaged_regions)."""
        try:
            while (message := self._next_of(name)) is not None:
                self._delivered[name] += 1
                yield message
            return
        except _DetachedError:
            pass
        skip = self._delivered[name]
        with self._open() as reader:
            for index, message in enumerate(_read(reader, self._topics[name])):
                if index >= skip:
                    yield message

    def damaged_regions(self) -> list[DamagedRegion]:
        """The damaged regions found so far: at opening, and by each reader of the streams.

        Each region once (by file and byte offset), in the order found. A
        damaged chunk is found when a stream's reading gets to its start
        time: after the run, these are the regions up to where it read.
        """
        found: dict[tuple[str, int], DamagedRegion] = {}
        for region in self._inputs.damage_at_open + [
            r for reader in self._readers for r in reader.damaged_regions
        ]:
            found.setdefault((str(region.path), region.offset), region)
        return list(found.values())

    def close(self) -> None:
        """Close the shared reader (idempotent)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None


class _DetachedError(Exception):
    """A stream leaves the shared pass (internal to RecordingStreams)."""


def _decoded_with_log_time(
    inputs: RecordingInputs, messages: Iterator[BagMessage]
) -> Iterator[tuple[int, Any]]:
    """(log time ns, message decoded); one that does not decode is counted in ``inputs``."""
    for message in messages:
        try:
            yield message.log_time_ns, deserialize(message)
        except MessageDeserializationError as error:
            inputs.undecodable[message.topic] += 1
            if inputs.first_undecodable is None:
                inputs.first_undecodable = str(error)


def _decoded(inputs: RecordingInputs, messages: Iterator[BagMessage]) -> Iterator[Any]:
    """Each message decoded; one that does not decode is counted in ``inputs`` and skipped."""
    return (decoded for _, decoded in _decoded_with_log_time(inputs, messages))


def _iter_decoded(inputs: RecordingInputs, topic: str) -> Iterator[Any]:
    with BagReader(inputs.path) as reader:
        # Counted where the stream is read for the run (CameraInfoPairing), not here too.
        uncounted = dataclasses.replace(inputs, undecodable=Counter())
        yield from _decoded(uncounted, _read(reader, [topic]))


def recording_streams(inputs: RecordingInputs) -> RecordingStreams:
    """The streams a run reads, on one shared pass: image, camera_info, tracker, ground truth."""
    streams = {"image": [inputs.topics.image], "tracker": [inputs.topics.tracker]}
    if inputs.fixed_camera is None:
        streams["camera_info"] = [inputs.topics.camera_info]
    if inputs.ground_truth:
        streams["truth"] = list(inputs.ground_truth)
    return RecordingStreams(inputs, streams)


def iter_tracker_poses(streams: RecordingStreams) -> Iterator[PoseStamped]:
    """The tracker topic's PoseStamped messages in log (arrival) order, one at a time.

    An undecodable message is skipped and counted (:attr:`RecordingInputs.undecodable`).
    """
    return _decoded(streams.inputs, streams.messages("tracker"))


class CameraInfoPairing:
    """The camera of each image: the newest camera_info stamped at or before it.

    The camera_info stream is read by a reader of its own, only as far as
    the image being paired (a camera_info logged after its image is found
    too). With ``--camera-info`` the one model serves every frame. Models
    are built once per distinct camera (its header's stamp aside, its
    frame_id included: :class:`endo_io.camera.CameraInfoCache`, as the live
    nodes), so every frame of one camera shares one model and its ray
    tables.

    Args:
        inputs: the recording.
        streams: its streams (:func:`recording_streams`).
    """

    def __init__(self, inputs: RecordingInputs, streams: RecordingStreams) -> None:
        self._fixed = inputs.fixed_camera
        self._stream: Iterator[CameraInfo] = (
            iter(()) if self._fixed is not None
            else _decoded(inputs, streams.messages("camera_info"))
        )  # fmt: skip
        self._next: CameraInfo | None = None
        self._current: CameraInfo | None = None
        self._cameras = CameraInfoCache()

    def _peek(self) -> CameraInfo | None:
        if self._next is None:
            self._next = next(self._stream, None)
        return self._next

    def at(self, stamp_ns: int) -> tuple[CameraModel, CameraInfo | None] | None:
        """(model, camera_info) of the image at ``stamp_ns``; None if none is at or before it.

        The camera_info is None with ``--camera-info``. Stamps are expected
        in order, as images come.

        Raises:
            CameraModelError: the camera_info gives no usable model.
        """
        if self._fixed is not None:
            return self._fixed, None
        while (candidate := self._peek()) is not None and stamp_to_ns(
            candidate.header.stamp
        ) <= stamp_ns:
            self._current, self._next = candidate, None
        current = self._current
        if current is None or stamp_to_ns(current.header.stamp) > stamp_ns:
            return None
        return self._cameras.model_of(current)[0], current  # may raise: nothing changes


def first_camera(inputs: RecordingInputs) -> CameraModel | None:
    """The camera of the recording's first camera_info (or ``--camera-info``), to warm up for.

    None when the first camera_info gives no usable model (the frame loop
    then reports it per frame, as it would anyway).
    """
    if inputs.fixed_camera is not None:
        return inputs.fixed_camera
    first = next(_iter_decoded(inputs, inputs.topics.camera_info), None)
    if first is None:
        return None
    try:
        return CameraModel.from_camera_info(first)
    except (CameraModelError, ValueError):
        return None


def iter_images(streams: RecordingStreams) -> Iterator[tuple[int, Image]]:
    """(log time ns, image) of the image topic in log order, decoded one at a time.

    An undecodable message is skipped and counted (:attr:`RecordingInputs.undecodable`).
    """
    return _decoded_with_log_time(streams.inputs, streams.messages("image"))


def iter_ground_truth(streams: RecordingStreams) -> Iterator[BagMessage]:
    """The ``/ground_truth/*`` messages in log order, raw (copied through unchanged)."""
    if "truth" not in streams:
        return iter(())
    return streams.messages("truth")
