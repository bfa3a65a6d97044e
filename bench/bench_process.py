"""Speed of endo-process on the phantom bag: frames/s, × real time, CPU, 1 and 2 jobs, 2 scales.

The phantom bag (bags/phantom_colon.mcap: 90 frames of 640×480 mono8 at
30 fps, 3.0 s) is processed end to end by :func:`endo_process.runner.process_bag`
(correction, SFS, tracker chain, flow, writing the output MCAP) with the
calibrations endo-demo fits, for every combination of ``--solve-scale``
{0.5, 1} and ``--jobs`` {1, 2} (2: two worker processes taking the frames
in turn), in two rounds (the order reversed in the second),
so that configurations are compared inside one run. Each run is its own
process (``python bench_process.py --one ...``) so that its CPU time is
its own: the main process's, and its workers' (reaped, so counted as
children). The wall figures are the frame loop's (setup and scoring not
counted; the wait for the workers' start-up is, and is also given apart:
"after the first frame" is the steady state, the frames after the first
one was written, ``ProcessReport.steady_real_time_factor``). "Whole run"
is what a user waits for: the run's process from its start to its exit
(Python, the imports, the set-up, the loop, the output closed), timed by
this script around it, as × real time of the recording.

A second table times what endo-process itself does to write a frame: three
640×480 32FC1 images (corrected, relative depth, metric depth) through
:class:`endo_process.output.OutputBag`, built as a message and serialised
(rclpy + the rosbags round trip) or encoded straight from the array
(``endo_io.image.array_to_image_cdr``), under each chunk compression, with
the bytes per frame on disk.

A configuration is ``solve_scale:jobs``, optionally ``:compression`` and
``:crc`` (the output's chunk compression, default none, and whether chunk
CRCs are stored, default not: endo-process's defaults) and ``:cN``
(``--cloud-decimation N``, default: the parameter file's, as live),
e.g. ``--configs 0.5:2,0.5:2:lz4,0.5:2:lz4:crc,0.5:2:none:c4``.

``--command`` times what a user times instead: the ``endo-process`` command
itself, start to exit (imports, set-up, the loop, scoring the output against
the ground truth when the recording carries it, the summary), on a long
recording (``--bag``, e.g. the 60 s colon render), with the recording's true
calibrations beside it (``.inverse_response.npy``, ``.light_map.npy``,
``.ground_truth.yaml``: :func:`soak._setup`, as bench_graph builds them), at
``--configs``' solve scales and jobs, alternating with ``--reference``'s tree
if given; the output is deleted after each run. It reports wall seconds, ×
real time over the whole command, the frame loop's (from ``--summary-json``),
CPU seconds user + system of the command and its workers (``os.wait4``), minor
page faults, and the accuracy figures (which must not change).

Run by hand: ``.venv/bin/python bench/bench_process.py [--rounds 2] [--bag B]``;
prints Markdown for docs/benchmarks.md ("endo-process").
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from machine import cpu_model

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"
CONFIGS = [(0.5, 1), (0.5, 2), (1.0, 1), (1.0, 2)]
#: The output compression endo-process uses by default (its --compression).
COMPRESSION = "none"


@dataclasses.dataclass(frozen=True)
class Config:
    """One configuration: solve scale, jobs, output compression, chunk CRCs, cloud decimation."""

    scale: float
    jobs: int
    compression: str = COMPRESSION
    crc: bool = False
    cloud_decimation: int | None = None  # endo-process's default: the parameter file's

    @classmethod
    def parse(cls, text: str) -> Config:
        parts = text.split(":")
        cloud = None
        if len(parts) > 2 and parts[-1][:1] == "c" and parts[-1][1:].isdigit():
            cloud = int(parts.pop()[1:])
        if len(parts) < 2 or len(parts) > 4 or (len(parts) == 4 and parts[3] != "crc"):
            raise SystemExit(f"--configs: {text!r} is not scale:jobs[:compression[:crc]][:cN]")
        return cls(float(parts[0]), int(parts[1]),
                   parts[2] if len(parts) > 2 else COMPRESSION, len(parts) == 4,
                   cloud)  # fmt: skip

    @property
    def label(self) -> str:
        """The table's first columns: solve_scale | jobs, and the output's if not the default."""
        output = "" if (self.compression, self.crc) == (COMPRESSION, False) else (
            f" ({self.compression}{', CRC' if self.crc else ''})")
        cloud = "" if self.cloud_decimation is None else f" (points every {self.cloud_decimation})"
        return f"{self.scale:g} | {self.jobs}{output}{cloud}"


def machine() -> str:
    return f"{cpu_model()}, {os.cpu_count()} cores"


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def reference_path(tree: Path) -> str:
    """PYTHONPATH that puts every package of an older checkout before this tree's."""
    packages = sorted(p for p in (Path(tree) / "src").iterdir() if (p / p.name).is_dir())
    if not packages:
        raise SystemExit(f"--reference: no packages under {tree}/src")
    return os.pathsep.join(str(p) for p in packages)


