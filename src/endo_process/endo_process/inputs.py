"""What ``endo-process`` reads from a recording: images, camera_info, tracker poses, truth.

A real rig records the camera driver's ``/endoscope/image_raw`` with its
``/endoscope/camera_info`` and the tracker driver's PoseStamped marker poses
on ``/tracker/pose``; endo_sim's bags add ``/ground_truth/*``. Images are
streamed (one at a time), everything else is small and read up front.

A truncated or damaged bag yields every intact message, then
:class:`endo_io.bag.BagCorruptError`; each reader here stops at the damage
and keeps its one-line description in :attr:`RecordingInputs.damage`, so
the run processes everything up to the cut and says so.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

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
        frame_count: messages on the image topic (the intact part).
        camera_infos: header stamp (ns) -> CameraInfo, empty with ``--camera-info``.
        fixed_camera: the ``--camera-info`` model, used for every frame, or None.
        tracker_poses: the tracker topic's PoseStamped messages in log order.
        ground_truth: the ``/ground_truth/*`` topics (name -> type).
        time_range_ns: (first, last) log time of the bag.
        damage: one-line description of the first damage met, or None.
    """

    path: Path
    frame_count: int
    camera_infos: dict[int, CameraInfo]
    fixed_camera: CameraModel | None
    tracker_poses: list[PoseStamped]
    ground_truth: dict[str, str]
    time_range_ns: tuple[int, int]
    damage: str | None = None
    _models: dict[int, CameraModel] = field(default_factory=dict, repr=False)


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
    """Check that the recording has what the run needs and read its small streams.

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
        inputs = RecordingInputs(
            path=Path(path),
            frame_count=available[names.image],
            camera_infos={},
            fixed_camera=fixed,
            tracker_poses=[],
            ground_truth={
                name: info.msgtype
                for name, info in reader.topics.items()
                if name.startswith(GROUND_TRUTH_PREFIX)
            },
            time_range_ns=span,
            damage=reader.damage,
        )
        wanted = [names.tracker] + ([names.camera_info] if fixed is None else [])
        for message in _read(reader, wanted, inputs):
            msg = deserialize(message)
            if message.topic == names.tracker:
                inputs.tracker_poses.append(msg)
            else:
                inputs.camera_infos[stamp_to_ns(msg.header.stamp)] = msg
    return inputs


def camera_at(inputs: RecordingInputs, stamp_ns: int) -> CameraModel | None:
    """The camera model of the frame at ``stamp_ns`` (the SFS node pairs by exact stamp).

    Returns the ``--camera-info`` model, else the model of the camera_info
    with this stamp, else None. Models are cached per distinct CameraInfo.
    Raises CameraModelError for a camera_info that gives no model.
    """
    if inputs.fixed_camera is not None:
        return inputs.fixed_camera
    info = inputs.camera_infos.get(stamp_ns)
    if info is None:
        return None
    key = id(info)
    model = inputs._models.get(key)
    if model is None:
        model = CameraModel.from_camera_info(info)
        for known in inputs._models.values():
            if known == model:
                model = known  # one model (and one ray table) per distinct camera
                break
        inputs._models[key] = model
    return model


def iter_images(inputs: RecordingInputs, topic: str) -> Iterator[Image]:
    """The image topic's messages in log order, decoded one at a time."""
    with BagReader(inputs.path) as reader:
        for message in _read(reader, [topic], inputs):
            yield deserialize(message)


def iter_ground_truth(inputs: RecordingInputs) -> Iterator[BagMessage]:
    """The ``/ground_truth/*`` messages in log order, raw (copied through unchanged)."""
    if not inputs.ground_truth:
        return
    with BagReader(inputs.path) as reader:
        yield from _read(reader, list(inputs.ground_truth), inputs)
