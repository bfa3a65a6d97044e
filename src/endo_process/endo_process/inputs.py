"""What ``endo-process`` reads from a recording: images, camera_info, tracker poses, truth.

A real rig records the camera driver's ``/endoscope/image_raw`` with its
``/endoscope/camera_info`` and the tracker driver's PoseStamped marker poses
on ``/tracker/pose``; endo_sim's bags add ``/ground_truth/*``. Every stream
is read lazily, each by a reader of its own, as far as the frame being
processed needs: memory does not grow with the recording's length (an hour
of tracker poses and camera_infos held as messages took ~1 GB;
docs/benchmarks.md, "endo-process").

An image pairs with the newest camera_info stamped at or before it
(:class:`CameraInfoPairing`): the same message when the driver stamps both
alike, and a driver that stamps its camera_info on its own clock works too.

A truncated or damaged bag yields every intact message, then
:class:`endo_io.bag.BagCorruptError`; each reader here stops at the damage
and keeps its one-line description in :attr:`RecordingInputs.damage`, so
the run processes everything up to the cut and says so.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from endo_io import topics
from endo_io.bag import BagCorruptError, BagMessage, BagReader, deserialize
from endo_io.camera import CameraModel
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
        damage: one-line description of the first damage met, or None.
    """

    path: Path
    topics: InputTopics
    frame_count: int
    fixed_camera: CameraModel | None
    ground_truth: dict[str, str]
    time_range_ns: tuple[int, int]
    damage: str | None = None


def _read(
    reader: BagReader, topic_names: list[str], inputs: RecordingInputs
) -> Iterator[BagMessage]:
    """Messages of ``topic_names``; damage ends the stream and is remembered."""
    try:
        yield from reader.messages(topics=topic_names)
    except BagCorruptError as error:
        if inputs.damage is None:
            inputs.damage = str(error)


def open_recording(
    path: Path, names: InputTopics, camera_info_yaml: Path | None = None
) -> RecordingInputs:
    """Check that the recording has what the run needs (its streams are read later, lazily).

    Raises:
        MissingTopicError: no image or no tracker message (naming the topic
            and listing the bag's topics).
        MissingCameraInfoError: no camera_info message and no ``--camera-info``.
        ProcessInputError: the ``--camera-info`` file cannot be read.
        BagError: the bag cannot be opened at all.
    """
    fixed: CameraModel | None = None
    if camera_info_yaml is not None:
        try:
            fixed = CameraModel.load_yaml(camera_info_yaml)
        except (OSError, CameraModelError, ValueError, KeyError) as error:
            raise ProcessInputError(f"--camera-info {camera_info_yaml}: {error}") from None
    with BagReader(path) as reader:
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
            damage=reader.damage,
        )


def _iter_decoded(inputs: RecordingInputs, topic: str) -> Iterator[Any]:
    with BagReader(inputs.path) as reader:
        for message in _read(reader, [topic], inputs):
            yield deserialize(message)


def iter_tracker_poses(inputs: RecordingInputs) -> Iterator[PoseStamped]:
    """The tracker topic's PoseStamped messages in log (arrival) order, one at a time."""
    return _iter_decoded(inputs, inputs.topics.tracker)


def _camera_key(info: CameraInfo) -> tuple[Any, ...]:
    """What makes two camera_infos the same camera (everything but the header)."""
    roi = info.roi
    return (info.width, info.height, info.distortion_model, tuple(info.d), tuple(info.k),
            tuple(info.r), tuple(info.p), info.binning_x, info.binning_y,
            roi.x_offset, roi.y_offset, roi.width, roi.height, roi.do_rectify)  # fmt: skip


class CameraInfoPairing:
    """The camera of each image: the newest camera_info stamped at or before it.

    The camera_info stream is read by a reader of its own, only as far as
    the image being paired (a camera_info logged after its image is found
    too). With ``--camera-info`` the one model serves every frame. Models
    are built once per distinct camera (header aside), so every frame of
    one camera shares one model and its ray tables.

    Args:
        inputs: the recording.
    """

    def __init__(self, inputs: RecordingInputs) -> None:
        self._fixed = inputs.fixed_camera
        self._stream: Iterator[CameraInfo] = (
            iter(()) if self._fixed is not None
            else _iter_decoded(inputs, inputs.topics.camera_info)
        )  # fmt: skip
        self._next: CameraInfo | None = None
        self._current: CameraInfo | None = None
        self._model: CameraModel | None = None
        self._key: tuple[Any, ...] | None = None

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
        key = _camera_key(current)
        if key != self._key or self._model is None:
            self._model = CameraModel.from_camera_info(current)  # may raise: nothing changes
            self._key = key
        return self._model, current


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


def iter_images(inputs: RecordingInputs) -> Iterator[Image]:
    """The image topic's messages in log order, decoded one at a time."""
    return _iter_decoded(inputs, inputs.topics.image)


def iter_ground_truth(inputs: RecordingInputs) -> Iterator[BagMessage]:
    """The ``/ground_truth/*`` messages in log order, raw (copied through unchanged)."""
    if not inputs.ground_truth:
        return
    with BagReader(inputs.path) as reader:
        yield from _read(reader, list(inputs.ground_truth), inputs)