def one_run(args: argparse.Namespace) -> None:
    """One configuration in this process; prints its figures as one JSON line."""
    import endo_process

    if (Path(endo_process.__file__).parent / "runtime.py").exists():  # not in an older tree
        from endo_process.runtime import reuse_freed_memory

        reuse_freed_memory()  # as endo-process's main() does (one_blas_thread: main())
    workers = None
    # As endo-process does: the workers first, importing beside this process. An
    # older tree (--reference) has no worker_start (looked up by file: the editable
    # install's finder would import this tree's module into the older package).
    if args.jobs > 1 and (Path(endo_process.__file__).parent / "worker_start.py").exists():
        from endo_process.worker_start import start_workers

        workers = start_workers(args.jobs)
    from endo_process.runner import ProcessOptions, process_bag

    before = os.times()
    extra = {} if workers is None else {"workers": workers}
    fields = {f.name for f in dataclasses.fields(ProcessOptions)}
    crcs = {"chunk_crcs": args.crc} if "chunk_crcs" in fields else {}  # not in an older tree
    if "cloud_decimation" in fields:  # not in an older tree
        crcs["cloud_decimation"] = args.cloud_decimation
    report = process_bag(ProcessOptions(
        bag=args.bag, output=args.out, calibration=args.photometric, handeye=args.handeye,
        params=args.params, solve_scale=args.scale, jobs=args.jobs, progress=False,
        compression=args.compression, max_frames=args.max_frames, **crcs,
    ), **extra)  # fmt: skip
    after = os.times()
    main_cpu = (after[0] - before[0]) + (after[1] - before[1])
    workers_cpu = (after[2] - before[2]) + (after[3] - before[3])
    frames = report.frames_in
    print(json.dumps({
        "fps": report.frames_per_second, "real_time": report.real_time_factor,
        "steady_real_time": getattr(report, "steady_real_time_factor", 0.0),
        "first_frame_s": getattr(report, "first_frame_seconds", 0.0),
        "frames": frames, "main_ms": main_cpu / frames * 1e3,
        "workers_ms": workers_cpu / frames * 1e3,
        "setup_s": report.setup_seconds, "loop_s": report.seconds,
        "loop_cpu_ms": getattr(report, "loop_cpu_seconds", 0.0) / frames * 1e3,
        "worker_loop_cpu_ms": getattr(report, "worker_cpu_seconds", 0.0) / frames * 1e3,
        "solve_ms": report.median_solve_ms,
        "mb_per_frame": args.out.stat().st_size / frames / 1e6,
        "stages_ms": {k: v / frames * 1e3
                      for k, v in getattr(report, "stage_seconds", {}).items()},
        "stages_cpu_ms": {k: v / frames * 1e3
                          for k, v in getattr(report, "stage_cpu_seconds", {}).items()},
        "shading_ms": {k: v / frames * 1e3
                       for k, v in getattr(report, "shading_seconds", {}).items()},
    }))  # fmt: skip


