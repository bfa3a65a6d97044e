"""``endo-process``: a recording in, the live graph's outputs out, with a summary.

Exit status:

* 0: every frame of the recording was processed;
* 1: the recording is truncated or damaged (a cut, a lost chunk among or
  after the frames processed, a damaged record that lost no message, or
  messages whose bytes do not decode as their topic's type: those are
  skipped and counted; damage after the frames ``--max-frames`` processed is
  a note, exit 0: :mod:`endo_process.damage`), or no
  frame gave a relative depth: what could be processed was, and was written;
  or writing the output failed (a full disk, a file size limit): the run
  stopped there, the output reads to its last complete chunk (as
  endo-record's), and the summary counts what it holds; ``--ply`` is still
  written from the map in memory (it may name another disk), and the same
  line says whether it was;
  one line on stderr says what was wrong. Any run prints one line per cause
  of dropped frames and rejected tracker samples, with the first one's
  message (the table counts them);
* 2: an input or option is unusable (missing file or topic, no camera_info,
  a bad parameter file, an existing output): one line on stderr, nothing
  written;
* 130: stopped by Ctrl-C or SIGTERM; the output holds every frame processed
  until then and is a complete, finalised MCAP.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from endo_io import topics
from endo_io.cli import EXIT_BAD_INPUT, refuse_existing, report_error
from endo_io.errors import Endo3dError
from endo_process.runtime import one_blas_thread, reuse_freed_memory
from endo_process.worker_start import StartedWorkers, start_workers

if TYPE_CHECKING:
    from endo_process.runner import ProcessOptions, ProcessReport

# The pipeline's modules (flow, SFS, matplotlib, ...) are imported in main():
# a --jobs worker process re-imports this module as its main module, and
# needs none of them (start-up CPU per worker: docs/benchmarks.md).

PROGRAM = "endo-process"
EXIT_OK, EXIT_DAMAGED, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, EXIT_BAD_INPUT, 130


def build_parser() -> argparse.ArgumentParser:
    """The command line."""
    from endo_io.bag.writer import OUTPUT_PATH_HELP  # not at import: a worker needs none of it

    parser = argparse.ArgumentParser(
        prog=PROGRAM,
        description="Run the endo3d graph's cores offline over a recording (no DDS): "
        "photometric correction, shape from shading, tracker poses via hand-eye, "
        "flow and scale; write the live graph's topics to an MCAP and print a summary.",
    )
    parser.add_argument("bag", type=Path, help="rosbag2 MCAP file or bag directory")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="the output bag; " + OUTPUT_PATH_HELP)
    parser.add_argument("--calibration", type=Path, required=True,
                        help="photometric.yaml (endo-calibrate)")
    parser.add_argument("--handeye", type=Path, required=True, help="handeye.yaml (endo-handeye)")
    parser.add_argument("--params", type=Path,
                        help="ROS 2 parameter file of the nodes (sfs, tracker_bridge, ...)")
    parser.add_argument("--solve-scale", type=float,
                        help="the SFS node's solve_scale (overrides --params)")
    parser.add_argument("--image-topic", default=topics.IMAGE_RAW,
                        help="the raw camera images (default %(default)s)")
    parser.add_argument("--camera-info-topic", default=topics.CAMERA_INFO,
                        help="their camera_info (default %(default)s)")
    parser.add_argument("--tracker-topic", default=topics.TRACKER_POSE,
                        help="the tracker driver's PoseStamped marker poses "
                        "(default %(default)s)")
    parser.add_argument("--camera-info", type=Path,
                        help="camera YAML (camera_calibration format) instead of the topic")
    parser.add_argument("--ply", type=Path, help="write the fused map as PLY")
    parser.add_argument("--cloud-decimation", type=int, default=None, metavar="N",
                        help="/endoscope/points takes every N-th pixel per axis (default: the "
                        "parameter file's cloud_decimation, 4, as the live topic; 1 is full "
                        "resolution at 32 B a point: the phantom's output 6.8 MB per frame "
                        "against 3.2); the map is fused at the flow node's map_decimation "
                        "(1: every pixel) either way")
    parser.add_argument("--jobs", type=int, default=2,
                        help="SFS chains (default 2: correction + SFS in 2 worker processes "
                        "taking the frames in turn, flow and writing in this one; 1: all in "
                        "this process)")
    parser.add_argument("--chunk-frames", type=int, default=1,
                        help="consecutive frames per worker turn with --jobs > 1 (default 1; "
                        "above 1 each turn starts cold)")
    parser.add_argument("--compression", choices=("zstd", "lz4", "none"), default="none",
                        help="output chunk compression (default none, as rosbag2 records: "
                        "~3.7 MB per 640x480 frame; lz4 ~2.1 MB for ~1.5 CPU-ms more per "
                        "frame, zstd ~1.8 MB)")
    parser.add_argument("--direct", action=argparse.BooleanOptionalAction, default=True,
                        help="write the output with O_DIRECT, past the page cache (default; "
                        "a file system that refuses it is written as usual); --no-direct "
                        "writes through the page cache (slow or network storage)")
    parser.add_argument("--chunk-crc", action="store_true",
                        help="store each output chunk's CRC-32 (off by default, as in "
                        "rosbag2's MCAP writer: it costs CPU on every byte written)")
    parser.add_argument("--report", type=Path,
                        help="draw a figure of the run (PNG): frames, errors, cloud, scale, "
                        "calibration")
    parser.add_argument("--summary-json", type=Path,
                        help="also write every summary figure to this JSON file")
    parser.add_argument("--max-frames", type=int, help="process only the first N images")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return parser  # fmt: skip


class _StopOnSignal:
    """SIGINT/SIGTERM set a flag the frame loop checks; a second SIGINT interrupts at once."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.event.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.event.set()

    def __enter__(self) -> threading.Event:
        for signum in self._previous:
            signal.signal(signum, self._handle)
        return self.event

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def _options(args: argparse.Namespace) -> ProcessOptions:
    from endo_process.inputs import InputTopics
    from endo_process.runner import ProcessOptions

    if args.jobs < 1:
        raise Endo3dError(f"--jobs must be >= 1, got {args.jobs}")
    if args.chunk_frames < 1:
        raise Endo3dError(f"--chunk-frames must be >= 1, got {args.chunk_frames}")
    if args.cloud_decimation is not None and args.cloud_decimation < 1:
        raise Endo3dError(f"--cloud-decimation must be >= 1, got {args.cloud_decimation}")
    if args.max_frames is not None and args.max_frames < 1:
        raise Endo3dError(f"--max-frames must be >= 1, got {args.max_frames}")
    for name in ("bag", "calibration", "handeye", "params", "camera_info"):
        path = getattr(args, name)
        if path is not None and not path.exists():
            option = "the recording" if name == "bag" else f"--{name.replace('_', '-')}"
            raise Endo3dError(f"{path}: no such file ({option})")
    if args.output.is_dir():
        raise Endo3dError(f"{args.output} is a directory (-o names a new bag: "
                          f"{args.output}.mcap, or a directory that does not exist yet)")
    refuse_existing(args.output, overwrite=args.overwrite)
    for name in ("report", "summary_json", "ply"):  # refused now, not after the run
        path = getattr(args, name)
        option = f"--{name.replace('_', '-')}"
        if path is not None and path.is_dir():
            raise Endo3dError(f"{path} is a directory ({option} names a file)")
        if path is not None and not path.parent.is_dir():
            raise Endo3dError(f"{path}: parent directory does not exist ({option})")
    return ProcessOptions(
        bag=args.bag, output=args.output, calibration=args.calibration, handeye=args.handeye,
        params=args.params, solve_scale=args.solve_scale,
        topics=InputTopics(args.image_topic, args.camera_info_topic, args.tracker_topic),
        camera_info=args.camera_info, ply=args.ply, cloud_decimation=args.cloud_decimation,
        jobs=args.jobs,
        chunk_frames=args.chunk_frames, compression=args.compression,
        chunk_crcs=args.chunk_crc, direct=args.direct, progress=not args.quiet,
        max_frames=args.max_frames,
        overwrite=args.overwrite,
    )  # fmt: skip


