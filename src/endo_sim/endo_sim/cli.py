"""``endo-sim``: render simulated endoscopy to bags, or publish it live.

    endo-sim render colon -o bags/phantom_colon.mcap --duration 10 --seed 1
    endo-sim render graycard -o graycard.mcap --frames-per-level 10
    endo-sim live colon --ros-args -r /endoscope/image_raw:=/camera/image_raw

SCENE is one of colon, abdomen, graycard, handeye. Both commands build the
same :class:`~endo_sim.sequences.Sequence` from the options; ``render``
writes it with :func:`~endo_sim.bagout.write_bag`, ``live`` publishes it
with :class:`~endo_sim.node.SimulatorNode`.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from endo_io.cli import exit_on_error, refuse_existing
from endo_io.progress import Progress
from endo_io.topics import IMAGE_RAW
from endo_sim.errors import SimulationParameterError
from endo_sim.graycard import DEFAULT_CARD_DISTANCE_M
from endo_sim.photometry import Photometry
from endo_sim.response import CameraResponse
from endo_sim.sequences import SCENES, SimulationConfig, build_sequence
from endo_sim.texture import TextureOptions
from endo_sim.tracker import TRACKER_UNITS, TrackerModel

if TYPE_CHECKING:
    from endo_sim.bagout import SizeEstimate

GROUND_TRUTH_SUFFIXES = (
    ".ground_truth.yaml",
    ".camera.yaml",
    ".inverse_response.npy",
    ".light_map.npy",
)


#: ``live``'s default --duration (s): colon and abdomen go on this long before the motion repeats.
LIVE_DURATION_S = 3600.0


def _add_common(parser: argparse.ArgumentParser, *, live: bool = False) -> None:
    parser.add_argument("scene", choices=SCENES, help="what to simulate")
    g = parser.add_argument_group("camera")
    g.add_argument("--width", type=int, default=640, help="image width, pixels (640)")
    g.add_argument("--height", type=int, default=480, help="image height, pixels (480)")
    g.add_argument("--focal", type=float, default=None, help="focal length, pixels (width/2)")
    g.add_argument("--k1", type=float, default=0.0, help="radial distortion k1 (plumb_bob; 0)")
    g.add_argument("--k2", type=float, default=0.0, help="radial distortion k2 (plumb_bob; 0)")
    g.add_argument(
        "--fov-radius",
        type=float,
        default=None,
        help="circular field of view radius, pixels (height/2)",
    )
    g.add_argument("--fps", type=float, default=30.0, help="frame rate (30)")
    if live:
        g.add_argument("--duration", type=float, default=LIVE_DURATION_S,
                       help="colon/abdomen: the motion repeats after this many s "
                       f"(default {LIVE_DURATION_S:g})")  # fmt: skip
    else:
        g.add_argument("--duration", type=float, default=10.0,
                       help="length in s, colon/abdomen (10)")  # fmt: skip
    g.add_argument("--color", action="store_true", help="rgb8 instead of mono")
    g.add_argument(
        "--bit-depth",
        type=int,
        choices=(8, 12),
        default=8,
        help="8 (mono8/rgb8) or 12 (mono16 holding 0..4095)",
    )
    g.add_argument("--seed", type=int, default=0, help="seed of everything random (0)")
    p = parser.add_argument_group("photometry")
    defaults = Photometry()
    p.add_argument(
        "--noise",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="shot and read noise (on)",
    )
    p.add_argument(
        "--response",
        choices=("gamma", "s_curve"),
        default="gamma",
        help="camera response curve (gamma)",
    )
    p.add_argument(
        "--gamma", type=float, default=None, help="response exponent (gamma: 2.22, s_curve: 2.2)"
    )
    p.add_argument("--contrast", type=float, default=1.6, help="s_curve contrast (1.6)")
    p.add_argument(
        "--roughness",
        type=float,
        default=defaults.roughness,
        help=f"Oren-Nayar sigma, rad ({defaults.roughness}; 0 = Lambertian)",
    )
    p.add_argument(
        "--full-scale-distance",
        type=float,
        default=defaults.full_scale_distance_m,
        help="exposure: distance (m) at which white reaches full scale "
        f"({defaults.full_scale_distance_m})",
    )
    p.add_argument(
        "--light-offset",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="light position in the optical frame, m (0 0 0)",
    )
    p.add_argument(
        "--spot-exponent",
        type=float,
        default=defaults.spot_exponent,
        help=f"light spot profile cos^p (p = {defaults.spot_exponent})",
    )
    p.add_argument(
        "--vignetting",
        type=float,
        default=defaults.vignetting_exponent,
        help=f"vignetting cos^q (q = {defaults.vignetting_exponent})",
    )
    p.add_argument(
        "--specular",
        type=float,
        default=defaults.specular_strength,
        help=f"specular strength ({defaults.specular_strength})",
    )
    p.add_argument(
        "--shininess",
        type=float,
        default=defaults.specular_shininess,
        help=f"specular shininess ({defaults.specular_shininess})",
    )
    p.add_argument(
        "--full-well",
        type=float,
        default=defaults.full_well_electrons,
        help=f"full-well electrons ({defaults.full_well_electrons:g})",
    )
    p.add_argument(
        "--read-noise",
        type=float,
        default=defaults.read_noise_electrons,
        help=f"read noise, electrons RMS ({defaults.read_noise_electrons:g})",
    )
    x = parser.add_argument_group("tissue texture (colon, abdomen)")
    xdef = TextureOptions()
    x.add_argument(
        "--albedo-drift",
        type=float,
        default=xdef.drift,
        help=f"amplitude of ln albedo's slow (4 mm) drift ({xdef.drift})",
    )
    x.add_argument(
        "--albedo-mottle",
        type=float,
        default=xdef.mottle,
        help=f"relative amplitude of the fine (0.3 mm) mottling ({xdef.mottle})",
    )
    x.add_argument(
        "--vessel-density",
        type=float,
        default=xdef.vessel_density_per_cm2,
        help=f"vessel trees per cm² ({xdef.vessel_density_per_cm2}; 0: none)",
    )
    t = parser.add_argument_group("tracker")
    tdef = TrackerModel()
    t.add_argument(
        "--tracker-units",
        choices=TRACKER_UNITS,
        default="m",
        help="units of /tracker/pose positions (m)",
    )
    t.add_argument("--tracker-rate", type=float, default=tdef.rate_hz, help="Hz (60)")
    t.add_argument(
        "--tracker-latency",
        type=float,
        default=tdef.latency_s,
        help=f"stamp minus sample time, s ({tdef.latency_s})",
    )
    t.add_argument(
        "--tracker-noise-mm",
        type=float,
        default=tdef.position_noise_rms_m * 1e3,
        help="3-D RMS position noise, mm (0.25)",
    )
    t.add_argument(
        "--tracker-noise-deg",
        type=float,
        default=math.degrees(tdef.rotation_noise_rms_rad),
        help="RMS rotation noise, degrees (0.1)",
    )
    t.add_argument(
        "--dropout-rate",
        type=float,
        default=tdef.dropout_rate_hz,
        help=f"occlusions per second ({tdef.dropout_rate_hz})",
    )
    s = parser.add_argument_group("sequence")
    s.add_argument(
        "--depth-every", type=int, default=1, help="ground-truth depth with every n-th frame (1)"
    )
    s.add_argument(
        "--frames-per-level", type=int, default=10, help="gray card frames per card (10)"
    )
    s.add_argument(
        "--card-distance",
        type=float,
        default=DEFAULT_CARD_DISTANCE_M,
        help=f"gray card distance, m ({DEFAULT_CARD_DISTANCE_M}: the 0.8 card just saturates)",
    )
    s.add_argument("--stations", type=int, default=15, help="hand-eye stations (15)")
    s.add_argument("--dwell", type=float, default=0.8, help="hand-eye dwell per station, s (0.8)")
    s.add_argument(
        "--move", type=float, default=1.6, help="hand-eye move between stations, s (1.6)"
    )


def config_from_args(args: argparse.Namespace) -> SimulationConfig:
    """The :class:`SimulationConfig` the parsed options describe."""
    if args.response == "gamma":
        response = CameraResponse.gamma(args.gamma) if args.gamma else CameraResponse.gamma()
    else:
        response = CameraResponse.s_curve(args.gamma or 2.2, args.contrast)
    photometry = Photometry(
        roughness=args.roughness,
        full_scale_distance_m=args.full_scale_distance,
        light_offset_m=tuple(args.light_offset),
        spot_exponent=args.spot_exponent,
        vignetting_exponent=args.vignetting,
        response=response,
        noise=args.noise,
        full_well_electrons=args.full_well,
        read_noise_electrons=args.read_noise,
        bit_depth=args.bit_depth,
        specular_strength=args.specular,
        specular_shininess=args.shininess,
    )
    tracker = TrackerModel(
        rate_hz=args.tracker_rate,
        latency_s=args.tracker_latency,
        position_noise_rms_m=args.tracker_noise_mm * 1e-3,
        rotation_noise_rms_rad=math.radians(args.tracker_noise_deg),
        dropout_rate_hz=args.dropout_rate,
        units=args.tracker_units,
        phase_s=min(TrackerModel().phase_s, 0.5 / args.tracker_rate),
    )
    return SimulationConfig(
        scene=args.scene,
        width=args.width,
        height=args.height,
        focal_px=args.focal,
        distortion=(args.k1, args.k2),
        fov_radius_px=args.fov_radius,
        fps=args.fps,
        duration_s=args.duration,
        channels=3 if args.color else 1,
        seed=args.seed,
        depth_every=args.depth_every,
        photometry=photometry,
        tracker=tracker,
        texture=TextureOptions(
            drift=args.albedo_drift,
            mottle=args.albedo_mottle,
            vessel_density_per_cm2=args.vessel_density,
        ),
        frames_per_level=args.frames_per_level,
        card_distance_m=args.card_distance,
        stations=args.stations,
        dwell_s=args.dwell,
        move_s=args.move,
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-sim`` argument parser (subcommands ``render`` and ``live``)."""
    from endo_io.bag.writer import OUTPUT_PATH_HELP  # the writer's modules: only when parsing

    parser = argparse.ArgumentParser(
        prog="endo-sim", description="Simulated tracked endoscope with ground truth."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    render = sub.add_parser("render", help="write a rosbag2 MCAP bag and ground-truth files")
    _add_common(render)
    render.add_argument("-o", "--output", type=Path, required=True,
                        help="the bag; " + OUTPUT_PATH_HELP + "; the ground truth is written "
                        "beside it (NAME.ground_truth.yaml, ...)")
    render.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                        help="chunk compression of the bag (default zstd)")
    render.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing bag and its ground-truth files",
    )
    render.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bar (it is shown only on a terminal anyway)")
    live = sub.add_parser("live", help="publish in real time (stand-in camera driver + tracker)")
    _add_common(live, live=True)
    return parser