def writing_table(bag: Path, rounds: int) -> list[str]:
    """CPU ms to write three 640×480 32FC1 images per frame, per encoding, compression and CRC."""
    from endo_io import topics
    from endo_io.bag.streams import read_depth_frames
    from endo_io.image import array_to_image
    from endo_process.output import OutputBag

    # Real content: the phantom's true depth maps (640×480 32FC1, NaN outside
    # the field of view), which compress like the outputs; 30 frames.
    truth = list(read_depth_frames(bag, topics.TRUE_DEPTH).values())
    frames = [truth[k % len(truth)] * np.float32(1 + k / 1000) for k in range(30)]
    # (compression, encoded straight from the array, chunk CRCs stored)
    cases = [(c, direct, crc) for c in ("lz4", "zstd", "none")
             for direct, crc in ((False, True), (True, True), (True, False))]  # fmt: skip
    rows: dict[tuple[str, bool, bool], list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory() as work:
        # One-off costs (the rosbags type store, the codecs) before any timing.
        warm = OutputBag(Path(work) / "warm.mcap", "zstd")
        warm.write("/w", array_to_image(frames[0], "32FC1", 1, "optical"), 1)
        warm.write_image("/v", frames[0], "32FC1", 1, "optical")
        warm.close()
        for round_index in range(rounds):
            for compression, direct, crc in cases:
                path = Path(work) / f"w_{round_index}_{compression}_{direct}_{crc}.mcap"
                output = OutputBag(path, compression, crcs=crc)
                start = time.process_time()
                for index, image in enumerate(frames):
                    stamp = 10**9 + index * 33_333_333
                    for topic in ("/a", "/b", "/c"):
                        if direct:
                            output.write_image(topic, image, "32FC1", stamp, "optical")
                        else:
                            message = array_to_image(image, "32FC1", stamp, "optical")
                            output.write(topic, message, stamp)
                output.close()
                cpu = (time.process_time() - start) / len(frames) * 1e3
                size = path.stat().st_size / len(frames) / 1e6
                rows.setdefault((compression, direct, crc), []).append((cpu, size))
    lines = [
        "| compression | encoding | chunk CRC | CPU ms per frame (each run) | MB per frame |",
        "|---|---|---|---|---|",
    ]
    for (compression, direct, crc), values in rows.items():
        how = "array_to_image_cdr" if direct else "message + serialize"
        cpu = ", ".join(f"{v[0]:.2f}" for v in values)
        lines.append(f"| {compression} | {how} | {'yes' if crc else 'no'} | {cpu} | "
                     f"{values[0][1]:.2f} |")  # fmt: skip
    return lines


def corrected_writing_table(bag: Path, rounds: int) -> list[str]:
    """CPU ms and bytes to write one frame's corrected image, 32FC1 against 16UC1 fixed point.

    Real content: 30 of the phantom's frames corrected with its true
    calibration (NaN outside the field of view and where saturated). 16UC1
    is :func:`endo_io.image.encode_irradiance` then the same direct write;
    both into uncompressed chunks without CRCs (endo-process's defaults).
    """
    from endo_calib.calibration import ChannelCalibration, PhotometricCalibration
    from endo_calib.raw_image import to_raw_frame
    from endo_calib.response import InverseResponse
    from endo_io import topics
    from endo_io.bag import BagReader, deserialize
    from endo_io.image import encode_irradiance, image_to_array
    from endo_process.output import OutputBag

    lut = np.load(bag.with_suffix(".inverse_response.npy"))
    light = np.load(bag.with_suffix(".light_map.npy"))
    fov = light > 0
    channel = ChannelCalibration("mono", InverseResponse(lut, 8), np.where(fov, light, 0.0), None)
    calibration = PhotometricCalibration([channel], fov, None, "pixels")
    frames = []
    with BagReader(bag) as reader:
        for message in reader.messages([topics.IMAGE_RAW]):
            msg = deserialize(message)
            frames.append(calibration.correct(to_raw_frame(image_to_array(msg), msg.encoding)))
            if len(frames) == 30:
                break
    rows: dict[str, list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory() as work:
        warm = OutputBag(Path(work) / "warm.mcap", COMPRESSION)
        warm.write_image("/v", encode_irradiance(frames[0]).pixels, "16UC1", 1, "optical")
        warm.write_image("/w", frames[0], "32FC1", 1, "optical")
        warm.close()
        for round_index in range(rounds):
            for encoding in ("32FC1", "16UC1"):
                path = Path(work) / f"c_{round_index}_{encoding}.mcap"
                output = OutputBag(path, COMPRESSION)
                start = time.process_time()
                for index, irradiance in enumerate(frames):
                    stamp = 10**9 + index * 33_333_333
                    pixels = encode_irradiance(irradiance, encoding).pixels
                    output.write_image("/c", pixels, encoding, stamp, "optical")
                output.close()
                cpu = (time.process_time() - start) / len(frames) * 1e3
                size = path.stat().st_size / len(frames) / 1e6
                rows.setdefault(encoding, []).append((cpu, size))
    lines = ["| corrected image | CPU ms per frame, encode + write (each run) | MB per frame |",
             "|---|---|---|"]
    for encoding, values in rows.items():
        cpu = ", ".join(f"{v[0]:.2f}" for v in values)
        lines.append(f"| {encoding} | {cpu} | {values[0][1]:.2f} |")
    return lines


def command_runs(args: argparse.Namespace) -> None:
    """--command: the endo-process command, start to exit, on a long recording; prints Markdown."""
    from soak import _setup

    work = Path(tempfile.mkdtemp(prefix="bench_process_command_", dir=args.work))
    configs = [Config.parse(c) for c in args.configs.split(",")]
    trees = ["this tree"] + (["reference"] if args.reference else [])
    runs = [(tree, config) for config in configs for tree in trees]
    results: dict[tuple[str, Config], list[dict[str, Any]]] = {r: [] for r in runs}
    loads = [load()]
    for round_index in range(args.rounds):
        for tree, config in runs if round_index % 2 == 0 else runs[::-1]:
            photometric, handeye, params = _setup(work, config.scale, args.bag)
            env = dict(os.environ)
            if tree == "reference":
                env["PYTHONPATH"] = reference_path(args.reference)
            out, summary = work / "out.mcap", work / "summary.json"
            argv = [sys.executable, "-c",
                    "import sys; from endo_process.cli import main; sys.exit(main())",
                    str(args.bag), "-o", str(out), "--calibration", str(photometric),
                    "--handeye", str(handeye), "--params", str(params),
                    "--solve-scale", f"{config.scale:g}", "--jobs", str(config.jobs), "-q",
                    "--summary-json", str(summary)]  # fmt: skip
            start = time.perf_counter()
            process = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL)
            _, status, usage = os.wait4(process.pid, 0)
            wall = time.perf_counter() - start
            process.returncode = os.waitstatus_to_exitcode(status)
            if process.returncode != 0:
                raise SystemExit(f"endo-process exited with {process.returncode}")
            document = json.loads(summary.read_text())
            out.unlink()
            speed, accuracy = document["speed"], document["accuracy"] or {}
            row = {
                "wall_s": wall, "recording_s": speed["recording_seconds"],
                "loop_s": speed["seconds"], "setup_s": speed["setup_seconds"],
                "user_s": usage.ru_utime, "sys_s": usage.ru_stime, "minflt": usage.ru_minflt,
                "solve_ms": speed["median_solve_ms"],
                "accuracy": {k: accuracy.get(k) for k in (
                    "relative_abs_rel_mean", "metric_mae_m_mean", "metric_abs_rel_mean",
                    "cloud_rms_m_mean", "oracle_scale")},
            }  # fmt: skip
            results[(tree, config)].append(row)
            print(f"round {round_index + 1} {tree} {config.label}: whole {wall:.1f} s "
                  f"({row['recording_s'] / wall:.2f}x), loop {row['loop_s']:.1f} s, CPU "
                  f"{row['user_s']:.1f} + {row['sys_s']:.1f} s, {row['minflt']} minor faults, "
                  f"load {load()}", flush=True)  # fmt: skip
        loads.append(load())
    frames = args.bag.name
    print()
    print(f"Machine: {machine()}; {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC; "
          f"bag {frames}; the endo-process command start to exit; load average before/after "
          f"each round: {' | '.join(loads)}")  # fmt: skip
    print()
    label = "tree | " if args.reference else ""
    print(f"| {label}solve_scale | jobs | whole command s (× real time) | frame loop s "
          "(× real time) | after the loop s | CPU s user + system | minor page faults | "
          "median solve ms |")
    print("|---" * (7 + bool(label)) + "|")
    for tree, config in runs:
        rows = results[(tree, config)]
        whole = ", ".join(f"{r['wall_s']:.1f} ({r['recording_s'] / r['wall_s']:.2f})"
                          for r in rows)  # fmt: skip
        loop = ", ".join(f"{r['loop_s']:.1f} ({r['recording_s'] / r['loop_s']:.2f})"
                         for r in rows)  # fmt: skip
        after = ", ".join(f"{r['wall_s'] - r['loop_s'] - r['setup_s']:.1f}" for r in rows)
        cpu = ", ".join(f"{r['user_s']:.1f} + {r['sys_s']:.1f}" for r in rows)
        faults = ", ".join(f"{r['minflt'] / 1e6:.2f} M" for r in rows)
        solve = ", ".join(f"{r['solve_ms']:.1f}" for r in rows)
        first = f"{tree} | " if label else ""
        print(f"| {first}{config.label} | {whole} | {loop} | {after} | {cpu} | {faults} | "
              f"{solve} |")
    print()
    print("Accuracy of each run (relative AbsRel, metric MAE mm / AbsRel, cloud RMS mm, "
          "oracle scale):")
    for tree, config in runs:
        for r in results[(tree, config)]:
            a = r["accuracy"]
            if a["relative_abs_rel_mean"] is None:
                print(f"- {tree} {config.label}: no ground truth")
                continue
            print(f"- {tree} {config.label}: {a['relative_abs_rel_mean']:.4f}, "
                  f"{a['metric_mae_m_mean'] * 1e3:.2f} / {a['metric_abs_rel_mean']:.4f}, "
                  f"{a['cloud_rms_m_mean'] * 1e3:.2f}, {a['oracle_scale']:.6g}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, default=BAGS / "phantom_colon.mcap")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--configs", default=",".join(f"{s:g}:{j}" for s, j in CONFIGS),
                        help="solve_scale:jobs pairs, comma-separated")
    parser.add_argument("--no-writing", action="store_true", help="skip the writing table")
    parser.add_argument("--reference", type=Path, metavar="TREE",
                        help="also run every configuration on the packages of this older "
                        "checkout (alternating with this tree's)")
    parser.add_argument("--writing-only", action="store_true", help="only the writing table")
    parser.add_argument("--corrected-only", action="store_true",
                        help="only the corrected image's writing table (32FC1 vs 16UC1)")
    parser.add_argument("--command", action="store_true",
                        help="time the endo-process command start to exit on --bag (a long "
                        "render with its true calibrations beside it), scoring included")
    parser.add_argument("--work", type=Path, default=None,
                        help="--command: directory for the outputs (deleted after each run)")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    for name in ("out", "photometric", "handeye", "params"):
        parser.add_argument(f"--{name}", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--scale", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--jobs", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--max-frames", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--compression", default=COMPRESSION, help=argparse.SUPPRESS)
    parser.add_argument("--crc", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--cloud-decimation", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        one_run(args)
        return
    if args.command:
        command_runs(args)
        return
    if args.corrected_only:
        print(f"Writing one frame's 640×480 corrected image (load {load()}):\n")
        print("\n".join(corrected_writing_table(args.bag, args.rounds)))
        return
    if args.writing_only:
        print(f"Writing one frame's three 640×480 32FC1 images (load {load()}):\n")
        print("\n".join(writing_table(args.bag, args.rounds)))
        print(f"\nload at the end: {load()}")
        return
    from endo_bringup.graph import run_offline_calibrations
    from endo_process.simulated import write_simulated_parameters

    work = Path(tempfile.mkdtemp(prefix="bench_process_"))
    photometric, handeye = run_offline_calibrations(
        BAGS / "graycard.mcap", BAGS / "handeye.mcap", work, dict(os.environ)
    )
    params = write_simulated_parameters(args.bag, work / "endo3d.yaml")
    pairs = [Config.parse(c) for c in args.configs.split(",")]
    trees = ["this tree"] + (["reference"] if args.reference else [])
    configs = [(tree, config) for config in pairs for tree in trees]
    results: dict[tuple[str, Config], list[dict[str, Any]]] = {c: [] for c in configs}
    # One short unmeasured run per tree first: a tree's first run may compile its kernels.
    for tree in trees:
        env = dict(os.environ)
        if tree == "reference":
            env["PYTHONPATH"] = reference_path(args.reference)
        out = work / "warm_up.mcap"
        subprocess.run([
            sys.executable, __file__, "--one", "--bag", str(args.bag), "--out", str(out),
            "--photometric", str(photometric.result), "--handeye", str(handeye.result),
            "--params", str(params), "--scale", str(pairs[0].scale), "--jobs", "2",
            "--max-frames", "4",
        ], capture_output=True, text=True, check=True, env=env)  # fmt: skip
        out.unlink()
    loads = [load()]
    for round_index in range(args.rounds):
        order = configs if round_index % 2 == 0 else configs[::-1]
        for tree, config in order:
            scale, jobs = config.scale, config.jobs
            out = work / f"out_{scale}_{jobs}_{round_index}.mcap"
            env = dict(os.environ)
            if tree == "reference":
                env["PYTHONPATH"] = reference_path(args.reference)
            run_start = time.perf_counter()
            done = subprocess.run([
                sys.executable, __file__, "--one", "--bag", str(args.bag), "--out", str(out),
                "--photometric", str(photometric.result), "--handeye", str(handeye.result),
                "--params", str(params), "--scale", str(scale), "--jobs", str(jobs),
                "--compression", config.compression, *(["--crc"] if config.crc else []),
                *([] if config.cloud_decimation is None
                  else ["--cloud-decimation", str(config.cloud_decimation)]),
            ], capture_output=True, text=True, check=True, env=env)  # fmt: skip
            run_s = time.perf_counter() - run_start
            figures = json.loads(done.stdout.strip().splitlines()[-1])
            figures["run_s"] = run_s
            # the recording's seconds (the loop's real-time factor × its wall time)
            figures["whole_real_time"] = figures["real_time"] * figures["loop_s"] / run_s
            figures.setdefault("loop_s", figures["frames"] / figures["fps"])  # an older tree
            figures.setdefault("stages_ms", {})
            figures.setdefault("steady_real_time", 0.0)
            figures.setdefault("first_frame_s", 0.0)
            figures.setdefault("shading_ms", {})
            figures.setdefault("stages_cpu_ms", {})
            results[(tree, config)].append(figures)
            print(f"round {round_index + 1} {tree} solve_scale {scale:g} jobs {jobs} "
                  f"{config.compression}{' crc' if config.crc else ''} "
                  f"points every {config.cloud_decimation or 'as live'}: "
                  f"{figures['fps']:.1f} frames/s, {figures['real_time']:.2f}x real time "
                  f"({figures['steady_real_time']:.2f}x after the first frame, which took "
                  f"{figures['first_frame_s']:.2f} s; whole run {figures['run_s']:.2f} s, "
                  f"{figures['whole_real_time']:.2f}x), CPU "
                  f"main {figures['main_ms']:.0f} + workers {figures['workers_ms']:.0f} ms per "
                  f"frame, median solve {figures['solve_ms']:.1f} ms, output "
                  f"{figures['mb_per_frame']:.2f} MB per frame, flow step "
                  f"{figures['stages_cpu_ms'].get('flow', 0.0):.1f} + its writing "
                  f"{figures['stages_cpu_ms'].get('flow_write', 0.0):.1f} CPU-ms per frame, "
                  f"load {load()}",
                  flush=True)  # fmt: skip
            out.unlink()
        loads.append(load())
    print()
    frames = int(results[configs[0]][0]["frames"])
    label = "tree | " if args.reference else ""
    print(f"Machine: {machine()}; {datetime.date.today().isoformat()}; bag {args.bag.name} "
          f"({frames} frames); output {COMPRESSION} without chunk CRCs unless said; "
          f"load average before/after each round: {' | '.join(loads)}")  # fmt: skip
    print()
    print(f"| {label}solve_scale | jobs | frames/s (run 1, run 2) | × real time (run 1, run 2) | "
          "× real time with the set-up (run 1, run 2) | "
          "× real time after the first frame (run 1, run 2) | first frame s | "
          "whole run s (× real time) | "
          "CPU ms per frame: main + workers = total (run 1; run 2) | median solve ms |")
    print("|---" * (10 + bool(label)) + "|")
    for tree, config in configs:
        rows = results[(tree, config)]
        fps = ", ".join(f"{r['fps']:.1f}" for r in rows)
        rt = ", ".join(f"{r['real_time']:.2f}" for r in rows)
        with_setup = ", ".join(
            f"{r['real_time'] * r['loop_s'] / (r['loop_s'] + r['setup_s']):.2f}" for r in rows
        )
        cpu = "; ".join(
            f"{r['main_ms']:.0f} + {r['workers_ms']:.0f} = {r['main_ms'] + r['workers_ms']:.0f}"
            for r in rows
        )
        solve = ", ".join(f"{r['solve_ms']:.0f}" for r in rows)
        steady = ", ".join(f"{r['steady_real_time']:.2f}" for r in rows)
        first_s = ", ".join(f"{r['first_frame_s']:.2f}" for r in rows)
        whole = ", ".join(f"{r['run_s']:.2f} ({r['whole_real_time']:.2f})" for r in rows)
        first = f"{tree} | " if label else ""
        print(f"| {first}{config.label} | {fps} | {rt} | {with_setup} | {steady} | "
              f"{first_s} | {whole} | {cpu} | {solve} |")
    print()
    print("Where the frame loop's wall time goes, ms per frame (run 1 / run 2): the main "
          "process's steps (endo_process.runner.LOOP_STAGES; 'shading' is the wait for the "
          "correction + SFS, or for the worker) and, beside them, the correction and SFS "
          "steps themselves wherever they ran (ShadedFrame.timings):")
    print()
    stage_names = list(dict.fromkeys(
        name for rows in results.values() for r in rows for name in r["stages_ms"]
    ))  # fmt: skip
    shading_names = ["correct", "solve", *sorted(
        {name for rows in results.values() for r in rows for name in r["shading_ms"]}
        - {"correct", "solve"}
    )]  # fmt: skip
    print(f"| {label}solve_scale | jobs | loop ms per frame | loop CPU ms per frame: main, "
          "worker | setup s | " + " | ".join(stage_names + shading_names) + " |")
    print("|---" * (5 + bool(label) + len(stage_names) + len(shading_names)) + "|")
    for tree, config in configs:
        rows = results[(tree, config)]
        loop = " / ".join(f"{r['loop_s'] / r['frames'] * 1e3:.1f}" for r in rows)
        loop_cpu = " / ".join(
            f"{r.get('loop_cpu_ms', 0.0):.1f}, {r.get('worker_loop_cpu_ms', 0.0):.1f}"
            if r.get("loop_cpu_ms") else "–" for r in rows
        )
        setup = " / ".join(f"{r['setup_s']:.2f}" for r in rows)
        cells = [" / ".join(f"{r['stages_ms'].get(n, 0.0):.1f}" for r in rows)
                 for n in stage_names]
        cells += [" / ".join(f"{r['shading_ms'].get(n, 0.0):.1f}" for r in rows)
                  for n in shading_names]
        first = f"{tree} | " if label else ""
        print(f"| {first}{config.label} | {loop} | {loop_cpu} | {setup} | "
              + " | ".join(cells) + " |")
    print()
    print("The main process's CPU per frame in the frame loop, ms (run 1 / run 2): each step's "
          "CPU in the loop's thread (ProcessReport.stage_cpu_seconds), 'other threads' the rest "
          "of the process's loop CPU (OpenCV's threads in the flow step, the queues' feeders "
          "pickling the frames for the workers), and the workers' loop CPU per frame beside it:")
    print()
    print(f"| {label}solve_scale | jobs | main, all threads | " + " | ".join(stage_names)
          + " | other threads | workers |")
    print("|---" * (5 + bool(label) + len(stage_names)) + "|")
    for tree, config in configs:
        rows = results[(tree, config)]
        main_cpu = " / ".join(f"{r.get('loop_cpu_ms', 0.0):.1f}" for r in rows)
        cells = [" / ".join(f"{r.get('stages_cpu_ms', {}).get(n, 0.0):.1f}" for r in rows)
                 for n in stage_names]
        other = " / ".join(
            f"{r.get('loop_cpu_ms', 0.0) - sum(r.get('stages_cpu_ms', {}).values()):.1f}"
            for r in rows
        )
        workers = " / ".join(f"{r.get('worker_loop_cpu_ms', 0.0):.1f}" for r in rows)
        first = f"{tree} | " if label else ""
        print(f"| {first}{config.label} | {main_cpu} | " + " | ".join(cells)
              + f" | {other} | {workers} |")
    if args.no_writing:
        return
    print()
    print(f"Writing one frame's three 640×480 32FC1 images (load {load()}):")
    print()
    print("\n".join(writing_table(args.bag, args.rounds)))
    print(f"\nload at the end: {load()}")


if __name__ == "__main__":
    main()
