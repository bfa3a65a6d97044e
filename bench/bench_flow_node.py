"""The live ``endo-flow`` node alone at video rate: its CPU per frame, fed from a graph recording.

    .venv/bin/python bench/bench_flow_node.py RECORDING [--runs 2] [--rate 1.0]

RECORDING is a live graph's recording (``graph.mcap`` of a bench_graph or
``endo-demo`` run, with ``camera.yaml`` beside it): ``endo-replay`` plays its
corrected images, relative depths, camera_info and camera poses, as the
graph's nodes published them, into one ``endo-flow`` process (the graph's
command line, warmed up on the recording's camera), over loopback DDS with
the large-frame profile. The input is the same in every run, unlike in
bench_graph, where flow gets whatever depth frames the SFS node let out, so
the node's CPU per frame can be compared between two versions of it.

Reported per run: the depth frames played, the flow node's CPU time (user +
system, /proc) from the start of the play to 1 s after its end, per depth
frame played, and per message of any topic played (the node's subscriptions
wake it for each), and the CPU seconds of each of its threads since it
started (warm-up included).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from endo_bringup.dds_profile import with_large_frame_profile
from endo_bringup.graph import NODE_UP, camera_file_path, replay_process
from endo_bringup.graph_monitor import _cpu_and_rss
from endo_bringup.process_group import ProcessGroup, console_script
from endo_io.bag import BagReader
from endo_io.topics import CAMERA_INFO, CAMERA_POSE, DEPTH_RELATIVE, IMAGE_CORRECTED

PLAYED = (IMAGE_CORRECTED, DEPTH_RELATIVE, CAMERA_INFO, CAMERA_POSE)


def run_once(recording: Path, rate: float, env: dict[str, str], logs: Path) -> dict[str, float]:
    """One play of ``recording`` into a fresh flow node; its CPU figures."""
    with BagReader(recording) as reader:
        counts = {t: reader.topics[t].message_count for t in PLAYED if t in reader.topics}
    flow = [console_script("endo-flow"), "--ros-args", "-p",
            f"warm_up_camera_file:={camera_file_path(recording)}"]
    player = replay_process(recording, list(counts), rate,
                            {t: 1 for t in counts})  # the flow node's subscription of each
    with ProcessGroup(dict(env, PYTHONUNBUFFERED="1"), logs) as group:
        node = group.start("endo-flow", flow)
        deadline = time.monotonic() + 90.0
        while not NODE_UP.search(group.log("endo-flow")):
            if not group.running("endo-flow") or time.monotonic() > deadline:
                raise RuntimeError(f"endo-flow did not come up:\n{group.log('endo-flow')}")
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
    return {"depth frames": counts.get(DEPTH_RELATIVE, 0), "messages": sum(counts.values()),
            "cpu ms": cpu_ms, "ms per depth frame": cpu_ms / max(counts.get(DEPTH_RELATIVE, 0), 1),
            "ms per message": cpu_ms / max(sum(counts.values()), 1), "rss MB": after[1],
            **{f"thread {name} s": seconds for name, seconds in threads.items()}}


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
    parser.add_argument("recording", type=Path)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--rate", type=float, default=1.0)
    args = parser.parse_args()
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", "43")
    work = Path(tempfile.mkdtemp(prefix="endo3d_bench_flow_node_"))
    env, note = with_large_frame_profile(env, work)
    print(f"bench_flow_node: {args.recording}, rate {args.rate:g}; "
          f"{note}", flush=True)
    figures = []
    for run in range(1, args.runs + 1):
        load = os.getloadavg()[0]
        result = run_once(args.recording, args.rate, env, work / f"logs{run}")
        figures.append(result)
        print(f"run {run} (load {load:.1f} -> {os.getloadavg()[0]:.1f}): "
              + ", ".join(f"{k} {v:.3g}" for k, v in result.items()), flush=True)
    per_frame = [f["ms per depth frame"] for f in figures]
    print(f"flow CPU per depth frame: {', '.join(f'{x:.2f}' for x in per_frame)} ms "
          f"(median {statistics.median(per_frame):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
