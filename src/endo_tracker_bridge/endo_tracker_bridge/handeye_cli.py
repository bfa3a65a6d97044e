"""``endo-handeye BAG -o handeye.yaml``: hand–eye and clock calibration from a bag.

The bag holds checkerboard images (``/endoscope/image_raw``), the camera's
intrinsics (``/endoscope/camera_info``) and the tracker's marker poses
(``/tracker/pose``, as ``endo-tracker-bridge`` publishes them, or as the
``endo_sim`` hand–eye bag has them). For each image the board's inner
corners are detected and its pose solved (PnP with the camera_info
intrinsics and distortion); :func:`endo_tracker_bridge.handeye.calibrate_hand_eye`
does the rest. The result goes to ``handeye.yaml``, which the bridge loads
through its ``handeye_file`` parameter.

Without ``--board`` the board's size is detected among
:data:`~endo_tracker_bridge.handeye.COMMON_BOARDS`; a ``--board`` that is not
found in the images stops with one line naming the size they show. Without
``--square-mm`` the square side is estimated from the tracker
(:func:`~endo_tracker_bridge.handeye.estimate_square_size`).
"""

from __future__ import annotations

import argparse
import datetime
import sys
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from endo_io.bag import BagReader, MessageDeserializationError, deserialize, msgtype_of
from endo_io.bag.streams import PoseStreamCollector
from endo_io.camera import CameraModel
from endo_io.cli import exit_on_error, refuse_existing
from endo_io.errors import PoseError
from endo_io.image import image_to_array
from endo_io.provenance import camera_record, file_record, tool_record
from endo_io.stamp import stamp_to_ns
from endo_io.topics import CAMERA_INFO, IMAGE_RAW, TRACKER_POSE
from endo_tracker_bridge.conventions import LengthUnit
from endo_tracker_bridge.errors import HandEyeError
from endo_tracker_bridge.handeye import (
    COMMON_BOARDS,
    MS,
    BoardView,
    Checkerboard,
    HandEyeResult,
    OffsetSearch,
    board_view,
    calibrate_hand_eye,
    detect_checkerboard,
    estimate_square_size,
    find_board_size,
    scaled_views,
)
from endo_tracker_bridge.handeye_file import HandEyeCalibration

#: Square side (mm) the views are solved with before the real one is estimated.
NOMINAL_SQUARE_MM = 5.0


@dataclass(frozen=True)
class BagTopics:
    """Topic names of the calibration bag."""

    image: str = IMAGE_RAW
    camera_info: str = CAMERA_INFO
    pose: str = TRACKER_POSE


@dataclass(frozen=True)
class BagObservations:
    """What the bag gives the solver: board views, tracker stream, camera.

    ``skipped_poses`` tracker samples gave no pose (NaN: the tool out of
    view; a non-unit quaternion; undecodable bytes) and were left out;
    ``first_skipped`` is the first one's cause and message.
    """

    views: list[BoardView]
    images: int
    tracker_stamps_ns: np.ndarray
    tracker_poses: np.ndarray
    camera: CameraModel
    skipped_poses: int = 0
    first_skipped: str | None = None


