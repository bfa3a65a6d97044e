"""The whole live graph at video rate: frames per stage, latency, CPU and memory.

    .venv/bin/python bench/bench_graph.py                  # writes docs/benchmarks.md
    .venv/bin/python bench/bench_graph.py --quick --no-write

Every configuration runs the table of :func:`endo_bringup.graph.graph_processes`
through :func:`endo_bringup.graph.run_live_graph`, exactly as ``endo-demo``
does (replay → correction → sfs → tracker bridge → flow → recorder, each its
own OS process over loopback DDS with the large-frame profile), and watches it
with :mod:`endo_bringup.graph_monitor` (the figures ``endo-demo`` prints come
from the same module). The calibrations are the bag's true ones (photometric,
hand–eye and clock offset from the simulator, :func:`soak._setup`), so no
fitting step runs first.

Bags: the committed phantom (3 s, 90 frames) and a longer render
(``endo-sim render colon --seed 2``, 60 s by default, rendered once into
``out/bench/`` when missing), both 640×480 at 30 fps, played at ``--rate``
(1.0: 30 fps).

Configurations, at ``solve_scale`` 1 and 0.5: every optimisation on; then
each one off alone: ``newest_frame`` (correction, sfs and flow process every
frame in arrival order instead of the newest), ``warm_start`` (sfs); and
``corrected 32FC1``: the corrected image as float instead of its default
16UC1 fixed point (correction's ``output_encoding``). Each
configuration runs ``--runs`` times (2); the runs are passes over all
configurations, so the ratios inside one pass compare configurations under
the same load.

``--baseline SRC_ROOT`` (a checkout's root, e.g. ``git archive main src | tar
-x -C /tmp/base``) runs each configuration a second time in every pass with
that checkout's ``src/*`` packages first on PYTHONPATH (every process of the
graph, the bench's own imports stay this tree's), named ``<configuration>
[baseline]``: a change compares with what it replaces as a ratio inside one
pass, under the same load.

``--listener`` chooses how the bench watches the graph
(:data:`endo_bringup.graph_monitor.LISTEN_MODES`): ``recording`` (default,
what ``endo-demo`` does) times the nodes' outputs from the recorder's
recording and subscribes only to the camera_info and /diagnostics;
``topics`` subscribes to every node output, as before, and also times the
same run from the recording (the two definitions side by side); ``both``
runs each configuration once per mode in every pass (``[topics listener]``
after the name of the second).

``--sweep`` also finds ``endo-demo``'s default playback rate: the phantom at
the demo's solve_scale and each rate of ``--sweep-rates``; the fastest rate
at which every stage kept every frame in every run. It goes into its own
section of docs/benchmarks.md (``--sweep-only`` replaces that one alone).
"""

from __future__ import annotations

import argparse
import os
import pickle
import signal
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

from machine import cpu_model
from results import replace_section
from soak import _setup as true_calibrations

from endo_bringup.dds_profile import with_large_frame_profile
from endo_bringup.demo import GRAPH_SOLVE_SCALE, graph_settings_for
from endo_bringup.graph import GraphProcess, recorder_lost, run_live_graph
from endo_bringup.graph_monitor import (
    LISTEN_MODES,
    GraphFigures,
    GraphMonitor,
    ProcessSampler,
    graph_figures,
    planned_graph,
    recorded_arrivals,
    sent_topic,
    stage_lines,
)

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "bags" / "phantom_colon.mcap"
LONG_BAG = ROOT / "out" / "bench" / "colon_seed2_60s.mcap"
TITLE = "## The live graph at video rate (bench_graph)"
SWEEP_TITLE = "## endo-demo's playback rate (bench_graph --sweep)"
CORRECTION, SFS, FLOW = "endo-photometric-correction", "endo-sfs", "endo-flow"
#: The targets of issue 15 at solve_scale 0.5 (p50, p99 end to end, ms) and at 1 (depth Hz).
TARGET_P50_MS, TARGET_P99_MS, TARGET_FULL_HZ = 60.0, 150.0, 15.0


@dataclass(frozen=True)
class Configuration:
    """A named set of extra node parameters at one solve_scale."""

    name: str
    solve_scale: float
    node_parameters: dict[str, dict[str, str]] = field(default_factory=dict)
    #: endo-sfs processes sharing the frames (GraphSettings.sfs_workers).
    sfs_workers: int = 1
    #: the recorder's niceness (GraphSettings.recorder_nice; None: the default).
    recorder_nice: int | None = None
    #: the recorder's chunk compression (GraphSettings.recorder_compression; None: lz4).
    recorder_compression: str | None = None
    #: (process niceness, writing thread's niceness) of the recorder (None: the defaults)
    recorder_priorities: tuple[int, int] | None = None


