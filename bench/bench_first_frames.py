"""The live graph's first frames: when each one reached each stage, and which a stage skipped.

    .venv/bin/python bench/bench_first_frames.py                 # phantom at the demo's rate
    .venv/bin/python bench/bench_first_frames.py --rate 0.5 --frames 15 --runs 2

Runs the demo's graph (:func:`endo_bringup.graph.run_live_graph` with the
table of :func:`endo_bringup.graph.graph_processes`, the bag's true
calibrations as in ``bench_graph.py``) on the phantom bag, watched by
:class:`endo_bringup.graph_monitor.GraphMonitor`, and prints for each of the
first ``--frames`` image stamps, and of every later frame a stage did not
give: the image's publish at the replay (ms after the first image's), and
how long after that publish the corrected image, the relative depth and
flow's scale arrived at the listener (ms; ``skip``:
that stage never gave this frame). Also the nodes' start-up lines
(readiness, warm-up) from their logs, with their time before the first image.

This is the measurement behind the start-up fixes of the demo (frames skipped
at the start: first-call costs, discovery after the replay began, the cold
first solve); it prints, it does not write docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from dataclasses import replace
from datetime import datetime
from pathlib import Path

from soak import _setup as true_calibrations

from endo_bringup.dds_profile import with_large_frame_profile
from endo_bringup.demo import GRAPH_RATE, GRAPH_SOLVE_SCALE, graph_settings_for
from endo_bringup.graph import run_live_graph
from endo_bringup.graph_monitor import GraphMonitor, graph_figures, planned_graph, stage_lines
from endo_io import topics

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "bags" / "phantom_colon.mcap"
#: The per-frame topics printed, upstream first, with their column names.
COLUMNS = ((topics.IMAGE_CORRECTED, "corrected"), (topics.DEPTH_RELATIVE, "depth_rel"),
           (topics.SCALE, "scale"))  # fmt: skip
#: Log lines worth showing from the nodes' start-up.
_STARTUP = re.compile(r"ready|warm|kernels|DDS: domain|subscribed|playing|matched", re.I)
#: ROS log lines start with [LEVEL] [seconds.nanoseconds] [node]: ...
_LOG_TIME = re.compile(r"\[(\d+\.\d+)\]")


def run(rate: float, solve_scale: float, frames: int, work: Path, env: dict[str, str]) -> None:
    """One graph run; prints the first frames' table and the start-up lines."""
    out = Path(tempfile.mkdtemp(prefix="first_frames_", dir=work))
    photometric, handeye, _ = true_calibrations(out, solve_scale, PHANTOM)
    settings = graph_settings_for(PHANTOM, rate, solve_scale)
    processes = planned_graph(PHANTOM, photometric, handeye, out, settings)
    settings = replace(settings, listeners=GraphMonitor.played_listeners(processes))
    with GraphMonitor(processes, env) as monitor:
        graph = run_live_graph(PHANTOM, photometric, handeye, out, env, settings)
    arrivals, _ = monitor.snapshot()
    images = arrivals.get(topics.IMAGE_RAW, {})
    every = sorted(images)
    stamps = [s for i, s in enumerate(every) if i < frames or any(
        s not in arrivals.get(topic, {}) for topic, _ in COLUMNS)]
    if not stamps:
        print("  the listener saw no image")
        return
    first_publish = images[stamps[0]][0]
    print(f"  {'frame':>5} {'published':>9} " + " ".join(f"{n:>10}" for _, n in COLUMNS))
    for stamp in stamps:
        index = every.index(stamp)
        sent = images[stamp][0]
        cells = []
        for topic, _ in COLUMNS:
            got = arrivals.get(topic, {}).get(stamp)
            cells.append("skip" if got is None else f"{(got[1] - sent) / 1e6:.0f}")
        print(f"  {index:>5} {(sent - first_publish) / 1e6:>9.0f} "
              + " ".join(f"{c:>10}" for c in cells))
    figures = graph_figures(graph.processes, monitor, None, graph.played)
    print("\n".join("  " + line for line in stage_lines(figures)))
    print("  start-up lines (s before the first image was published):")
    for name in ("endo-photometric-correction", "endo-sfs", "endo-tracker-bridge", "endo-flow",
                 "endo-replay"):
        log = graph.log_dir / f"{name}.log"
        if not log.exists():
            continue
        for line in log.read_text(errors="replace").splitlines():
            found = _LOG_TIME.search(line)
            if found and _STARTUP.search(line):
                before = first_publish / 1e9 - float(found.group(1))
                print(f"    {name:<28} {before:>7.2f}  {line[found.end():].strip()[:110]}")


def main() -> int:
    """Run ``--runs`` times at ``--rate``; print each run's table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=GRAPH_RATE)
    parser.add_argument("--solve-scale", type=float, default=GRAPH_SOLVE_SCALE)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", "43")
    work = Path(tempfile.mkdtemp(prefix="endo3d_first_frames_"))
    env, note = with_large_frame_profile(env, work)
    print(f"bench_first_frames: {note}; runs in {work}", flush=True)
    for run_index in range(1, args.runs + 1):
        load = os.getloadavg()
        print(f"== run {run_index}: phantom at {args.rate:g}x, solve_scale {args.solve_scale:g}, "
              f"{datetime.now():%Y-%m-%d %H:%M}, load {load[0]:.2f} {load[1]:.2f}", flush=True)
        run(args.rate, args.solve_scale, args.frames, work, env)
    return 0


if __name__ == "__main__":
    sys.exit(main())