def read_observations(
    path: str | Path,
    board: Checkerboard,
    topics: BagTopics | None = None,
    pose_unit: LengthUnit = LengthUnit.METRE,
    max_views: int = 0,
    workers: int = 2,
) -> BagObservations:
    """Detect the board in the bag's images and collect the tracker poses.

    ``max_views`` > 0 uses at most that many images, evenly spread over the
    recording; ``workers`` threads run the corner detection (OpenCV releases
    the GIL). A tracker sample that gives no pose is left out and counted
    (``BagObservations.skipped_poses``). Raises HandEyeError when the bag
    lacks a topic, TopicTypeError when one holds another type.
    """
    topics = topics or BagTopics()
    with BagReader(path) as bag:
        for name in (topics.image, topics.camera_info, topics.pose):
            if name not in bag.topics:
                raise HandEyeError(f"bag {path} has no topic {name}")
        bag.check_types({topics.image: msgtype_of(Image), topics.camera_info:
                         msgtype_of(CameraInfo), topics.pose: msgtype_of(PoseStamped)})  # fmt: skip
        info = next(bag.messages(topics=[topics.camera_info]))
        camera = CameraModel.from_camera_info(deserialize(info))
        image_count = bag.topics[topics.image].message_count
        stride = max(1, -(-image_count // max_views)) if max_views > 0 else 1

        poses = PoseStreamCollector(metres_per_unit=pose_unit.metres_per_unit)
        images: list[tuple[int, np.ndarray]] = []
        image_index = skipped = 0
        first_skipped: str | None = None
        for message in bag.messages(topics=[topics.image, topics.pose]):
            if message.topic == topics.pose:
                try:
                    poses.add(message)
                except (PoseError, MessageDeserializationError) as error:
                    skipped += 1
                    first_skipped = first_skipped or f"{type(error).__name__}: {error}"
                continue
            if image_index % stride == 0:
                msg = deserialize(message)
                images.append((stamp_to_ns(msg.header.stamp), image_to_array(msg)))
            image_index += 1

    def detect(item: tuple[int, np.ndarray]) -> BoardView | None:
        stamp_ns, image = item
        corners = detect_checkerboard(image, board)
        if corners is None:
            return None
        try:
            return board_view(stamp_ns, corners, board, camera)
        except HandEyeError:
            return None

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        detected = list(pool.map(detect, images))
    views = [v for v in detected if v is not None]
    tracker = poses.stream()
    return BagObservations(
        views=views,
        images=len(images),
        tracker_stamps_ns=tracker.stamps_ns,
        tracker_poses=tracker.poses,
        camera=camera,
        skipped_poses=skipped,
        first_skipped=first_skipped,
    )


#: Board views the solver needs at least (calibrate_hand_eye's minimum).
MIN_VIEWS = 5
#: Images sampled (evenly over the recording) to find the board's size.
SIZE_SAMPLE_IMAGES = 6


def sample_images(
    path: str | Path, topic: str, count: int = SIZE_SAMPLE_IMAGES
) -> list[np.ndarray]:
    """``count`` images spread evenly over the bag's ``topic`` (fewer if it has fewer)."""
    with BagReader(path) as bag:
        if topic not in bag.topics:
            raise HandEyeError(f"bag {path} has no topic {topic}")
        bag.check_types({topic: msgtype_of(Image)})
        total = bag.topics[topic].message_count
        wanted = set(np.linspace(0, max(total - 1, 0), min(count, total)).round().astype(int))
        images = []
        for index, message in enumerate(bag.messages(topics=[topic])):
            if index in wanted:
                images.append(image_to_array(deserialize(message)))
    return images


def resolve_board(
    path: str | Path, topic: str, given: str | None, square_mm: float
) -> Checkerboard:
    """The checkerboard of the recording, its size detected among the common ones.

    ``given`` ("9x6"), when not None, is the board the user named and that
    was not found in the recording: the error then names the size the images
    show. Images are sampled evenly over the recording, SIZE_SAMPLE_IMAGES
    first and four times as many when those show no common board.

    Raises:
        HandEyeError: one line naming the size the images show (when ``given``
            is not it) or saying that no common size was found.
    """
    images: list[np.ndarray] = []
    found = None
    for count in (SIZE_SAMPLE_IMAGES, 4 * SIZE_SAMPLE_IMAGES):
        images = sample_images(path, topic, count)
        found = find_board_size(images)
        if found is not None:
            break
    if found is None:
        sizes = ", ".join(f"{c}x{r}" for c, r in COMMON_BOARDS)
        what = f"board {given} is not" if given else "no common checkerboard is"
        raise HandEyeError(
            f"{what} found in {len(images)} images sampled from {path} (tried {sizes}); "
            "pass --board COLSxROWS (inner corners)"
        )
    (columns, rows), seen = found
    if given is not None and parse_board(given, square_mm).pattern_size != (columns, rows):
        raise HandEyeError(
            f"board {given} is not found in {path}, but {columns}x{rows} inner corners are "
            f"(in {seen} of {len(images)} sampled images): pass --board {columns}x{rows}"
        )
    return Checkerboard(columns, rows, square_mm * 1e-3)


def with_estimated_square(
    observations: BagObservations,
    board: Checkerboard,
    search: OffsetSearch | None = None,
    max_gap_ns: int = 60 * MS,
) -> tuple[BagObservations, Checkerboard]:
    """The observations and board with the square side estimated from the tracker.

    ``observations`` were solved with ``board``'s (nominal) square; the board
    views are rescaled to the estimate
    (:func:`~endo_tracker_bridge.handeye.estimate_square_size`).
    """
    square_m = estimate_square_size(
        observations.views,
        observations.tracker_stamps_ns,
        observations.tracker_poses,
        board,
        observations.camera,
        search,
        max_gap_ns=max_gap_ns,
    )
    views = scaled_views(observations.views, square_m / board.square_m)
    return replace(observations, views=views), Checkerboard(board.columns, board.rows, square_m)


def calibrate_observations(
    observations: BagObservations,
    board: Checkerboard,
    search: OffsetSearch | None = None,
    *,
    max_gap_ns: int = 60 * MS,
) -> HandEyeResult:
    """:func:`~endo_tracker_bridge.handeye.calibrate_hand_eye` on what a bag gave.

    Args:
        observations: from :func:`read_observations`.
        board: the checkerboard seen in the images.
        search: the clock offset search (default :class:`OffsetSearch`'s).
        max_gap_ns: longest tracker dropout bridged by interpolation, ns.

    Raises:
        HandEyeError: too few views, too little rotation, or no solution.
    """
    return calibrate_hand_eye(
        observations.views,
        observations.tracker_stamps_ns,
        observations.tracker_poses,
        board,
        observations.camera,
        search,
        max_gap_ns=max_gap_ns,
    )


def result_to_calibration(
    result: HandEyeResult,
    observations: BagObservations,
    provenance: dict[str, object] | None = None,
) -> HandEyeCalibration:
    """The handeye.yaml content of a solver result (``provenance``: see endo_io.provenance)."""
    return HandEyeCalibration(
        provenance=dict(provenance or {}),
        T_marker_camera=result.T_marker_camera,
        time_offset_ns=result.time_offset_ns,
        residuals={
            "reprojection_rms_px": result.reprojection_rms_px,
            "translation_rms_mm": result.translation_rms_mm,
            "rotation_rms_deg": result.rotation_rms_deg,
        },
        method=result.method,
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        views_used=result.views_used,
        views_total=result.views_total,
        T_tracker_target=result.T_tracker_target,
        details={
            "closed_form": result.closed_form,
            "images_read": observations.images,
            "tracker_poses": len(observations.tracker_stamps_ns),
            "offset_search_ms": [result.coarse_offsets_ms[0], result.coarse_offsets_ms[-1]],
            "residual_meaning": (
                "translation_rms_mm/rotation_rms_deg: RMS difference between each measured "
                "marker pose and the one predicted from its board view; reprojection_rms_px: "
                "board corners projected through tracker pose and calibration"
            ),
        },
    )


def _summary_lines(result: HandEyeResult, observations: BagObservations) -> Iterator[str]:
    yield (
        f"board found in {len(observations.views)} of {observations.images} images; "
        f"{len(observations.tracker_stamps_ns)} tracker poses"
    )
    for method, values in result.closed_form.items():
        yield (
            f"  closed form {method:<10} residual {values['translation_rms_mm']:.3f} mm "
            f"{values['rotation_rms_deg']:.3f} deg"
        )
    yield f"chosen: {result.method}; views used {result.views_used}/{result.views_total}"
    yield f"time offset (tracker_stamp = camera_time + offset): {result.time_offset_ns / MS:.3f} ms"
    yield (
        f"residuals: {result.translation_rms_mm:.3f} mm, {result.rotation_rms_deg:.3f} deg, "
        f"reprojection {result.reprojection_rms_px:.2f} px"
    )
    T = result.T_marker_camera
    yield f"T_marker_camera translation (mm): {np.array2string(T[:3, 3] * 1e3, precision=3)}"


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-handeye`` command line."""
    parser = argparse.ArgumentParser(
        prog="endo-handeye",
        description="Hand-eye (T_marker_camera) and tracker clock offset from a checkerboard bag.",
    )
    parser.add_argument("bag", type=Path, help="rosbag2 MCAP file or directory")
    parser.add_argument("-o", "--output", type=Path, default=Path("handeye.yaml"),
                        help="the calibration YAML (default handeye.yaml; an existing one "
                        "only with --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing -o file")
    parser.add_argument(
        "--board",
        default=None,
        metavar="COLSxROWS",
        help="inner corners of the checkerboard (default: detected among common sizes)",
    )
    parser.add_argument(
        "--square-mm",
        type=float,
        default=None,
        help="checkerboard square side in mm (default: estimated from the tracker)",
    )
    parser.add_argument("--report", type=Path, help="write the hand-eye report figure (PNG)")
    parser.add_argument("--image-topic", default=BagTopics.image,
                        help="the checkerboard images (default %(default)s)")
    parser.add_argument("--camera-info-topic", default=BagTopics.camera_info,
                        help="their camera_info (default %(default)s)")
    parser.add_argument("--pose-topic", default=BagTopics.pose,
                        help="the tracker's PoseStamped marker poses (default %(default)s)")
    parser.add_argument("--pose-unit", choices=("m", "mm"), default="m",
                        help="unit of the poses' positions (default m; mm for a tracker "
                        "driver publishing millimetres)")
    parser.add_argument(
        "--offset-range-ms",
        type=float,
        nargs=2,
        default=(-200.0, 200.0),
        metavar=("LOW", "HIGH"),
        help="clock offset search range in ms (default -200 200; equal values fix the offset)",
    )
    parser.add_argument(
        "--offset-step-ms", type=float, default=4.0, help="coarse search step in ms (default 4)"
    )
    parser.add_argument(
        "--max-views", type=int, default=0, help="use at most this many images (0: all)"
    )
    parser.add_argument(
        "--max-gap-ms",
        type=float,
        default=60.0,
        help="longest tracker dropout bridged by interpolation, ms (default 60)",
    )
    return parser


def parse_board(text: str, square_mm: float) -> Checkerboard:
    """``"9x6"`` and a square size in mm → Checkerboard; HandEyeError if malformed."""
    try:
        columns, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise HandEyeError(f"--board must look like 9x6, got '{text}'") from None
    return Checkerboard(columns, rows, square_mm * 1e-3)


@exit_on_error("endo-handeye")
def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``endo-handeye``; exit code 0 on success, 2 on bad input."""
    options = build_parser().parse_args(argv)
    # before reading the bag: a calibration the user has is never replaced silently
    refuse_existing(options.output, overwrite=options.overwrite)
    topics = BagTopics(options.image_topic, options.camera_info_topic, options.pose_topic)
    nominal_mm = options.square_mm if options.square_mm is not None else NOMINAL_SQUARE_MM
    unit = LengthUnit.parse(options.pose_unit)
    if options.board is not None:
        board = parse_board(options.board, nominal_mm)
        # Another common board plainly in view of a few sampled images (OpenCV's fast
        # check) while the given one is in none: say so at once, not after searching
        # every image for a board that is not there (~20 s on the sample bag).
        sampled = sample_images(options.bag, topics.image)
        if find_board_size(sampled, (board.pattern_size,)) is None and find_board_size(sampled):
            resolve_board(options.bag, topics.image, options.board, nominal_mm)
        observations = read_observations(options.bag, board, topics, unit, options.max_views)
        if len(observations.views) < MIN_VIEWS:
            # the board given is (almost) nowhere: name the one the images show
            resolve_board(options.bag, topics.image, options.board, nominal_mm)
    else:
        board = resolve_board(options.bag, topics.image, None, nominal_mm)
        print(f"board: {board.columns}x{board.rows} inner corners (detected)")
        observations = read_observations(options.bag, board, topics, unit, options.max_views)
    if observations.skipped_poses:
        print(f"endo-handeye: warning: left out {observations.skipped_poses} tracker samples "
              f"that give no pose; the first: {observations.first_skipped}",
              file=sys.stderr)  # fmt: skip
    low, high = (round(v * MS) for v in options.offset_range_ms)
    search = OffsetSearch(low, high, round(options.offset_step_ms * MS))
    max_gap_ns = round(options.max_gap_ms * MS)
    square_source = "given (--square-mm)"
    if options.square_mm is None:
        observations, board = with_estimated_square(observations, board, search, max_gap_ns)
        square_m = board.square_m
        square_source = "estimated from the tracker (pass --square-mm to fix it)"
        print(f"square: {square_m * 1e3:.3f} mm, {square_source}")
    result = calibrate_observations(observations, board, search, max_gap_ns=max_gap_ns)
    provenance = {
        "input": file_record(options.bag),
        "topics": {"image": topics.image, "camera_info": topics.camera_info, "pose": topics.pose},
        "camera_info": camera_record(observations.camera, f"bag topic {topics.camera_info}"),
        "board": {
            "inner_corners": f"{board.columns}x{board.rows}",
            "size_source": "given (--board)" if options.board else "detected",
            "square_mm": board.square_m * 1e3,
            "square_source": square_source,
        },
        "pose_unit": options.pose_unit,
        "tool": tool_record("endo-handeye", argv),
    }
    result_to_calibration(result, observations, provenance).save(options.output)
    for line in _summary_lines(result, observations):
        print(line)
    print(f"wrote {options.output}")
    if options.report is not None:
        from endo_tracker_bridge.handeye_report import write_handeye_report

        print(f"wrote {write_handeye_report(result, options.report, provenance)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
