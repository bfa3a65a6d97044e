"""Speed of endo-process on the phantom bag: frames/s, × real time, 1 and 2 jobs, 2 scales.

The phantom bag (bags/phantom_colon.mcap: 90 frames of 640×480 mono8 at
30 fps, 3.0 s) is processed end to end by :func:`endo_process.runner.process_bag`
(correction, SFS, tracker chain, flow, writing the output MCAP) with the
calibrations endo-demo fits, for every combination of ``--solve-scale``
{0.5, 1} and ``--jobs`` {1, 2}, in two rounds (the order alternates), so
that configurations are compared inside one run. The figures are the frame
loop's wall time (setup and the final scoring are not counted; the worker
processes' start-up is).

Run by hand: ``.venv/bin/python bench/bench_process.py [--rounds 2] [--bag B]``;
prints a Markdown table for docs/benchmarks.md ("endo-process").
"""

from __future__ import annotations

import argparse
import datetime
import os
import tempfile
from pathlib import Path

from machine import cpu_model

from endo_bringup.graph import run_offline_calibrations
from endo_process.runner import ProcessOptions, process_bag
from endo_process.simulated import write_simulated_parameters

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"


def machine() -> str:
    return f"{cpu_model()}, {os.cpu_count()} cores"


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, default=BAGS / "phantom_colon.mcap")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--compression", default="lz4")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_process_"))
    photometric, handeye = run_offline_calibrations(
        BAGS / "graycard.mcap", BAGS / "handeye.mcap", work, dict(os.environ)
    )
    params = write_simulated_parameters(args.bag, work / "endo3d.yaml")
    configs = [(scale, jobs) for scale in (0.5, 1.0) for jobs in (1, 2)]
    results: dict[tuple[float, int], list[tuple[float, float, float]]] = {c: [] for c in configs}
    loads = [load()]
    for round_index in range(args.rounds):
        order = configs if round_index % 2 == 0 else configs[::-1]
        for scale, jobs in order:
            out = work / f"out_{scale}_{jobs}_{round_index}.mcap"
            cpu_before = os.times()
            report = process_bag(ProcessOptions(
                bag=args.bag, output=out, calibration=photometric.result,
                handeye=handeye.result, params=params, solve_scale=scale, jobs=jobs,
                compression=args.compression, progress=False,
            ))  # fmt: skip
            cpu_after = os.times()
            cpu = sum(cpu_after[i] - cpu_before[i] for i in range(4))
            results[(scale, jobs)].append(
                (report.frames_per_second, report.real_time_factor, cpu / report.frames_in * 1e3)
            )
            print(f"round {round_index + 1} solve_scale {scale:g} jobs {jobs}: "
                  f"{report.frames_per_second:.1f} frames/s, {report.real_time_factor:.2f}x real "
                  f"time, median solve {report.median_solve_ms:.1f} ms, load {load()}",
                  flush=True)  # fmt: skip
            out.unlink()
        loads.append(load())
    print()
    print(f"Machine: {machine()}; {datetime.date.today().isoformat()}; bag {args.bag.name} "
          f"(90 frames 640×480 mono8, 3.0 s at 30 fps); output compression {args.compression}; "
          f"load average before/after each round: {' | '.join(loads)}")  # fmt: skip
    print()
    print("| solve_scale | jobs | frames/s (run 1, run 2) | × real time (run 1, run 2) | "
          "CPU ms per frame (all processes) |")
    print("|---|---|---|---|---|")
    for scale, jobs in configs:
        rows = results[(scale, jobs)]
        fps = ", ".join(f"{r[0]:.1f}" for r in rows)
        rt = ", ".join(f"{r[1]:.2f}" for r in rows)
        cpu = ", ".join(f"{r[2]:.0f}" for r in rows)
        print(f"| {scale:g} | {jobs} | {fps} | {rt} | {cpu} |")


if __name__ == "__main__":
    main()