def configurations(scales: list[float]) -> list[Configuration]:
    """All optimisations on, each off alone, then SFS's threads and workers, at every scale.

    "all on" runs one endo-sfs with its default threads (2), the corrected
    image in 16UC1 fixed point (the default); "corrected 32FC1" publishes it
    as float, as before 2026-12-02; "recorder nice 0" runs the recorder at
    the nodes' priority, as before the recorder was niced; "recorder
    uncompressed" records without lz4 (ros2 bag record's default); "recorder
    writer niced" runs the recorder at nice 0 with only its writing thread at
    nice 10 (endo-record's --writer-nice); "map off" runs flow
    without its voxel map, "map unpublished" fuses it but does not publish it
    in the run (map_period_s 3600), "map no budget" publishes it every
    map_period_s whatever its size (map_bandwidth_mb_s 0, as before
    2026-12-03), "map budget 6" at 6 MB/s instead of the default, "map stream
    whole" publishes the whole map while frames come (map_stream_max_points 0,
    as before 2026-12-03's thinned live map); "sfs threads 1"
    one endo-sfs on one thread; "sfs 2 workers x 1 thread" two endo-sfs
    processes (worker_count 2) of one thread each; "frame backlog 0" skips
    every frame that has a newer one waiting (frame_backlog_s 0), as before
    session 15.
    """
    off = {
        "newest_frame off": {n: {"newest_frame": "false"} for n in (CORRECTION, SFS, FLOW)},
        "warm_start off": {SFS: {"warm_start": "false"}},
        # every frame with a newer one behind it skipped, as before 2026-12-03 (session 15)
        "frame backlog 0": {n: {"frame_backlog_s": "0.0"} for n in (CORRECTION, SFS, FLOW)},
    }
    found = []
    for scale in scales:
        found.append(Configuration("all on", scale))
        found += [Configuration(name, scale, params) for name, params in off.items()]
        found.append(Configuration("corrected 32FC1", scale,
                                   {CORRECTION: {"output_encoding": "32FC1"}}))
        found += [Configuration("sfs threads 1", scale, {SFS: {"threads": "1"}}),
                  Configuration("sfs threads 2", scale, {SFS: {"threads": "2"}}),
                  Configuration("sfs 2 workers x 1 thread", scale, {SFS: {"threads": "1"}},
                                sfs_workers=2),
                  Configuration("recorder nice 0", scale, recorder_nice=0),
                  Configuration("recorder uncompressed", scale, recorder_compression="none"),
                  Configuration("recorder writer niced", scale, recorder_priorities=(0, 10)),
                  Configuration("map off", scale, {FLOW: {"map_enabled": "false"}}),
                  Configuration("map unpublished", scale, {FLOW: {"map_period_s": "3600.0"}}),
                  Configuration("map no budget", scale, {FLOW: {"map_bandwidth_mb_s": "0.0"}}),
                  Configuration("map budget 6", scale, {FLOW: {"map_bandwidth_mb_s": "6.0"}}),
                  Configuration("map stream whole", scale,
                                {FLOW: {"map_stream_max_points": "0"}})]
    return found


@dataclass
class Result:
    """One run of one configuration on one bag."""

    bag: str
    configuration: Configuration
    rate: float
    run: int
    figures: GraphFigures
    load_before: float
    #: CPU ms the bench process (its listener and /proc sampler) spent per frame
    #: played, from the start of the play to its end (the drain included, as the
    #: processes' CPU): not the graph's, but taken from the same 2 cores.
    listener_ms_per_frame: float = float("nan")
    #: How the listener timed the run (graph_monitor.LISTEN_MODES).
    listen: str = "topics"
    #: CPU ms per frame played of reading the recording after the run ("recording").
    read_ms_per_frame: float = float("nan")
    #: A "topics" run timed from its recording too (the two definitions, one run).
    recording_figures: GraphFigures | None = None
    #: A "topics" run: per topic, (median, p99, n) of recorder reception minus the
    #: listener's, ms; for the played camera_info its source time minus the image's.
    offsets: dict[str, tuple[float, float, int]] = field(default_factory=dict)


