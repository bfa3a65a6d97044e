"""``endo-calibrate``: fit a photometric calibration from gray-card images.

Input is either a gray-card bag (image topic plus ``/calibration/gray_level``,
std_msgs/Float32 with the reflectance of the card in view) or a manifest YAML::

    camera_info: camera.yaml          # optional, else --camera-info
    bit_depth: 8                      # optional
    card: {distance_m: 0.05, normal: [0, 0, -1]}   # optional
    levels:
      - reflectance: 0.2
        images: [card20_0.png, card20_1.png]   # relative to the manifest
      - reflectance: 0.3
        images: [...]
        card: {distance_m: 0.04}      # optional per-level pose

It writes ``photometric.yaml`` (plus the light-map PNG beside it), optionally
the report figure and the TUM/DSO files. ``--import-dso`` converts a DSO
calibration instead of fitting one.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from endo_calib.calibration import LIGHT_SOURCES, PhotometricCalibration
from endo_calib.dso import export_dso, import_dso
from endo_calib.errors import CalibrationError, InsufficientLevelsError, ManifestError
from endo_calib.fit import FitReport, fit_gray_card
from endo_calib.geometry import CardPose
from endo_calib.gray_levels import GrayCardAccumulator
from endo_calib.raw_image import to_raw_frame
from endo_io import topics
from endo_io.camera import CameraModel
from endo_io.cli import exit_on_error, refuse_existing
from endo_io.provenance import camera_record, file_record, tool_record

#: A level message logged this long after an image still applies to it (ns).
LEVEL_TOLERANCE_NS = 5_000_000


def truth_beside(source: Path | None) -> NDArray[np.float64] | None:
    """endo_sim's ``<stem>.inverse_response.npy`` beside a bag or manifest, when present.

    Simulated recordings carry their ground truth beside them; the report
    overlays it. Returns the (2^bits,) table or None.
    """
    if source is None:
        return None
    path = source.with_name(source.stem + ".inverse_response.npy")
    if not path.is_file():
        return None
    try:
        table = np.load(path)
    except (OSError, ValueError):
        return None
    return np.asarray(table, dtype=np.float64).ravel()


def read_raw_image(path: Path) -> NDArray[np.integer]:
    """Read an 8/16-bit PNG/TIFF as (H, W) or (H, W, 3) RGB; ManifestError when unreadable."""
    if not path.is_file():
        raise ManifestError(f"image {path} not found")
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise ManifestError(f"image {path} cannot be decoded")
    if decoded.dtype not in (np.uint8, np.uint16):
        raise ManifestError(f"image {path} is {decoded.dtype}, raw 8- or 16-bit values are needed")
    image = cast("NDArray[np.integer]", decoded)
    if image.ndim == 3:
        image = to_raw_frame(image, "bgra8" if image.shape[2] == 4 else "bgr8")
    return np.ascontiguousarray(image)


def card_pose(spec: Any, base: CardPose) -> CardPose:
    """A CardPose from a manifest mapping ({distance_m, normal}), defaults from ``base``."""
    if spec is None:
        return base
    if not isinstance(spec, dict):
        raise ManifestError(f"card must be a mapping of distance_m/normal, got {spec!r}")
    try:
        normal = tuple(float(x) for x in spec.get("normal", base.normal))
        pose = CardPose(
            normal=(normal[0], normal[1], normal[2]),
            distance_m=float(spec.get("distance_m", base.distance_m)),
        )
        pose.unit_normal()
    except (TypeError, ValueError, IndexError) as error:
        raise ManifestError(f"invalid card pose {spec!r}: {error}") from error
    return pose


def load_manifest(path: Path) -> dict[str, Any]:
    """Read and check the top level of a manifest YAML (see the module docstring)."""
    if not path.is_file():
        raise ManifestError(f"manifest {path} not found")
    try:
        manifest = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as error:
        raise ManifestError(
            f"manifest {path} is not valid YAML: {str(error).splitlines()[0]}"
        ) from error
    if not isinstance(manifest, dict) or not isinstance(manifest.get("levels"), list):
        raise ManifestError(f"manifest {path} needs a 'levels' list")
    return manifest


def accumulate_manifest(
    manifest: dict[str, Any], base_dir: Path, accumulator: GrayCardAccumulator, base_pose: CardPose
) -> None:
    """Stream every image a manifest names (paths relative to ``base_dir``) into ``accumulator``."""
    default_pose = card_pose(manifest.get("card"), base_pose)
    for index, level in enumerate(manifest["levels"]):
        if not isinstance(level, dict) or "reflectance" not in level:
            raise ManifestError(f"manifest level {index} needs a reflectance")
        try:
            reflectance = float(level["reflectance"])
            exposure = float(level.get("exposure", 1.0))
        except (TypeError, ValueError) as error:
            raise ManifestError(f"manifest level {index}: {error}") from error
        images = level.get("images") or []
        if not isinstance(images, list) or not images:
            raise InsufficientLevelsError(f"manifest gray level {reflectance:g} lists no images")
        pose = card_pose(level.get("card"), default_pose)
        for name in images:
            frame = read_raw_image(base_dir / str(name))
            accumulator.add(frame, reflectance, pose, exposure)


def accumulate_bag(
    path: Path,
    accumulator: GrayCardAccumulator,
    pose: CardPose,
    image_topic: str,
    level_topic: str,
    info_topic: str,
    settle_frames: int = 0,
    level_tolerance_ns: int = LEVEL_TOLERANCE_NS,
) -> CameraModel | None:
    """Stream a gray-card bag into ``accumulator``; returns the bag's camera model if it has one.

    Each image takes the gray level of the last level message logged no later
    than ``level_tolerance_ns`` after it: a recorder may log the level of a new
    card a moment after (or, at the same time stamp, just after) the card's
    first frame. Images before the first level, and the first
    ``settle_frames`` after each change, are skipped.
    """
    from sensor_msgs.msg import CameraInfo, Image

    from endo_io.bag import BagReader, deserialize, msgtype_of
    from endo_io.image import image_to_array

    camera: CameraModel | None = None
    with BagReader(path) as bag:
        if image_topic not in bag.topics:
            raise ManifestError(f"bag {path} has no topic {image_topic}")
        if level_topic not in bag.topics:
            raise InsufficientLevelsError(f"bag {path} has no gray-level topic {level_topic}")
        bag.check_types({image_topic: msgtype_of(Image), info_topic: msgtype_of(CameraInfo)})
        # First pass: the (small) gray-level stream.
        level_times: list[int] = []
        level_values: list[float] = []
        for message in bag.messages(topics=[level_topic]):
            level_times.append(message.log_time_ns)
            level_values.append(float(deserialize(message).data))
        times = np.asarray(level_times, dtype=np.int64)
        current: float | None = None
        since_change = 0
        for message in bag.messages(topics=[image_topic, info_topic]):
            msg = deserialize(message)
            if message.topic == info_topic:
                if camera is None:
                    camera = CameraModel.from_camera_info(msg)
                continue
            index = (
                int(np.searchsorted(times, message.log_time_ns + level_tolerance_ns, "right")) - 1
            )
            if index < 0:
                continue
            level = level_values[index]
            if level != current:
                current, since_change = level, 0
            since_change += 1
            if level <= 0.0 or since_change <= settle_frames:
                continue
            frame = to_raw_frame(image_to_array(msg), msg.encoding)
            accumulator.add(frame, level, pose)
    return camera


def fit_provenance(
    args: argparse.Namespace,
    camera_source: str,
    camera: CameraModel,
    argv: Sequence[str] | None,
) -> dict[str, Any]:
    """The ``provenance`` of a fitted photometric.yaml: input, topics, camera, card, run."""
    source = args.bag if args.bag is not None else args.manifest
    document: dict[str, Any] = {"input": file_record(source)}
    if args.bag is not None:
        document["topics"] = {
            "image": args.image_topic,
            "gray_level": args.gray_level_topic,
            "camera_info": args.camera_info_topic,
        }
    document["camera_info"] = camera_record(camera, camera_source)
    document["card"] = {
        "distance_m": float(args.card_distance),
        "normal": [float(x) for x in args.card_normal],
        "note": "the default for levels without their own card pose (a manifest may set them)",
    }
    document["tool"] = tool_record("endo-calibrate", argv)
    return document


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``endo-calibrate``."""
    parser = argparse.ArgumentParser(
        prog="endo-calibrate",
        description="Fit a camera's inverse response and light map from gray-card images.",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--bag", type=Path, help="gray-card bag (.mcap or rosbag2 directory)")
    source.add_argument("--manifest", type=Path, help="levels.yaml listing images per reflectance")
    source.add_argument(
        "--import-dso",
        type=Path,
        metavar="DIR",
        help="convert a TUM/DSO pcalib.txt + vignette.png instead of fitting",
    )
    parser.add_argument("--camera-info", type=Path, help="camera calibration YAML (for G)")
    parser.add_argument("--image-topic", default=topics.IMAGE_RAW,
                        help="the gray-card images in --bag (default %(default)s)")
    parser.add_argument("--gray-level-topic", default=topics.GRAY_LEVEL,
                        help="the card's reflectance per image in --bag (default %(default)s)")
    parser.add_argument("--camera-info-topic", default=topics.CAMERA_INFO,
                        help="camera_info in --bag (default %(default)s)")
    parser.add_argument(
        "--settle-frames",
        type=int,
        default=0,
        help="frames to skip after each gray-level change in a bag (default 0)",
    )
    parser.add_argument(
        "--card-distance",
        type=float,
        default=0.05,
        metavar="M",
        help="card distance from the optical centre in metres (default 0.05)",
    )
    parser.add_argument(
        "--card-normal",
        type=float,
        nargs=3,
        default=(0.0, 0.0, -1.0),
        metavar=("NX", "NY", "NZ"),
        help="card normal in the optical frame (default 0 0 -1: facing the camera)",
    )
    parser.add_argument("--bit-depth", type=int, help="raw bit depth (default: inferred)")
    parser.add_argument("--saturation-value", type=int, help="raw values >= this are saturated")
    parser.add_argument(
        "--light-degree", type=int, default=8, help="light model degree (default 8)"
    )
    parser.add_argument(
        "--light-source",
        choices=LIGHT_SOURCES,
        default="model",
        help="divide by the smooth light model or the per-pixel map (default model)",
    )
    parser.add_argument("-o", "--output", type=Path, default=Path("photometric.yaml"),
                        help="the calibration YAML, with <stem>.light_map.png beside it "
                        "(default photometric.yaml; an existing one only with --overwrite)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing -o file (and its light map)")
    parser.add_argument("--report", type=Path, help="write the report figure (PNG)")
    parser.add_argument(
        "--export-dso", type=Path, metavar="DIR", help="also write pcalib.txt + vignette.png"
    )
    parser.add_argument("--dso-channel", help="channel to export to DSO (default mono / green)")
    return parser


def run(args: argparse.Namespace, argv: Sequence[str] | None = None) -> PhotometricCalibration:
    """Execute a parsed command line; returns the calibration written.

    argv: the arguments it was parsed from (recorded in the provenance;
    default ``sys.argv[1:]``).
    """
    # refused before the fit: the user's calibration is never replaced silently
    refuse_existing(Path(args.output), overwrite=args.overwrite)
    report: FitReport | None = None
    if args.import_dso is not None:
        calibration = import_dso(args.import_dso)
    else:
        pose = CardPose(tuple(args.card_normal), args.card_distance)
        pose = card_pose({}, pose)
        camera = CameraModel.load_yaml(args.camera_info) if args.camera_info else None
        camera_source = f"file {args.camera_info}" if args.camera_info else ""
        if args.manifest is not None:
            manifest = load_manifest(args.manifest)
            bit_depth = args.bit_depth or manifest.get("bit_depth")
            accumulator = GrayCardAccumulator(
                int(bit_depth) if bit_depth else None, args.saturation_value
            )
            accumulate_manifest(manifest, args.manifest.parent, accumulator, pose)
            if camera is None and manifest.get("camera_info"):
                camera = CameraModel.load_yaml(args.manifest.parent / str(manifest["camera_info"]))
                camera_source = f"file {args.manifest.parent / str(manifest['camera_info'])}"
        else:
            accumulator = GrayCardAccumulator(args.bit_depth, args.saturation_value)
            bag_camera = accumulate_bag(
                args.bag,
                accumulator,
                pose,
                args.image_topic,
                args.gray_level_topic,
                args.camera_info_topic,
                args.settle_frames,
            )
            if camera is None and bag_camera is not None:
                camera, camera_source = bag_camera, f"bag topic {args.camera_info_topic}"
        if camera is None:
            raise ManifestError(
                "no camera model: pass --camera-info (or record camera_info in the bag)"
            )
        started = time.monotonic()
        report = fit_gray_card(
            accumulator,
            camera,
            saturation_value=args.saturation_value,
            light_model_degree=args.light_degree,
        )
        calibration = PhotometricCalibration.from_fit(report, args.light_source)
        calibration.provenance = fit_provenance(args, camera_source, camera, argv)
        for level in report.levels:
            print(
                f"level {level['reflectance']:.3g}: {level['frames']} frames, "
                f"{100 * level['usable_fraction']:.0f}% of the FOV usable"
            )
        for name, fit in report.channels.items():
            print(
                f"channel {name}: residual RMS {fit.residual_rms:.3f} DN, "
                f"{fit.iterations} iterations"
                f"{'' if fit.converged else ' (not converged)'}"
            )
            if fit.extent is not None:
                top = (1 << report.bit_depth) - 1
                extrapolated = (
                    f"; {fit.extent.observed_high + 1}..{top} extrapolated"
                    if fit.extent.observed_high < top - 1
                    else ""
                )
                print(
                    f"channel {name}: raw values {fit.extent.observed_low}.."
                    f"{fit.extent.observed_high} observed{extrapolated} "
                    f"(top: {fit.extent.top_model})"
                )
        print(f"fit took {time.monotonic() - started:.1f} s")
    written = calibration.save(args.output)
    print(f"wrote {written}")
    if args.report is not None:
        if report is None:
            raise CalibrationError("--report needs a gray-card fit; a DSO import has none")
        from endo_calib.report import write_report

        truth = truth_beside(args.bag if args.bag is not None else args.manifest)
        written_report = write_report(
            report,
            args.report,
            light_source=args.light_source,
            truth_inverse_response=truth,
            inputs=calibration.provenance,
        )
        print(f"wrote {written_report}")
    if args.export_dso is not None:
        pcalib, vignette = export_dso(calibration, args.export_dso, args.dso_channel)
        print(f"wrote {pcalib} and {vignette}")
    return calibration


@exit_on_error("endo-calibrate")
def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; exit code 0 on success, 2 on bad input."""
    run(build_parser().parse_args(argv), argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
