"""endo_bringup.graph_monitor: the figures bench_graph and endo-demo report, from known arrivals.

No DDS here: the monitor's arrivals and /diagnostics are filled by hand with
a run whose every latency and count is known, and the figures must say
exactly that. The /proc readers are checked on real child processes.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from endo_bringup.graph import PLAYER, RECORDER, GraphError, GraphSettings, graph_processes
from endo_bringup.graph_monitor import (
    CLOUD_TOPIC,
    GraphFigures,
    GraphMonitor,
    GraphMonitorError,
    ProcessFigures,
    ProcessSampler,
    StageFigures,
    _children,
    _cpu_and_rss,
    graph_figures,
    node_name_of,
    recorded_arrivals,
    stage_lines,
)
from endo_io import topics

PERIOD_NS = 33_333_333
T0 = 1_800_000_000 * 1_000_000_000  # wall-clock ns of the first publish
STAMP0 = 1_700_000_000 * 1_000_000_000
MS = 1_000_000


def _table(tmp_path: Path, settings: GraphSettings | None = None):
    played = [topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE]
    return graph_processes(tmp_path / "bag.mcap", played, tmp_path / "p.yaml",
                           tmp_path / "h.yaml", tmp_path / "graph.mcap",
                           settings or GraphSettings())


def test_node_parameters_of_a_configuration_are_added_to_their_rows(tmp_path: Path) -> None:
    settings = GraphSettings(node_parameters={"endo-sfs": {"warm_start": "false"},
                                              "endo-flow": {"newest_frame": "false"}})
    rows = {p.name: p for p in _table(tmp_path, settings)}
    assert rows["endo-sfs"].parameters["warm_start"] == "false"
    assert rows["endo-sfs"].parameters["model"] == "near_light"  # the table's own stay
    camera = f"warm_up_camera_file:={tmp_path / 'camera.yaml'}"
    assert rows["endo-flow"].command()[1:] == ["--ros-args", "-p", camera,
                                               "-p", "newest_frame:=false"]
    assert "newest_frame" not in rows["endo-photometric-correction"].parameters


def test_sfs_workers_are_rows_of_their_own(tmp_path: Path) -> None:
    settings = GraphSettings(node_parameters={"endo-sfs": {"threads": "1"}}, sfs_workers=2)
    processes = _table(tmp_path, settings)
    rows = {p.name: p for p in processes}
    workers = [rows["endo-sfs"], rows["endo-sfs-1"]]
    assert [p.name for p in processes].index("endo-sfs-1") == 3  # beside worker 0
    for index, worker in enumerate(workers):
        assert worker.parameters["worker_count"] == "2"
        assert worker.parameters["worker_index"] == str(index)
        assert worker.parameters["threads"] == "1"  # the configuration's, on every worker
        assert worker.command()[-2:] == ["-r", f"__node:=sfs_{index}"]
    assert [node_name_of(w) for w in workers] == ["sfs_0", "sfs_1"]
    # one depth topic: recorded once, every frame expected once
    recorder = rows[RECORDER]
    assert recorder.subscribes.count(topics.DEPTH_RELATIVE) == 1
    # the replay waits for both workers' camera_info subscriptions
    assert f"{topics.CAMERA_INFO}=4" in rows[PLAYER].command()
    # the other rows are one worker's table
    single = {p.name: p for p in _table(tmp_path)}
    assert set(rows) - set(single) == {"endo-sfs-1"}
    assert "worker_count" not in single["endo-sfs"].parameters
    with pytest.raises(GraphError):
        _table(tmp_path, GraphSettings(sfs_workers=0))
    # the sampler tells the two processes of one executable apart by their command lines
    sampler = ProcessSampler(processes)
    python = sys.executable
    assert sampler.row_of([python, *workers[1].command()]) == "endo-sfs-1"
    assert sampler.row_of([python, *workers[0].command()]) == "endo-sfs"
    assert sampler.row_of([python, *rows["endo-flow"].command()]) == "endo-flow"
    assert sampler.row_of([python, "/usr/bin/other"]) is None


def test_figures_of_a_known_run(tmp_path: Path) -> None:
    processes = _table(tmp_path)
    monitor = GraphMonitor(processes, {"ROS_DOMAIN_ID": "67"})
    assert monitor.watched_topics()[0] == topics.IMAGE_RAW
    assert [node_name_of(p) for p in processes[1:5]] == [
        "photometric_correction", "sfs", "tracker_bridge", "flow"]
    times = monitor.arrivals.times
    frames = 30
    _fill_known_run(times, frames)
    monitor.arrivals.status = {
        "sfs: image input": {"hardware_id": "/sfs", "received": "60", "processed": "20",
                             f"received.{topics.IMAGE_CORRECTED}": "30",
                             "skipped": "10", "dropped": "0", "lost": "0"},
        "photometric_correction: image input": {"hardware_id": "/photometric_correction",
                                                "skipped": "0", "dropped": "0", "lost": "0"},
    }
    figures = graph_figures(processes, monitor, None)
    assert figures.frames_played == frames
    assert figures.window_s == pytest.approx(frames * PERIOD_NS / 1e9)
    correction = figures.stage("endo-photometric-correction")
    assert (correction.frames_in, correction.frames_out, correction.skipped) == (30, 30, 0)
    assert correction.latency_ms == (pytest.approx(10.0), pytest.approx(10.0))
    sfs = figures.stage("endo-sfs")
    assert (sfs.input_topic, sfs.frames_in, sfs.received, sfs.frames_out, sfs.skipped) == (
        topics.IMAGE_CORRECTED, 30, 30, 20, 10)
    assert sfs.rate_hz == pytest.approx(20 / figures.window_s)
    assert sfs.latency_ms[0] == pytest.approx(40.0)
    flow = figures.stage("endo-flow")
    assert (flow.input_topic, flow.output_topic, flow.frames_out) == (
        topics.DEPTH_RELATIVE, topics.SCALE, 20)
    assert flow.skipped is None  # no /diagnostics from flow: unknown, not zero
    bridge = figures.stage("endo-tracker-bridge")  # pose stamps are not the images'
    assert bridge.output_topic == topics.CAMERA_POSE and math.isnan(bridge.latency_ms[0])
    # clouds of frames 6..29 without the skipped ones: 16, at 70 + k ms
    clouds = [70.0 + k for k in range(6, frames) if k % 3 != 2]
    assert figures.end_to_end_frames == len(clouds) == 16
    assert figures.end_to_end_ms[0] == pytest.approx((86.0 + 88.0) / 2)  # the middle two
    assert not figures.every_frame_kept
    costs = dataclasses.replace(figures, processes=[ProcessFigures("endo-sfs", 50.0, 300.0, 0.8),
                                                    ProcessFigures("endo-replay", 5.0, 90.0, 0.3)])
    assert costs.cpu_ms_per_frame("endo-sfs") == pytest.approx(800.0 / 20)  # per depth out
    assert costs.cpu_ms_per_frame("endo-replay") == pytest.approx(300.0 / 30)  # per frame played
    assert math.isnan(costs.cpu_ms_per_frame("endo-flow"))  # not sampled
    # the monitor matched the player late and missed its first 3 images: the counts played say
    for k in range(3):
        del times[topics.IMAGE_RAW][STAMP0 + k * PERIOD_NS]
    late = graph_figures(processes, monitor, None, {topics.IMAGE_RAW: frames,
                                                    topics.TRACKER_POSE: 61})
    assert late.stage("endo-tracker-bridge").frames_in == 61  # a played topic not watched
    assert late.frames_played == frames
    assert late.stage("endo-photometric-correction").frames_in == frames
    assert late.window_s == pytest.approx(figures.window_s)
    document = figures.document()
    assert document["end_to_end_ms"] == list(figures.end_to_end_ms)
    assert document["stages"][1]["skipped"] == 10
    text = "\n".join(stage_lines(figures))
    assert "p50 87 ms, p99 98 ms over 16 clouds of 30 frames" in text
    assert any(line.split()[:7] == ["endo-sfs", topics.DEPTH_RELATIVE, "30", "30", "20", "10",
                                    "0"]
               for line in stage_lines(figures))


def _fill_known_run(times: dict, frames: int) -> None:
    """The run of test_figures_of_a_known_run: topic -> stamp -> (source, reception) ns."""
    for k in range(frames):
        stamp, sent = STAMP0 + k * PERIOD_NS, T0 + k * PERIOD_NS
        times[topics.IMAGE_RAW][stamp] = (sent, sent + 1 * MS)
        times[topics.IMAGE_CORRECTED][stamp] = (sent + 9 * MS, sent + 10 * MS)
        if k % 3 == 2:
            continue  # sfs skipped every third frame
        times[topics.DEPTH_RELATIVE][stamp] = (sent + 39 * MS, sent + 40 * MS)
        times[topics.SCALE][stamp] = (sent + 59 * MS, sent + 60 * MS)
        if k >= 6:  # clouds once the scale converged
            times[CLOUD_TOPIC][stamp] = (sent + 69 * MS, sent + 70 * MS + k * MS)


def test_figures_timed_from_the_recording_equal_the_listeners(tmp_path: Path) -> None:
    from geometry_msgs.msg import Vector3Stamped
    from sensor_msgs.msg import Image, PointCloud2

    from endo_io.bag import BagWriter
    from endo_io.stamp import ns_to_stamp

    processes = _table(tmp_path)
    listener = GraphMonitor(processes, {"ROS_DOMAIN_ID": "67"})
    frames = 30
    _fill_known_run(listener.arrivals.times, frames)
    expected = graph_figures(processes, listener, None)
    # the same run as the recorder saw it: each output's log time is its reception,
    # and the monitor received only the camera_info, published 0.2 ms after its image
    monitor = GraphMonitor(processes, {"ROS_DOMAIN_ID": "67"}, listen="recording")
    assert monitor.watched_topics() == [topics.CAMERA_INFO]
    assert GraphMonitor.played_listeners(processes, "recording") == {topics.CAMERA_INFO: 1}
    assert GraphMonitor.played_listeners(processes) == {topics.IMAGE_RAW: 1,
                                                       topics.CAMERA_INFO: 1}
    kinds = {topics.IMAGE_CORRECTED: Image, topics.DEPTH_RELATIVE: Image,
             topics.SCALE: Vector3Stamped, CLOUD_TOPIC: PointCloud2}
    written = sorted((reception, topic, stamp)
                     for topic, kind in kinds.items()
                     for stamp, (_, reception) in listener.arrivals.times[topic].items())
    with BagWriter(tmp_path / "graph.mcap") as bag:
        for reception, topic, stamp in written:
            message = kinds[topic]()
            message.header.stamp = ns_to_stamp(stamp)
            bag.write_message(topic, message, reception)
            if topic == topics.IMAGE_CORRECTED:  # a second copy of a stamp: the first counts
                bag.write_message(topic, message, reception + 50 * MS)
    for stamp, (sent, reception) in listener.arrivals.times[topics.IMAGE_RAW].items():
        monitor.arrivals.times[topics.CAMERA_INFO][stamp] = (sent + MS // 5, reception)
    assert recorded_arrivals(tmp_path / "graph.mcap", [topics.SCALE, "/absent"]) == {
        topics.SCALE: {stamp: (reception, reception) for stamp, (_, reception)
                       in listener.arrivals.times[topics.SCALE].items()}}
    with pytest.raises(GraphMonitorError, match="needs the run's recording"):
        graph_figures(processes, monitor, None)
    figures = graph_figures(processes, monitor, None, {topics.IMAGE_RAW: frames},
                            tmp_path / "graph.mcap")
    assert figures.timing == "recording" and expected.timing == "topics"
    assert figures.frames_played == frames
    assert figures.window_s == pytest.approx(expected.window_s)
    for got, want in zip(figures.stages, expected.stages, strict=True):
        assert (got.stage, got.frames_in, got.frames_out) == (want.stage, want.frames_in,
                                                              want.frames_out)
        for a, b in zip(got.latency_ms, want.latency_ms, strict=True):
            assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b - 0.2)
    assert figures.end_to_end_frames == expected.end_to_end_frames == 16
    assert figures.end_to_end_ms[0] == pytest.approx(expected.end_to_end_ms[0] - 0.2)
    assert "-> /endoscope/points at the recorder" in "\n".join(stage_lines(figures))
    with pytest.raises(GraphMonitorError, match="listen must be one of"):
        GraphMonitor(processes, {}, listen="images")


def test_cpu_and_memory_of_children_come_from_proc() -> None:
    # The child says when its interpreter is up: read before that, /proc shows the
    # forked copy of this process or a half-loaded executable, not the child's RSS.
    child = subprocess.Popen(
        [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(30)"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        import os

        assert child.stdout is not None and child.stdout.readline() == "up\n"

        assert child.pid in _children(os.getpid())
        usage = _cpu_and_rss(child.pid)
        assert usage is not None and usage[0] >= 0.0 and 1.0 < usage[1] < 500.0
        sampler = ProcessSampler([], period_s=0.05)
        assert sampler._name(child.pid) is None  # not a row of the table: not sampled
    finally:
        child.kill()
        child.wait()
    assert _cpu_and_rss(child.pid) is None


def test_missing_truth_frames_are_a_shortfall_when_stages_skipped(tmp_path: Path) -> None:
    from endo_bringup.demo import GraphReport
    from endo_bringup.graph import GraphRun, OfflineStep

    processes = _table(tmp_path)
    step = OfflineStep(["endo-calibrate"], 0, "", tmp_path / "p.yaml", 1.0)
    run = GraphRun(tmp_path / "graph.mcap", {topics.IMAGE_RAW: 90, topics.CAMERA_INFO: 90,
                                             topics.TRACKER_POSE: 180},
                   {p.name: 0 for p in processes}, tmp_path, 10.0, processes)
    counts = {t: 5 for p in processes for t in p.publishes}
    report = GraphReport(calibrate=step, handeye=step, scores=None, run=run, counts=counts)
    truth = "no depth frame has a ground truth with the same stamp"
    assert truth in report.failures()  # nothing skipped: a broken wire
    stage = StageFigures("endo-sfs", topics.IMAGE_CORRECTED, topics.DEPTH_RELATIVE, 90, 90, 30,
                         60, 0, 0, 10.0, (1.0, 2.0))
    report.figures = GraphFigures(3.0, 90, [stage], (1.0, 2.0), 3, [], 1.0)
    assert truth not in report.failures()  # the SFS node skipped them: slower than the play
    assert any(p.startswith(truth + " (the stages skipped") for p in report.shortfalls())


def test_the_profile_variables_are_put_back_after_the_run(tmp_path: Path, monkeypatch) -> None:
    from endo_bringup.dds_profile import PROFILE_VARIABLES

    for name in PROFILE_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    profile = tmp_path / "profile.xml"
    env = {"ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "42"),
           PROFILE_VARIABLES[0]: str(profile)}
    with GraphMonitor(_table(tmp_path), env):
        assert os.environ[PROFILE_VARIABLES[0]] == str(profile)
    # a later graph or test in this process must not inherit this run's file
    assert not any(name in os.environ for name in PROFILE_VARIABLES)