def ensure_long_bag(path: Path, seconds: float) -> Path:
    """Render the long bag (colon, seed 2) once; the phantom's photometry applies to it."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        command = [str(Path(sys.executable).parent / "endo-sim"), "render", "colon",
                   "-o", str(path), "--seed", "2", "--duration", f"{seconds:g}",
                   "--depth-every", "30", "--overwrite"]  # fmt: skip
        print("$ " + " ".join(command), flush=True)
        subprocess.run(command, check=True)
    return path


BASELINE_SUFFIX = " [baseline]"
TOPICS_SUFFIX = " [topics listener]"


def baseline_env(env: dict[str, str], root: Path) -> dict[str, str]:
    """``env`` with the ``src/*`` packages of the checkout at ``root`` first on PYTHONPATH."""
    packages = sorted(str(p) for p in (root / "src").iterdir() if p.is_dir())
    return dict(env, PYTHONPATH=os.pathsep.join(packages))


def _cpu_ms() -> float:
    times = os.times()
    return 1e3 * (times.user + times.system)


def _offsets(monitor: GraphMonitor, processes: list[GraphProcess], recording: Path
             ) -> dict[str, tuple[float, float, int]]:
    """A "topics" run: per topic, recorder reception minus the listener's (median, p99, n; ms).

    Also the replay's publish of each frame's camera_info minus its image's.
    """
    here, _ = monitor.snapshot()
    recorded = recorded_arrivals(recording, list(here))
    found = {}

    def summary(deltas: list[float]) -> tuple[float, float, int]:
        ordered = sorted(deltas)
        return statistics.median(ordered), ordered[int(0.99 * (len(ordered) - 1))], len(ordered)

    for topic, arrived in here.items():
        deltas = [(recorded[topic][s][1] - r) / 1e6 for s, (_, r) in arrived.items()
                  if s in recorded.get(topic, {})]
        if deltas:
            found[f"{topic}: received at the recorder − here"] = summary(deltas)
    images = here.get(sent_topic(processes, "topics"), {})
    infos = here.get(sent_topic(processes, "recording"), {})
    deltas = [(infos[s][0] - sent) / 1e6 for s, (sent, _) in images.items() if s in infos]
    if deltas and infos is not images:
        found["camera_info published − image published (replay)"] = summary(deltas)
    return found


def run_once(bag: Path, configuration: Configuration, rate: float, work: Path,
             env: dict[str, str], listen: str = "recording", *,
             keep_recording: bool = False) -> Result:
    """The graph on ``bag`` in ``configuration`` at ``rate``, watched as ``listen`` says.

    The result's run number and load are the caller's to set. The run's
    recording (~2 GB per 60 s at 0.5, 4 GB at full resolution) is deleted
    once its figures are read, unless ``keep_recording`` or a process failed;
    the logs stay.
    """
    out = Path(tempfile.mkdtemp(prefix=f"{bag.stem}_", dir=work))
    photometric, handeye, _ = true_calibrations(out, configuration.solve_scale, bag)
    settings = replace(graph_settings_for(bag, rate, configuration.solve_scale),
                       node_parameters=configuration.node_parameters,
                       sfs_workers=configuration.sfs_workers)
    if configuration.recorder_nice is not None:
        settings = replace(settings, recorder_nice=configuration.recorder_nice)
    if configuration.recorder_compression is not None:
        settings = replace(settings, recorder_compression=configuration.recorder_compression)
    if configuration.recorder_priorities is not None:
        process_nice, writer_nice = configuration.recorder_priorities
        settings = replace(settings, recorder_nice=process_nice,
                           recorder_writer_nice=writer_nice)
    processes = planned_graph(bag, photometric, handeye, out, settings)
    settings = replace(settings, listeners=GraphMonitor.played_listeners(processes, listen))
    before = _cpu_ms()
    with GraphMonitor(processes, env, listen) as monitor, \
            ProcessSampler(processes) as sampler:
        run = run_live_graph(bag, photometric, handeye, out, env, settings)
    during = _cpu_ms()
    figures = graph_figures(run.processes, monitor, sampler, run.played, run.recording)
    read_ms = _cpu_ms() - during
    frames = max(figures.frames_played, 1)
    print(f"   bench process over the whole run (start-up included): "
          f"{(during - before) / frames:.1f} CPU-ms per frame played", flush=True)
    result = Result(bag.stem, configuration, rate, 0, figures, float("nan"),
                    1e3 * figures.listener_cpu_s / frames, listen,
                    read_ms / frames if listen == "recording" else float("nan"))
    if listen == "topics":
        result.recording_figures = graph_figures(run.processes, monitor, sampler, run.played,
                                                 run.recording, timing="recording")
        result.offsets = _offsets(monitor, list(run.processes), run.recording)
    lost = recorder_lost(run.log_dir)
    if lost:  # the counts above are the recording's: these frames are the recorder's loss
        print(f"   endo-record {lost}", flush=True)
    bad = {name: code for name, code in run.return_codes.items() if code != 0}
    if bad:
        print(f"  exit codes {bad}; logs in {run.log_dir}", flush=True)
    if not keep_recording and not bad:  # a failed run's recording is kept, with its logs
        run.recording.unlink(missing_ok=True)
    return result


def _print_result(result: Result) -> None:
    print("\n".join("   " + line for line in stage_lines(result.figures)), flush=True)
    print(f"   bench listener ({result.listen}): {result.listener_ms_per_frame:.1f} CPU-ms per "
          f"frame played over the play; reading the recording after it "
          f"{result.read_ms_per_frame:.1f}", flush=True)
    if result.recording_figures is not None:
        print("   the same run timed from the recording:", flush=True)
        print("\n".join("   " + line for line in stage_lines(result.recording_figures)),
              flush=True)
    for topic, (median, p99, n) in result.offsets.items():
        print(f"   {topic}: median {median:.2f} ms, p99 {p99:.2f} ms over {n}", flush=True)


def _stage(figures: GraphFigures, name: str) -> str:
    s = figures.stage(name)
    return f"{s.frames_out}/{s.frames_in} (rcvd {s.received}, {s.skipped} skipped)"


def _ms(pair: tuple[float, float]) -> str:
    return f"{pair[0]:.0f} / {pair[1]:.0f}"


def report(results: list[Result], args: argparse.Namespace) -> str:
    """The docs/benchmarks.md section of the configurations."""
    loads = [r.load_before for r in results] + [r.figures.load for r in results]
    lines = [
        TITLE,
        "",
        f"`bench/bench_graph.py{' --quick' if args.quick else ''}`, "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {cpu_model()}, {os.cpu_count()} cores, "
        f"Python {sys.version.split()[0]}. 1-minute load average {min(loads):.1f}–"
        f"{max(loads):.1f} (median {statistics.median(loads):.1f}) on {os.cpu_count()} cores "
        "before and after each run, the graph's own six processes included (alone, they make "
        "~2); above ~3 the machine was shared and absolute rates and latencies measure the "
        "load as much as the graph. Compare configurations as ratios inside one pass (each "
        "pass runs every configuration once, back to back)."
        + (f" Left out: {', '.join(args.exclude)} (bag:pass; that pass overlapped with a test "
           "graph on the same DDS domain, whose messages the listener counted too); a later "
           "pass replaces it." if getattr(args, "exclude", None) else "")
        + (f" **Every run stalled on purpose**: {args.stalls[0]:g} ms of one nice -20 busy "
           f"process per core, {args.stalls[1]:g} s after the end of the stall before "
           "(bench/stall_injector.py)." if getattr(args, "stalls", None) else ""),
        "",
        "Bags: `phantom_colon` (the committed 3 s phantom, 90 frames) and the long render "
        f"(`endo-sim render colon --seed 2 --duration {args.long_seconds:g} --depth-every 30`, "
        f"{30 * args.long_seconds:.0f} frames; not tuned on), 640×480 mono8 at 30 fps, played "
        "at 1× (30 fps) unless said. "
        "Each run is `endo_bringup.graph.run_live_graph` (the demo's runner and table: "
        "replay → correction → sfs → tracker bridge → flow → recorder, separate processes, "
        "loopback DDS with the large-frame shared-memory profile) with the bag's true "
        "calibrations, watched by `endo_bringup.graph_monitor` (what `endo-demo` prints). "
        "Timing (`--listener recording`, the default since 2026-12-02): the nodes' outputs "
        "are taken from the recording the graph's `endo-record` writes anyway (its log time: "
        "the middleware's receive time at the recorder); the bench process "
        "subscribes only to the camera_info the replay publishes beside each image and to "
        "/diagnostics. Runs named `[topics listener]` are watched as before this change (a "
        "listener in the bench process subscribed to every node output: ~5 MB of images a "
        "frame), their figures taken at that listener. "
        "out/in: frames on the stage's output and input as the recorder (or the listener) "
        "received them; rcvd: frames the node received on that input (its /diagnostics; fewer "
        "than in: frames DDS overwrote before the starved node took them, or still waiting "
        "when the run ended); skipped: the node's own /diagnostics count of stale frames it "
        "passed over for a newer one; rate: outputs per second of the play window; latency: "
        "arrival at the recorder (or the listener) minus the frame's publish at the replay "
        "(the DDS source timestamp of its camera_info, or of its image for the topics "
        "listener), same stamp; end to end: to the world cloud `/endoscope/points` (flow "
        "publishes clouds once its scale has converged, so the first ~1 s of frames have "
        "none). CPU: % of one core over the play window from /proc (utime + stime); RSS: peak.",
        "",
        "| bag | configuration | scale | pass | load | correction out/in | sfs out/in | "
        "flow out/in | depth Hz | clouds | correction p50/p99 ms | sfs p50/p99 ms | "
        "end to end p50/p99 ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        f = r.figures
        lines.append(
            f"| {r.bag} | {r.configuration.name} | {r.configuration.solve_scale:g} | {r.run} | "
            f"{r.load_before:.1f} | {_stage(f, CORRECTION)} | {_stage(f, SFS)} | "
            f"{_stage(f, FLOW)} | {f.stage(SFS).rate_hz:.1f} | {f.end_to_end_frames} | "
            f"{_ms(f.stage(CORRECTION).latency_ms)} | {_ms(f.stage(SFS).latency_ms)} | "
            f"{_ms(f.end_to_end_ms)} |"
        )
    names = process_names(results)
    lines += ["", "CPU (% of one core over the play window) and peak RSS (MB) per process:", "",
              "| bag | configuration | scale | pass | " + " | ".join(names) + " |",
              "|---|---|---|---|" + "---|" * len(names)]
    for r in results:
        cells = {p.name: f"{p.cpu_percent:.0f} % / {p.rss_mb:.0f}" for p in r.figures.processes}
        lines.append(
            f"| {r.bag} | {r.configuration.name} | {r.configuration.solve_scale:g} | {r.run} | "
            + " | ".join(cells.get(name, "—") for name in names) + " |"
        )
    lines += ["", *ratio_lines(results), "", *cost_lines(results), "", *timing_lines(results),
              "", *target_lines(results)]
    return "\n".join(lines) + "\n"


def sweep_report(sweep: list[Result]) -> str:
    """The docs/benchmarks.md section of the demo-rate sweep."""
    loads = [r.load_before for r in sweep] + [r.figures.load for r in sweep]
    lines = [
        SWEEP_TITLE,
        "",
        f"`bench/bench_graph.py --sweep-only`, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, "
        f"{cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}; 1-minute "
        f"load average {min(loads):.1f}–{max(loads):.1f} (median {statistics.median(loads):.1f}) "
        "before and after each run. The phantom (90 frames, 640×480 at 30 fps) through the "
        "demo's graph and runner (`endo_bringup.graph.run_live_graph`: every node warmed up on "
        "the bag's camera and up, every subscription matched before the replay plays), every "
        "optimisation on; each rate once per pass, the passes back to back. Every frame kept: "
        "every stage's per-frame output carried every frame played and no stage skipped one "
        "(`GraphFigures.every_frame_kept`, what the demo's OK needs besides the accuracy bars).",
        "",
        "| scale | rate | fps | pass | load | correction out/in | sfs out/in | "
        "flow out/in | every frame kept | sfs p50/p99 ms | end to end p50/p99 ms |",
        "|---" * 11 + "|",
    ]
    for r in sorted(sweep, key=lambda r: (-r.configuration.solve_scale, r.rate, r.run)):
        f = r.figures
        lines.append(
            f"| {r.configuration.solve_scale:g} | {r.rate:g} | {30 * r.rate:g} | {r.run} | "
            f"{r.load_before:.1f} | "
            f"{_stage(f, CORRECTION)} | {_stage(f, SFS)} | {_stage(f, FLOW)} | "
            f"{'yes' if f.every_frame_kept else 'no'} | {_ms(f.stage(SFS).latency_ms)} | "
            f"{_ms(f.end_to_end_ms)} |"
        )
    for scale in sorted({r.configuration.solve_scale for r in sweep}, reverse=True):
        best = demo_rate_of([r for r in sweep if r.configuration.solve_scale == scale])
        lines += ["", f"Fastest rate with every frame kept in every pass at solve_scale "
                  f"{scale:g}: " + (f"**{best:g}**" if best else "none of those tried") + "."]
    return "\n".join(lines) + "\n"


def process_names(results: list[Result]) -> list[str]:
    """The processes of every run, in the order first seen (SFS workers add rows)."""
    return list(dict.fromkeys(p.name for r in results for p in r.figures.processes))


def ratio_lines(results: list[Result]) -> list[str]:
    """Each optimisation off against all on, same bag, scale and pass (none: no lines)."""
    if all(r.configuration.name == "all on" for r in results):
        return []
    lines = ["Each other configuration (an optimisation off, or the baseline) against all on "
             "(same bag, scale and pass; >1: the other is "
             "worse for latency, <1: off gives fewer depth frames):", ""]
    lines += ["| bag | configuration | scale | pass | depth frames off/on | "
              "end-to-end p50 off/on | sfs CPU off/on (all workers) |",
              "|---|---|---|---|---|---|---|"]
    for r in results:
        if r.configuration.name == "all on":
            continue
        base = next((b for b in results if b.bag == r.bag and b.run == r.run
                     and b.configuration.solve_scale == r.configuration.solve_scale
                     and b.configuration.name == "all on"), None)
        if base is None:
            continue

        def cpu(res: Result) -> float:  # every SFS worker's
            found = [p.cpu_percent for p in res.figures.processes
                     if p.name == SFS or p.name.startswith(SFS + "-")]
            return sum(found) if found else float("nan")

        depth = r.figures.stage(SFS).frames_out / max(base.figures.stage(SFS).frames_out, 1)
        p50 = r.figures.end_to_end_ms[0] / base.figures.end_to_end_ms[0]
        lines.append(f"| {r.bag} | {r.configuration.name} | {r.configuration.solve_scale:g} | "
                     f"{r.run} | {depth:.2f} | {p50:.2f} | {cpu(r) / cpu(base):.2f} |")
    return lines


def cost_lines(results: list[Result]) -> list[str]:
    """CPU ms per frame of each process (all on), and the cores 30 Hz would need."""
    runs = [r for r in results if " off" not in r.configuration.name]
    names = process_names(runs)
    if not names:
        return []
    lines = ["CPU cost per frame, every optimisation on (each SFS configuration): CPU ms "
             "each process spent (from the start of the play to its end, the drain included) "
             "per frame it let out (SFS workers: each per frame the stage let out; the "
             "recorder, bridge and replay: per frame played). CPU time is less sensitive to the "
             "load than wall time, but not immune: on a starved machine it grows with cache and "
             "memory contention and with sfs's two threads waiting for each other, and a "
             "stage's work on frames that gave no output (flow takes every corrected image and "
             "pose; frames it processed without a pose) is charged to those it let out. So Σ "
             "ms per frame is an upper bound of the CPU a frame costs, against the 66 CPU-ms "
             "of 2 cores × 33 ms, and Σ × 30 / 1000 of the cores 30 Hz needs:", "",
             "| bag | configuration | scale | pass | " + " | ".join(names) + " | Σ ms per frame | "
             "cores for 30 Hz (bound) | bench listener ms per frame over the play (not in "
             "Σ) | reading the recording after it, ms per frame |",
             "|---|---|---|---|" + "---|" * (len(names) + 4)]
    for r in runs:
        costs = [r.figures.cpu_ms_per_frame(n) for n in names]
        total = sum(c for c in costs if c == c)  # a process this run did not have: NaN, "—"
        lines.append(f"| {r.bag} | {r.configuration.name} | {r.configuration.solve_scale:g} | "
                     f"{r.run} | "
                     + " | ".join("—" if c != c else f"{c:.1f}" for c in costs)
                     + f" | {total:.0f} | {total * 30 / 1000:.2f} | "
                     f"{getattr(r, 'listener_ms_per_frame', float('nan')):.1f} | "
                     f"{getattr(r, 'read_ms_per_frame', float('nan')):.1f} |")
    return lines


def timing_lines(results: list[Result]) -> list[str]:
    """The topics listener's runs timed both ways: the two latency definitions side by side."""
    runs = [r for r in results if getattr(r, "recording_figures", None) is not None]
    if not runs:
        return []
    lines = ["The two timings of one run (`[topics listener]` runs: the listener's arrivals "
             "and the recording's, the same messages): frames out and latency p50/p99 ms, "
             "listener → recording:", "",
             "| bag | configuration | pass | correction out | sfs out | flow out | clouds | "
             "correction | sfs | end to end |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        a, b = r.figures, r.recording_figures
        assert b is not None
        lines.append(
            f"| {r.bag} | {r.configuration.name} | {r.run} | "
            + " | ".join(f"{a.stage(n).frames_out} → {b.stage(n).frames_out}"
                         for n in (CORRECTION, SFS, FLOW))
            + f" | {a.end_to_end_frames} → {b.end_to_end_frames} | "
            + " | ".join(f"{_ms(a.stage(n).latency_ms)} → {_ms(b.stage(n).latency_ms)}"
                         for n in (CORRECTION, SFS))
            + f" | {_ms(a.end_to_end_ms)} → {_ms(b.end_to_end_ms)} |")
    lines += ["", "Per message of those runs (median / p99 ms, messages): the recorder's "
              "reception minus the listener's, and the replay's publish of a frame's "
              "camera_info minus its image's:", "", "| bag | pass | what | median | p99 | n |",
              "|---|---|---|---|---|---|"]
    for r in runs:
        for what, (median, p99, n) in r.offsets.items():
            lines.append(f"| {r.bag} | {r.run} | {what} | {median:.2f} | {p99:.2f} | {n} |")
    return lines


def target_lines(results: list[Result]) -> list[str]:
    """Issue 15's targets against the long bag's all-on runs."""
    def runs(scale: float) -> list[Result]:
        longest = max(r.figures.frames_played for r in results)
        return [r for r in results if r.configuration.name == "all on"
                and r.configuration.solve_scale == scale and r.figures.frames_played == longest]

    half, full = runs(0.5), runs(1.0)
    lines = ["Targets (issue 15), on the longest bag with every optimisation on, each pass:", "",
             "| target | measured | met |", "|---|---|---|"]
    if half:
        skipped = [r.figures.stage(SFS).skipped or 0 for r in half]
        kept = [r.figures.every_frame_kept for r in half]
        lines.append(
            "| 30 fps 640×480 at solve_scale 0.5: depth and cloud for every frame | "
            + "; ".join(f"sfs {_stage(r.figures, SFS)}, flow {_stage(r.figures, FLOW)}"
                        for r in half)
            + f" | {'yes' if all(kept) else 'no'} ({sum(skipped)} sfs skips) |"
        )
        p50 = [r.figures.end_to_end_ms[0] for r in half]
        p99 = [r.figures.end_to_end_ms[1] for r in half]
        lines.append(
            f"| end to end p50 ≤ {TARGET_P50_MS:g} ms, p99 ≤ {TARGET_P99_MS:g} ms | "
            + "; ".join(f"{a:.0f} / {b:.0f} ms" for a, b in zip(p50, p99, strict=True))
            + f" | {'yes' if max(p50) <= TARGET_P50_MS and max(p99) <= TARGET_P99_MS else 'no'} |"
        )
    if full:
        rates = [r.figures.stage(SFS).rate_hz for r in full]
        lines.append(
            f"| full resolution ≥ {TARGET_FULL_HZ:g} Hz depth | "
            + "; ".join(f"{x:.1f} Hz" for x in rates)
            + f" | {'yes' if min(rates) >= TARGET_FULL_HZ else 'no'} |"
        )
    return lines


def demo_rate_of(sweep: list[Result]) -> float | None:
    """The fastest rate at which every run kept every frame."""
    rates = sorted({r.rate for r in sweep})
    good = [rate for rate in rates if all(r.figures.every_frame_kept
                                          for r in sweep if r.rate == rate)]
    return max(good) if good else None


def main() -> int:
    """Run every configuration ``--runs`` times; print; write the section unless --no-write."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--rate", type=float, default=1.0, help="playback rate (1.0: 30 fps)")
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.5])
    parser.add_argument("--long-seconds", type=float, default=60.0)
    parser.add_argument("--long-bag", type=Path, default=LONG_BAG)
    parser.add_argument("--no-long", action="store_true", help="the phantom only")
    parser.add_argument("--long-only", action="store_true", help="the long bag only")
    parser.add_argument("--sweep", action="store_true", help="find the demo's playback rate")
    parser.add_argument("--sweep-rates", type=float, nargs="+", default=[0.1, 0.25, 0.5, 1.0])
    parser.add_argument("--only", nargs="+", default=None,
                        help="configuration names to run, in this order")
    parser.add_argument("--quick", action="store_true", help="one pass, phantom only, all on")
    parser.add_argument("--no-write", action="store_true", help="do not edit docs/benchmarks.md")
    parser.add_argument("--keep-recordings", action="store_true",
                        help="keep each run's graph.mcap (deleted once read: ~2 GB per minute)")
    parser.add_argument("--report-from", type=Path, nargs="+", default=None,
                        help="only write the report of saved results.pkl files (concatenated)")
    parser.add_argument("--exclude", nargs="+", default=[], metavar="BAG:PASS",
                        help="with --report-from: leave out a bag's runs of one pass (a pass "
                        "that was disturbed, e.g. by another graph on the same DDS domain)")
    parser.add_argument("--first-pass", type=int, default=1, help="number of the first pass")
    parser.add_argument("--baseline", type=Path, default=None, metavar="SRC_ROOT",
                        help="also run every configuration with this checkout's src/* packages")
    parser.add_argument("--listener", choices=[*LISTEN_MODES, "both"], default="recording",
                        help="how the bench watches the graph (see the module docstring)")
    parser.add_argument("--stalls", type=float, nargs=2, default=None, metavar=("MS", "EVERY_S"),
                        help="stall the whole machine for MS ms every EVERY_S seconds during "
                        "each run (bench/stall_injector.py: one nice -20 busy process per core)")
    parser.add_argument("--sweep-only", action="store_true", help="only the demo-rate sweep")
    parser.add_argument("--sweep-scale", type=float, default=GRAPH_SOLVE_SCALE,
                        help=f"solve_scale of the sweep (the demo's: {GRAPH_SOLVE_SCALE:g})")
    args = parser.parse_args()
    # SIGTERM ends the bench like Ctrl-C: unwinding stops every child process
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    if args.report_from is not None:
        results, sweep = [], []
        for path in args.report_from:
            with path.open("rb") as file:
                more, more_sweep = pickle.load(file)
            results += more
            sweep += more_sweep
        excluded = {tuple(item.rsplit(":", 1)) for item in args.exclude}
        results = [r for r in results if (r.bag, str(r.run)) not in excluded]
        results.sort(key=lambda r: (r.run, r.bag != PHANTOM.stem))
        return write_report(results, sweep, args)
    if args.quick:
        args.runs, args.no_long, args.only = 1, True, ["all on"]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", "43")
    work = Path(tempfile.mkdtemp(prefix="endo3d_bench_graph_"))
    env, note = with_large_frame_profile(env, work)
    print(f"bench_graph: {note}; runs in {work}", flush=True)
    no_long = args.no_long or args.sweep_only
    bags = [PHANTOM] if no_long else [PHANTOM, ensure_long_bag(args.long_bag, args.long_seconds)]
    if args.long_only and not no_long:
        bags = bags[1:]
    chosen = configurations(args.scales)
    if args.only is not None:  # in the order --only names them (a pass's order is a choice)
        chosen = [c for name in args.only for c in chosen if c.name == name]
    results: list[Result] = []
    sweep: list[Result] = []
    if args.sweep_only:
        chosen, args.sweep = [], True
    listens = ([("", "recording"), (TOPICS_SUFFIX, "topics")] if args.listener == "both"
               else [("", args.listener)])
    for run in range(args.first_pass, args.first_pass + args.runs):
        for bag in bags:
            for configuration in chosen:
                variants = [(replace(configuration, name=configuration.name + suffix), listen,
                             env) for suffix, listen in listens]
                if args.baseline is not None:
                    variants.append((replace(configuration,
                                             name=configuration.name + BASELINE_SUFFIX),
                                     listens[0][1], baseline_env(env, args.baseline)))
                for variant, listen, environment in variants:
                    load = os.getloadavg()[0]
                    stalled = ("" if args.stalls is None else
                               f", stalls of {args.stalls[0]:g} ms every {args.stalls[1]:g} s")
                    print(f"== pass {run}: {bag.name}, {variant.name}, solve_scale "
                          f"{variant.solve_scale:g}, rate {args.rate:g}, listener {listen}"
                          f"{stalled} (load {load:.1f})", flush=True)
                    with stalls(args.stalls):
                        result = run_once(bag, variant, args.rate, work, environment, listen,
                                          keep_recording=args.keep_recordings)
                    result.run, result.load_before = run, load
                    _print_result(result)
                    results.append(result)
                    save(work, results, sweep)
        if args.sweep:
            for rate in args.sweep_rates:
                load = os.getloadavg()[0]
                print(f"== sweep pass {run}: phantom at {rate:g}x (load {load:.1f})", flush=True)
                result = run_once(PHANTOM, Configuration("all on", args.sweep_scale), rate,
                                  work, env, listens[0][1], keep_recording=args.keep_recordings)
                result.run, result.load_before = run, load
                _print_result(result)
                sweep.append(result)
                save(work, results, sweep)
    return write_report(results, sweep, args)


@contextmanager
def stalls(stall: list[float] | None) -> Iterator[None]:
    """bench/stall_injector.py running (``stall``: ms, every seconds) while the block runs."""
    if stall is None:
        yield
        return
    injector = subprocess.Popen([sys.executable, str(Path(__file__).with_name(
        "stall_injector.py")), "--ms", str(stall[0]), "--every", str(stall[1])])
    try:
        yield
    finally:
        injector.terminate()
        injector.wait(10)


def save(work: Path, results: list[Result], sweep: list[Result]) -> None:
    """The results so far, for ``--report-from`` (a report can be rewritten without rerunning)."""
    with (work / "results.pkl").open("wb") as file:
        pickle.dump((results, sweep), file)


def write_report(results: list[Result], sweep: list[Result], args: argparse.Namespace) -> int:
    """Print the sections; write them into docs/benchmarks.md unless --no-write.

    The configurations' section and the sweep's are separate, so that a
    ``--sweep-only`` run replaces the sweep alone.
    """
    sections = [(report(results, args), TITLE)] if results else []
    sections += [(sweep_report(sweep), SWEEP_TITLE)] if sweep else []
    for section, title in sections:
        print(section)
        if not args.no_write:
            replace_section(section, title)
    return 0


if __name__ == "__main__":
    sys.exit(main())