def exit_status(report: ProcessReport) -> int:
    """The documented exit status of a finished run."""
    if report.interrupted:
        return EXIT_INTERRUPTED
    nothing = report.frames_in > 0 and report.frames_shaded == 0
    failed = report.damage or report.undecodable or report.write_failure
    return EXIT_DAMAGED if failed or nothing else EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point of ``endo-process``."""
    one_blas_thread()  # before numpy is imported (endo_process.runtime)
    args = build_parser().parse_args(argv)
    reuse_freed_memory()  # fewer page faults per frame (endo_process.runtime)
    # The shading workers first: they import their modules beside this
    # process's own imports below (~2 s), not after them.
    workers = start_workers(args.jobs) if args.jobs > 1 else None
    try:
        return _run(args, workers)
    finally:
        if workers is not None:
            workers.close()  # a no-op once the run took them


def _ply_outcome(ply: Path | None, report: ProcessReport) -> str:
    """What became of --ply after the output's writing failed (the map in memory)."""
    if ply is None:
        return ""
    if report.ply_vertices:
        return (f"; --ply {ply} written from the map in memory ({report.ply_vertices} "
                "vertices, the frames processed)")  # fmt: skip
    return f"; --ply {ply} not written ({report.ply_error or 'no map'})"


def _run(args: argparse.Namespace, workers: StartedWorkers | None) -> int:
    """The run and its summary, with the workers started in :func:`main`."""
    import numpy as np

    from endo_io.bag import BagError
    from endo_process.accuracy import Accuracy, score_recording
    from endo_process.damage import damage_line
    from endo_process.runner import process_bag
    from endo_process.settings import NODES, load_settings
    from endo_process.simulated import registration_mismatch
    from endo_process.summary import drop_lines, format_report, summary_document

    try:
        options = _options(args)
        for key in load_settings(options.params, solve_scale=options.solve_scale).ignored_sections:
            print(f"{PROGRAM}: warning: {options.params}: section {key} applies to none of the "
                  f"nodes ({', '.join(NODES)}, in the root namespace; /**/NODE applies in "
                  "any): ignored", file=sys.stderr)  # fmt: skip
        with _StopOnSignal() as stop:
            report = process_bag(options, stop, workers)
    except (Endo3dError, BagError) as error:
        return report_error(PROGRAM, error)
    accuracy = None
    if report.frames_shaded and not report.interrupted and not report.write_failure:
        # scored as it was written; read back only when the truth came late
        accuracy = report.accuracy or score_recording(options.output)
    print(format_report(report, accuracy))
    if accuracy is not None and accuracy.poses is not None:
        median_mm = (float(np.median(accuracy.poses.position_mm))
                     if accuracy.poses.compared else None)  # fmt: skip
        mismatch = registration_mismatch(
            options.bag, load_settings(options.params).T_world_tracker, median_mm
        )
        if mismatch is not None:
            print(f"{PROGRAM}: warning: {mismatch}", file=sys.stderr)
    if args.report is not None and report.write_failure:
        print(f"{PROGRAM}: error: --report {args.report} not drawn (the output is incomplete)",
              file=sys.stderr)  # fmt: skip
    elif args.report is not None and report.frames_shaded:
        # Only here: matplotlib is ~0.3 CPU-s of imports a run without --report skips.
        from endo_process.report import write_report_figure

        write_report_figure(options.output, accuracy or Accuracy(), options.calibration,
                            args.report)  # fmt: skip
    summary_failed = False  # the output itself may be whole: not a write_failure of it
    if args.summary_json is not None:
        document = summary_document(report, accuracy)
        try:
            args.summary_json.write_text(json.dumps(document, indent=1, allow_nan=False) + "\n")
        except OSError as error:  # the disk that refused the output, say
            print(f"{PROGRAM}: error: cannot write {args.summary_json} ({error.strerror})",
                  file=sys.stderr)  # fmt: skip
            summary_failed = True
    ply_failed = False  # the output and the summary are whole: it costs the PLY alone
    if args.ply is not None and report.ply_error and not report.write_failure:
        if report.ply_error.startswith("the "):  # empty, or no map: nothing to write
            print(f"{PROGRAM}: warning: --ply {args.ply} not written ({report.ply_error})",
                  file=sys.stderr)  # fmt: skip
        else:
            print(f"{PROGRAM}: error: --ply {args.ply} not written ({report.ply_error})",
                  file=sys.stderr)  # fmt: skip
            ply_failed = True
    for line in drop_lines(report):
        print(f"{PROGRAM}: warning: {line}", file=sys.stderr)
    damage = damage_line(report.input_damage, report.frames_in, report.recording_start_ns,
                         "interrupted" if report.interrupted else "--max-frames")  # fmt: skip
    if damage:
        print(f"{PROGRAM}: {damage}", file=sys.stderr)
    if report.undecodable:
        skipped = ", ".join(f"{n} on {topic}" for topic, n in report.undecodable.most_common())
        print(f"{PROGRAM}: error: skipped {skipped}, undecodable; the first: "
              f"{report.first_undecodable}", file=sys.stderr)  # fmt: skip
    if report.frames_shaded and not report.frames_with_pose and not report.interrupted:
        # every frame shaded, none placed: a run that makes no metric surface says why
        print(f"{PROGRAM}: warning: none of the {report.frames_shaded} frames with a relative "
              "depth had a camera pose, so no metric depth, points or map were made (the "
              "tracker's causes above)", file=sys.stderr)  # fmt: skip
    if report.frames_in > 0 and report.frames_shaded == 0 and not report.interrupted:
        print(f"{PROGRAM}: error: none of the {report.frames_in} frames read gave a relative "
              "depth (the causes above)", file=sys.stderr)  # fmt: skip
    if report.write_failure and report.output is not None:
        print(f"{PROGRAM}: error: writing stopped after {report.frames_in} of "
              f"{report.frames_total} frames: {report.write_failure}"
              + _ply_outcome(args.ply, report),
              file=sys.stderr)  # fmt: skip
    if report.interrupted:
        in_flight = (f"; {report.frames_in_flight} frames in flight at the interrupt were not "
                     "written" if report.frames_in_flight else "")  # fmt: skip
        print(f"{PROGRAM}: interrupted; {options.output} holds the "
              f"{report.frames_shaded} frames processed{in_flight}", file=sys.stderr)  # fmt: skip
    status = exit_status(report)
    return max(status, EXIT_DAMAGED) if summary_failed or ply_failed else status


if __name__ == "__main__":
    sys.exit(main())
