"""One live node alone at video rate: its CPU per frame, fed from a graph recording.

    .venv/bin/python bench/bench_flow_node.py RECORDING [--runs 2] [--rate 1.0]
        [--node flow|record] [--baseline SRC_ROOT] [--variant NAME=PARAM:=VALUE,...]
    .venv/bin/python bench/bench_flow_node.py --decoding [RECORDING]

RECORDING is a live graph's recording (``graph.mcap`` of a bench_graph or
``endo-demo`` run, with ``camera.yaml`` beside it): ``endo-replay`` plays its
corrected images, relative depths, camera_info and camera poses, as the
graph's nodes published them, into one ``endo-flow`` process (the graph's
command line, warmed up on the recording's camera), over loopback DDS with
the large-frame profile. The input is the same in every run, unlike in
bench_graph, where flow gets whatever depth frames the SFS node let out, so
the node's CPU per frame can be compared between two versions of it.

``--node record`` plays every topic of the recording into one ``endo-record``
(the graph's recorder command: lz4 chunks, flushed every 0.2 s) instead; its
CPU is reported per image_corrected frame played (a frame of the graph).

``--baseline SRC_ROOT`` (a checkout's root, e.g. ``git archive main src | tar
-x -C /tmp/base``) alternates each run of this tree's node with one of the
baseline's (its ``src/*`` packages first on PYTHONPATH), so that the two
compare as a ratio inside one pass, under the same load.

``--variant NAME=PARAM:=VALUE[,PARAM:=VALUE]`` (repeatable) runs the flow
node of this tree once per variant in each pass, with those parameters
added to its command line (e.g. ``map1=map_decimation:=1``
``map4=map_decimation:=4``), so that settings compare inside one pass too.

``--decoding`` times, instead, what flow does with each pose and camera_info
it takes, rclpy's message objects against endo_io's CDR readers, on the
recording's own messages (or synthetic ones without a recording): per
message, ``deserialize_message`` + ``pose_to_matrix`` against
``pose_stamped_from_cdr`` + ``pose_to_matrix``; ``deserialize_message`` +
``CameraInfoCache.model_of`` against ``camera_info_from_cdr`` + the same.

Reported per run: the depth frames played, the clouds and the flow hop's
latency (the cloud's publish at flow minus its depth_relative's publish at
the replay, p50 / p99: a listener subscribes to both), the node's CPU time (user +
system, /proc) from the start of the play to 1 s after its end, per depth
frame played (per image_corrected frame for the recorder), per frame
processed (a scale out: a node that skips fewer stale depths spends more per
frame played), and per message
of any topic played (the node's subscriptions wake it for each), and the CPU
seconds of each of its threads since it started (warm-up included).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from endo_bringup.dds_profile import with_large_frame_profile
from endo_bringup.graph import (
    NODE_UP,
    RECORDER,
    GraphProcess,
    camera_file_path,
    recorder_process,
    replay_process,
)
from endo_bringup.graph_monitor import GraphMonitor, _cpu_and_rss
from endo_bringup.process_group import ProcessGroup, console_script
from endo_io.bag import BagReader
from endo_io.topics import (
    CAMERA_INFO,
    CAMERA_POSE,
    DEPTH_RELATIVE,
    IMAGE_CORRECTED,
    POINTS,
    SCALE,
)

PLAYED = (IMAGE_CORRECTED, DEPTH_RELATIVE, CAMERA_INFO, CAMERA_POSE)


def run_once(recording: Path, rate: float, env: dict[str, str], logs: Path,
             node_name: str = "flow", parameters: tuple[str, ...] = ()) -> dict[str, float]:
    """One play of ``recording`` into a fresh node (``flow`` or ``record``); its CPU figures.

    ``parameters``: ``name:=value`` items added to the flow node's command line.
    """
    with BagReader(recording) as reader:
        wanted = PLAYED if node_name == "flow" else tuple(reader.topics)
        counts = {t: reader.topics[t].message_count for t in wanted if t in reader.topics}
    if node_name == "flow":
        name = "endo-flow"
        command = [console_script(name), "--ros-args", "-p",
                   f"warm_up_camera_file:={camera_file_path(recording)}",
                   *(item for parameter in parameters for item in ("-p", parameter))]
        up = NODE_UP
    else:
        name = RECORDER
        process = recorder_process(list(counts), logs / "recorded.mcap")
        command = [console_script(process.executable), *process.arguments]
        up = re.compile(r"recording ")
    # the node's subscription of each topic, and the listener's of the first one
    waits = {t: 1 for t in counts}
    waits[next(iter(counts))] += 1
    player = replay_process(recording, list(counts), rate, waits)
    # a listener counts the flow node's outputs (one scale per frame it processed) and
    # times its clouds from the depth_relative of their stamp (both publish times)
    watched = [GraphProcess("endo-flow", "endo-flow", publishes=(SCALE, POINTS)), player]
    if node_name == "flow":
        waits[DEPTH_RELATIVE] += 1
        watched.append(GraphProcess("depth listener", "depth listener",
                                    publishes=(DEPTH_RELATIVE,)))
    logs.mkdir(parents=True, exist_ok=True)
    with GraphMonitor(watched, env) as monitor, \
            ProcessGroup(dict(env, PYTHONUNBUFFERED="1"), logs) as group:
        node = group.start(name, command)
        deadline = time.monotonic() + 90.0
        while not up.search(group.log(name)):
            if not group.running(name) or time.monotonic() > deadline:
                raise RuntimeError(f"{name} did not come up:\n{group.log(name)}")
            time.sleep(0.1)
        before = _cpu_and_rss(node.pid)
        replay = group.start(player.name, player.command())
        replay.wait(120.0)
        time.sleep(1.0)  # the last frames' processing
        after = _cpu_and_rss(node.pid)
        threads = thread_cpu_s(node.pid)
        group.stop()
    assert before is not None and after is not None
    cpu_ms = 1e3 * (after[0] - before[0])
    outputs = len(monitor.arrivals.times.get(SCALE, {}))
    hops = hop_ms(monitor.arrivals.times.get(DEPTH_RELATIVE, {}),
                  monitor.arrivals.times.get(POINTS, {}))
    frames = counts.get(DEPTH_RELATIVE if node_name == "flow" else IMAGE_CORRECTED, 0)
    return {"frames": frames, "processed": outputs, "messages": sum(counts.values()),
            "cpu ms": cpu_ms, "ms per frame": cpu_ms / max(frames, 1),
            "ms per processed": cpu_ms / max(outputs, 1),
            "ms per message": cpu_ms / max(sum(counts.values()), 1), "rss MB": after[1],
            "clouds": len(hops), "hop p50 ms": percentile(hops, 50),
            "hop p99 ms": percentile(hops, 99),
            **{f"thread {name} s": seconds for name, seconds in threads.items()}}


def decoding_costs(recording: Path | None, repeats: int = 5) -> dict[str, float]:
    """Microseconds per message of flow's pose and camera_info handling, rclpy's and endo_io's.

    Each figure is the best of ``repeats`` passes over the messages (at most
    500 of each topic), so that it is the code's cost, not the machine's load.
    """
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CameraInfo

    from endo_io.camera import CameraInfoCache, CameraModel, camera_info_from_cdr
    from endo_io.pose import matrix_to_pose, pose_stamped_from_cdr, pose_to_matrix, rigid_transform

    poses: list[bytes] = []
    infos: list[bytes] = []
    if recording is not None:
        with BagReader(recording) as reader:
            for message in reader.messages([CAMERA_POSE, CAMERA_INFO]):
                kept = poses if message.topic == CAMERA_POSE else infos
                if len(kept) < 500:
                    kept.append(bytes(message.data))
    else:
        camera = CameraModel.pinhole(640, 480, 500.0, 500.0, 319.5, 239.5)
        for k in range(500):
            T = rigid_transform([0.01 * k, 0.2, 0.3], [0.01, 0.02, 0.001 * k])
            poses.append(serialize_message(matrix_to_pose(T, 10**9 + k * 16_666_667, "world")))
            infos.append(serialize_message(camera.to_camera_info(10**9 + k * 33_333_333)))

    def best_us(step: Any, items: list[bytes]) -> float:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            for data in items:
                step(data)
            times.append(time.perf_counter() - start)
        return 1e6 * min(times) / len(items)

    rclpy_cache, cdr_cache = CameraInfoCache(), CameraInfoCache()
    return {
        "poses": len(poses), "camera_infos": len(infos),
        "pose rclpy us": best_us(lambda d: pose_to_matrix(deserialize_message(d, PoseStamped)),
                                 poses),
        "pose cdr us": best_us(lambda d: pose_to_matrix(pose_stamped_from_cdr(d)), poses),
        "camera_info rclpy us": best_us(
            lambda d: rclpy_cache.model_of(deserialize_message(d, CameraInfo)), infos),
        "camera_info cdr us": best_us(lambda d: cdr_cache.model_of(camera_info_from_cdr(d)),
                                      infos),
    }


def hop_ms(depths: dict[int, tuple[int, int]], clouds: dict[int, tuple[int, int]]
           ) -> list[float]:
    """Per cloud: its publish at flow minus its depth_relative's publish at the replay, ms.

    Both are DDS source timestamps (the publishers' system clocks, one machine).
    """
    return [1e-6 * (cloud[0] - depths[stamp][0]) for stamp, cloud in clouds.items()
            if stamp in depths]


def percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile of ``values`` (NaN when empty)."""
    return float(np.percentile(values, q)) if values else float("nan")


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) of each thread name of process ``pid``, since it started."""
    found: dict[str, float] = {}
    ticks = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1: stat.rindex(")")]
        fields = stat.rsplit(")", 1)[1].split()
        found[name] = found.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / ticks
    return dict(sorted(found.items(), key=lambda item: -item[1]))


def main() -> int:
    """Play the recording ``--runs`` times into the flow node; print each run's figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path, nargs="?", default=None)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--rate", type=float, default=1.0)
    parser.add_argument("--node", choices=("flow", "record"), default="flow")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="a checkout's root whose src/* packages run in alternate runs")
    parser.add_argument("--variant", action="append", default=[],
                        metavar="NAME=PARAM:=VALUE[,PARAM:=VALUE]",
                        help="a run of this tree's flow node with these parameters in each "
                        "pass (repeatable)")
    parser.add_argument("--decoding", action="store_true",
                        help="time flow's pose and camera_info decoding instead (no node)")
    args = parser.parse_args()
    if args.decoding:
        print(f"bench_flow_node --decoding on {args.recording or 'synthetic messages'} "
              f"(load {os.getloadavg()[0]:.1f}): "
              + ", ".join(f"{k} {v:.3g}" for k, v in decoding_costs(args.recording).items()))
        return 0
    if args.recording is None:
        parser.error("a recording is needed (all but --decoding)")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", "43")
    work = Path(tempfile.mkdtemp(prefix="endo3d_bench_flow_node_"))
    env, note = with_large_frame_profile(env, work)
    print(f"bench_flow_node: {args.node} on {args.recording}, rate {args.rate:g}; "
          f"{note}", flush=True)
    variants: dict[str, tuple[dict[str, str], tuple[str, ...]]] = {"this tree": (env, ())}
    if args.variant:
        variants = {}
        for spec in args.variant:
            name, _, parameters = spec.partition("=")
            if not name or ":=" not in parameters:
                parser.error(f"--variant {spec!r}: expected NAME=PARAM:=VALUE[,...]")
            variants[name] = (env, tuple(parameters.split(",")))
    if args.baseline is not None:
        packages = sorted(str(p) for p in (args.baseline / "src").iterdir() if p.is_dir())
        variants = {"baseline": (dict(env, PYTHONPATH=os.pathsep.join(packages)), ()),
                    **variants}
    figures: dict[str, list[float]] = {name: [] for name in variants}
    hops: dict[str, list[tuple[float, float]]] = {name: [] for name in variants}
    for run in range(1, args.runs + 1):
        for name, (variant_env, parameters) in variants.items():
            load = os.getloadavg()[0]
            result = run_once(args.recording, args.rate, variant_env,
                              work / f"logs{run}_{len(figures[name])}_{name.replace(' ', '_')}",
                              args.node, parameters)
            figures[name].append(result["ms per frame"])
            hops[name].append((result["hop p50 ms"], result["hop p99 ms"]))
            print(f"run {run}, {name} (load {load:.1f} -> {os.getloadavg()[0]:.1f}): "
                  + ", ".join(f"{k} {v:.3g}" for k, v in result.items()), flush=True)
    for name, per_frame in figures.items():
        print(f"{args.node} CPU per frame, {name}: {', '.join(f'{x:.2f}' for x in per_frame)} ms "
              f"(median {statistics.median(per_frame):.2f})")
    if args.node == "flow":
        for name, pairs in hops.items():
            print(f"flow hop (depth_relative published -> cloud published), {name}: "
                  + ", ".join(f"p50 {p50:.1f} / p99 {p99:.1f}" for p50, p99 in pairs) + " ms")
    if args.baseline is not None and "this tree" in figures:
        ratios = [a / b for a, b in zip(figures["this tree"], figures["baseline"], strict=True)]
        print(f"this tree / baseline, per pass: {', '.join(f'{r:.3f}' for r in ratios)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
