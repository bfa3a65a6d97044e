"""The graph's table of processes: command lines, expected counts, stage report, round trip."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

from endo_bringup.demo import compare_bags, playable_topics, run_round_trip, write_synthetic_bag
from endo_bringup.graph import (
    PLAYER,
    RECORDER,
    RECORDER_NICENESS,
    GraphRun,
    GraphSettings,
    describe_graph,
    expected_counts,
    graph_processes,
    node_outputs,
    stage_counts,
)
from endo_io import topics

PLAYED = [topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE, topics.TRUE_DEPTH]


def _table(tmp_path: Path):
    settings = GraphSettings(rate=0.5, roughness=0.3, solve_scale=1.0)
    settings.T_world_tracker[:3, 3] = [1.0, 2.0, 3.0]
    return graph_processes(
        tmp_path / "phantom.mcap",
        PLAYED,
        tmp_path / "photometric.yaml",
        tmp_path / "handeye.yaml",
        tmp_path / "graph.mcap",
        settings,
    )


def test_command_lines_come_from_the_table(tmp_path: Path) -> None:
    processes = _table(tmp_path)
    names = [p.name for p in processes]
    nodes = ["endo-photometric-correction", "endo-sfs", "endo-tracker-bridge", "endo-flow"]
    assert names == [RECORDER, *nodes, PLAYER]
    commands = {p.name: p.command() for p in processes}
    assert Path(commands["endo-sfs"][0]).name == "endo-sfs"
    sfs = commands["endo-sfs"][1:]
    assert sfs[0] == "--ros-args"
    assert sfs[1:7] == ["-p", "model:=near_light", "-p", "roughness:=0.3", "-p", "solve_scale:=1.0"]
    # sfs and flow warm up on the bag's camera (written beside the recording by the run)
    camera = f"warm_up_camera_file:={tmp_path / 'camera.yaml'}"
    assert sfs[7:9] == ["-p", camera]
    # the nodes take every topic by its absolute name (endo_io.topics): no remaps
    assert sfs[9:] == []
    assert not any("-r" in p.command() for p in processes)
    bridge = commands["endo-tracker-bridge"]
    # the bridge listens on the driver's /tracker/pose by default: no ros_topic, no remap
    assert not any(a.startswith(("ros_topic:=", "/tracker")) for a in bridge)
    assert "T_world_tracker:=[1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0, " in (
        " ".join(bridge)
    )
    # the player plays the bag's topics as they are
    player = commands[PLAYER][1:]
    assert player[:6] == [str(tmp_path / "phantom.mcap"), "--topics", *PLAYED]
    # it plays once every subscription of each played topic matched: the correction's of the
    # images; sfs's, flow's and the recorder's of camera_info; the bridge's; the recorder's
    assert player[6:] == ["--rate", "0.5", "--wait-topics", f"{topics.IMAGE_RAW}=1",
                          f"{topics.CAMERA_INFO}=3", f"{topics.TRACKER_POSE}=1",
                          f"{topics.TRUE_DEPTH}=1", "--wait-timeout", "30.0"]
    # the recorder keeps what the nodes publish and the ground truth; no --ros-args
    outputs = [topics.IMAGE_CORRECTED, topics.DEPTH_RELATIVE, topics.CAMERA_POSE]
    outputs += [topics.MARKER_POSE, topics.SCALE, topics.DEPTH, topics.POINTS, topics.MAP]
    assert node_outputs(processes) == outputs
    # the flow node takes every topic by its absolute name: its one parameter is the camera
    assert commands["endo-flow"][1:] == ["--ros-args", "-p", camera]
    recorder = commands[RECORDER][1:]
    assert recorder == [
        "--topics", *outputs, topics.CAMERA_INFO, topics.TRUE_DEPTH, topics.TRUE_CAMERA_POSE,
        "-o", str(tmp_path / "graph.mcap"),
        "--flush-period", "0.2", "--compression", "lz4", "--writer-nice", "0",
    ]  # fmt: skip
    # the recorder yields the CPU to the frames' path; every other process runs as its parent
    assert {p.name: p.nice for p in processes} == {
        RECORDER: RECORDER_NICENESS, **{name: 0 for name in [*nodes, PLAYER]}}
    text = describe_graph(processes)
    assert len(text.splitlines()) == 1 + len(processes)
    bridge_row = rf"^endo-tracker-bridge +{topics.TRACKER_POSE} +{topics.CAMERA_POSE}, "
    assert re.search(bridge_row + topics.MARKER_POSE + "$", text, re.M)


def test_expected_counts_and_stage_report(tmp_path: Path) -> None:
    processes = _table(tmp_path)
    played = {topics.IMAGE_RAW: 90, topics.CAMERA_INFO: 90, topics.TRACKER_POSE: 170}
    played[topics.TRUE_DEPTH] = 3
    expected = expected_counts(processes, played)
    assert expected[topics.IMAGE_CORRECTED] == expected[topics.DEPTH_RELATIVE] == 90
    assert expected[topics.CAMERA_POSE] == expected[topics.MARKER_POSE] == 170
    assert expected[topics.TRACKER_POSE] == 170 and expected[topics.TRUE_DEPTH] == 3
    # flow: one scale per relative depth; depth, cloud and map are not per frame
    assert expected[topics.SCALE] == 90
    assert all(t not in expected for t in (topics.DEPTH, topics.POINTS, topics.MAP))

    run = GraphRun(
        recording=tmp_path / "graph.mcap",
        played=played,
        return_codes={p.name: 0 for p in processes} | {"endo-sfs": None},
        log_dir=tmp_path,
        seconds=1.0,
        processes=processes,
    )
    recorded = {topics.IMAGE_CORRECTED: 88, topics.DEPTH_RELATIVE: 40, topics.CAMERA_POSE: 169}
    recorded |= {topics.TRUE_DEPTH: 3, topics.MARKER_POSE: 170, topics.CAMERA_INFO: 90}
    recorded |= {topics.SCALE: 39, topics.DEPTH: 30, topics.POINTS: 29, topics.MAP: 4}
    rows = {(r.stage, r.topic): r for r in stage_counts(run, recorded)}
    assert list(rows) == [
        ("endo-photometric-correction", topics.IMAGE_CORRECTED),
        ("endo-sfs", topics.DEPTH_RELATIVE),
        ("endo-tracker-bridge", topics.CAMERA_POSE),
        ("endo-tracker-bridge", topics.MARKER_POSE),
        ("endo-flow", topics.SCALE),
        ("endo-flow", topics.DEPTH),
        ("endo-flow", topics.POINTS),
        ("endo-flow", topics.MAP),
        (PLAYER, topics.CAMERA_INFO),
        (PLAYER, topics.TRUE_DEPTH),
    ]
    correction = rows["endo-photometric-correction", topics.IMAGE_CORRECTED]
    assert (correction.count_in, correction.count_out) == (90, 88)
    sfs = rows["endo-sfs", topics.DEPTH_RELATIVE]
    # the SFS node's input is recorded: what reached the recorder, not what was played
    assert (sfs.count_in, sfs.count_out, sfs.return_code) == (88, 40, None)
    bridge = rows["endo-tracker-bridge", topics.CAMERA_POSE]
    assert (bridge.count_in, bridge.count_out) == (170, 169)
    # the flow node's input is the recorded relative depth
    flow = rows["endo-flow", topics.SCALE]
    assert (flow.count_in, flow.count_out) == (40, 39)
    assert rows["endo-flow", topics.DEPTH].count_out == 30
    truth = rows[PLAYER, topics.TRUE_DEPTH]
    assert (truth.count_in, truth.count_out) == (3, 3)


@pytest.mark.ros
def test_round_trip_through_the_process_group(tmp_path: Path) -> None:
    env = dict(os.environ)
    assert "ROS_DOMAIN_ID" in env, "run with the test's own ROS_DOMAIN_ID"
    bag = tmp_path / "in.mcap"
    write_synthetic_bag(bag, seconds=1.0)
    output = tmp_path / "out.mcap"
    replay_rc, record_rc, logs = run_round_trip(bag, output, 4.0, env)
    assert (replay_rc, record_rc) == (0, 0), logs
    result = compare_bags(bag, output, playable_topics(bag)[0])
    assert result.equal
    assert {name: t.received for name, t in result.topics.items()} == {
        topics.CAMERA_INFO: 30,
        topics.IMAGE_RAW: 30,
        "/light/level": 10,
        "/tool/pose": 60,
    }
    assert "subscribed to /tool/pose" in (tmp_path / "logs/round_trip/endo-record.log").read_text()
    assert np.all([t.sent_bytes > 0 for t in result.topics.values()])


def test_the_recorders_own_loss_line_is_read_from_its_log(tmp_path):
    # a run's counts come from the recording: what the recorder could not write must be
    # named as its loss, not a stage's (the line is endo_io.record's own summary)
    from endo_bringup.graph import RECORDER, recorder_lost
    from endo_io.record import RecordedTopic, RecordReport

    report = RecordReport(topics={"/a": RecordedTopic("std_msgs/msg/String", messages=7,
                                                      received=10)},
                          write_error="3 refused: the write queue held 512 MB (--buffer-mb)")
    (tmp_path / f"{RECORDER}.log").write_text(
        "endo-record: wrote x.mcap\n" + "\n".join(report.summary_lines()) + "\n")
    assert recorder_lost(tmp_path) == (
        "lost: 3 of 10 received messages are not in the file "
        "(3 refused: the write queue held 512 MB (--buffer-mb))")
    (tmp_path / f"{RECORDER}.log").write_text("\n".join(RecordReport().summary_lines()))
    assert recorder_lost(tmp_path) == ""
    assert recorder_lost(tmp_path / "missing") == ""


def test_the_printed_stage_table_does_not_call_in_minus_out_dropped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The demo printed 'dropped 34' for SFS and, 12 lines below, 'skipped 34 dropped 0'.

    The first table's column is in − out (stale frames skipped and messages
    dropped alike); "dropped" is the nodes' own count of bad input.
    """
    from endo_bringup.demo import GraphReport, print_graph_report
    from endo_bringup.graph import OfflineStep

    processes = _table(tmp_path)
    played = {topics.IMAGE_RAW: 90, topics.CAMERA_INFO: 90, topics.TRACKER_POSE: 170,
              topics.TRUE_DEPTH: 3}  # fmt: skip
    run = GraphRun(recording=tmp_path / "graph.mcap", played=played,
                   return_codes={p.name: 0 for p in processes}, log_dir=tmp_path, seconds=1.0,
                   processes=processes)  # fmt: skip
    step = OfflineStep(["endo-calibrate"], 0, "", tmp_path / "x.yaml", 1.0)
    counts = {topics.IMAGE_CORRECTED: 90, topics.DEPTH_RELATIVE: 55, topics.CAMERA_INFO: 90}
    print_graph_report(GraphReport(step, step, None, run, counts=counts), 0.5)
    lines = capsys.readouterr().out.splitlines()
    (header,) = [line for line in lines if "output topic" in line]
    assert header.split() == ["stage", "output", "topic", "in", "out", "in-out", "exit"]
    (sfs,) = [line for line in lines if line.split()[:2] == ["endo-sfs", topics.DEPTH_RELATIVE]]
    assert sfs.split()[2:5] == ["90", "55", "35"]
    # pip-only the recording has no /tf: the hint says what the viewer can and cannot place
    hint = [line for line in lines if "no /tf" in line]
    assert len(hint) == 1 and "offline.mcap) carry /tf" in hint[0]
    print_graph_report(GraphReport(step, step, None, run, counts=counts | {topics.TF: 89}), 0.5)
    assert "no /tf" not in capsys.readouterr().out