#: A bag larger than this is announced before rendering.
LARGE_BAG_BYTES = 100_000_000


def _warn_if_large(estimate: SizeEstimate, depth_every: int, fps: float) -> None:
    """One line on stderr when the bag will be large, saying how to keep depth sparse."""
    if estimate.total_bytes <= LARGE_BAG_BYTES:
        return
    line = f"endo-sim: the bag will be about {estimate.total_bytes / 1e6:.0f} MB"
    if estimate.depth_bytes > estimate.total_bytes / 4:
        sparse = max(depth_every, round(fps))
        share = estimate.depth_bytes / 1e6
        kept = estimate.total_bytes - estimate.depth_bytes * (1.0 - depth_every / sparse)
        line += (f", {share:.0f} MB of it ground-truth depth ({estimate.depth_frames} frames "
                 f"of 32FC1); --depth-every {sparse} keeps one per second (about "
                 f"{kept / 1e6:.0f} MB)")  # fmt: skip
    print(line, file=sys.stderr)


def _render(args: argparse.Namespace) -> int:
    output: Path = args.output
    if output.is_dir():  # an existing bag directory is never deleted, --overwrite or not
        raise SimulationParameterError(f"{output} is a directory (-o names a new bag: "
                                       f"{output}.mcap, or a directory that does not exist yet)")
    targets = [output] + [output.with_name(output.stem + s) for s in GROUND_TRUTH_SUFFIXES]
    refuse_existing(*targets, overwrite=args.overwrite)
    for path in targets:
        path.unlink(missing_ok=True)
    from endo_sim.bagout import estimated_size, write_bag  # rclpy types; only needed here

    sequence = build_sequence(config_from_args(args))
    frames = len(sequence.frame_times_ns)
    _warn_if_large(estimated_size(sequence.config, frames), sequence.config.depth_every,
                   sequence.config.fps)  # fmt: skip
    progress = Progress(frames, enabled=not args.quiet,
                        description="endo-sim")  # fmt: skip
    try:
        summary = write_bag(sequence, output, args.compression, progress.update)
    finally:
        progress.close()
    print(f"endo-sim: wrote {summary.bag_path} ({summary.bag_bytes / 1e6:.2f} MB)")
    for topic, count in summary.message_counts.items():
        print(f"  {topic}: {count} messages")
    for path in summary.ground_truth_paths:
        print(f"  ground truth: {path}")
    if summary.failure:  # a full disk: what is on disk is readable and counted above
        print(f"endo-sim: error: writing stopped after {summary.message_counts[IMAGE_RAW]} of "
              f"{frames} frames: {summary.failure}", file=sys.stderr)  # fmt: skip
        return 1
    return 0


def _live(args: argparse.Namespace, argv: Sequence[str]) -> int:
    from endo_io.process import run_node
    from endo_sim.node import SimulatorNode

    sequence = build_sequence(config_from_args(args))
    return run_node(lambda: SimulatorNode(sequence), args=argv)


@exit_on_error("endo-sim")
def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; exit code 0 on success, 2 on bad input, 1 when writing failed.

    A full disk (or file size limit) stops ``render``: the bag reads to its
    last complete chunk, the counts printed are what it holds, and one line
    on stderr names the cause.
    """
    full = list(sys.argv if argv is None else [sys.argv[0], *argv])
    from rclpy.utilities import remove_ros_args

    args = build_parser().parse_args(remove_ros_args(full)[1:])
    if args.command == "render":
        return _render(args)
    return _live(args, full)


if __name__ == "__main__":
    sys.exit(main())
