"""``endo-launch``: the whole graph as separate processes, as a user starts it.

On a small simulated colon bag (160×120, 15 fps, 3 s, rendered here) with the
simulator's true photometric and hand–eye calibrations in a copy of
config/endo3d.yaml:

* ``endo-launch replay BAG --record OUT`` runs every node, plays the bag once
  SFS has its kernels, records every node output and ends by itself: every
  frame gives a corrected image, a relative depth and a scale, every tracker
  sample a camera and a marker pose, and flow's metric depth and clouds are
  there once its scale converged;
* ``--respawn``: ``kill -9`` of the SFS node is reported with its exit code,
  the node comes back and the graph gives depth again; SIGTERM to the launcher
  stops every child and finalises the recording;
* a node that cannot start (a parameter out of range in the file) is reported
  with its exit code and its own error line, and the launcher exits 1;
* the command lines: the parameter file goes to every node, ``--namespace``
  and ``--remap`` move every graph topic, the source and the recorder too.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from endo_bringup.launcher import build_parser, plan_launch
from endo_calib.calibration import ChannelCalibration, PhotometricCalibration
from endo_calib.response import InverseResponse
from endo_io import topics
from endo_io.bag import BagReader
from endo_io.bag.streams import count_messages
from endo_io.stamp import NS_PER_S
from endo_sim.bagout import write_bag
from endo_sim.ground_truth import ground_truth_of
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_tracker_bridge.handeye_file import HandEyeCalibration

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = str(Path(sys.executable).parent / "endo-launch")
FPS, DURATION_S = 15.0, 3.0


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(a 160×120 colon bag, a parameter file with its true calibrations)."""
    out = tmp_path_factory.mktemp("launch_bag")
    sequence = build_sequence(SimulationConfig(
        scene="colon", width=160, height=120, fps=FPS, duration_s=DURATION_S, seed=11,
        depth_every=1000, start_ns=1_800_000_000 * NS_PER_S,
    ))  # fmt: skip
    bag = write_bag(sequence, out / "colon.mcap").bag_path
    light = np.load(out / "colon.light_map.npy")
    fov = light > 0
    lut = np.load(out / "colon.inverse_response.npy")
    channel = ChannelCalibration("mono", InverseResponse(lut, 8), np.where(fov, light, 0.0), None)
    calibration = PhotometricCalibration([channel], fov, None, "pixels").save(
        out / "photometric.yaml"
    )
    tracker = ground_truth_of(bag)["tracker"]
    handeye = out / "handeye.yaml"
    HandEyeCalibration(
        T_marker_camera=np.asarray(tracker["T_marker_camera"], dtype=float),
        time_offset_ns=round(float(tracker["latency_s"]) * NS_PER_S),
    ).save(handeye)
    T_world_tracker = np.linalg.inv(np.asarray(tracker["T_tracker_world"], dtype=float))
    params = yaml.safe_load((ROOT / "config" / "endo3d.yaml").read_text())
    params["/**/photometric_correction"]["ros__parameters"]["calibration_file"] = str(calibration)
    bridge = params["/**/tracker_bridge"]["ros__parameters"]
    bridge["handeye_file"] = str(handeye)
    bridge["T_world_tracker"] = [float(v) for v in T_world_tracker.ravel()]
    params["/**/sfs"]["ros__parameters"]["threads"] = 1
    params["/**/flow"]["ros__parameters"]["tracking_downsample"] = 1
    for section in params.values():  # every frame, in order: the counts below are exact
        section["ros__parameters"]["newest_frame"] = False
    path = out / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return bag, path


class Launcher:
    """An ``endo-launch`` child whose output is collected line by line."""

    def __init__(self, argv: list[str]) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.process = subprocess.Popen(
            [LAUNCH, *argv], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        return "\n".join(self.lines)

    def wait_for(self, pattern: str, timeout_s: float, start: int = 0) -> int:
        """Index of the first line from ``start`` on matching ``pattern``."""
        deadline = time.monotonic() + timeout_s
        regex = re.compile(pattern)
        while time.monotonic() < deadline:
            for index in range(start, len(self.lines)):
                if regex.search(self.lines[index]):
                    return index
            if self.process.poll() is not None:
                self._reader.join(2.0)
            time.sleep(0.1)
        raise AssertionError(f"no line matching {pattern!r} in {timeout_s:g} s:\n{self.output}")

    def finish(self, timeout_s: float) -> int:
        try:
            code = self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            raise AssertionError(f"endo-launch did not end:\n{self.output}") from None
        self._reader.join(5.0)
        return code

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()


def _children(pid: int) -> dict[str, int]:
    """Executable name -> pid of the direct children of ``pid``."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid and len(cmdline) > 1:
            found[Path(cmdline[1].decode()).name] = int(entry.name)
    return found


def test_the_command_lines_carry_the_params_file_namespace_and_remaps(small_bag, tmp_path):
    bag, params = small_bag
    options = build_parser().parse_args([
        "replay", str(bag), "--params", str(params), "--namespace", "rig1",
        "--remap", "/endoscope/image_raw:=/camera/image_raw", "--record", str(tmp_path / "o.mcap"),
        "--rate", "0.5", "--loop",
    ])  # fmt: skip
    plan = plan_launch(options)
    assert [n.node_name for n in plan.nodes] == [
        "photometric_correction", "sfs", "tracker_bridge", "flow"
    ]
    for node in plan.nodes:
        argv = node.command()
        assert argv[argv.index("--params-file") + 1] == str(params.resolve())
        assert node.remaps["__ns"] == "/rig1"
        for topic in node.subscribes + node.publishes:
            assert topic.startswith("/rig1/") or topic == "/camera/image_raw", topic
    correction = plan.nodes[0]
    assert correction.remaps[topics.IMAGE_RAW] == "/camera/image_raw"
    assert correction.remaps[topics.IMAGE_CORRECTED] == "/rig1" + topics.IMAGE_CORRECTED
    assert plan.source is not None
    source = plan.source.command()
    assert source[1:3] == [str(bag), "--topics"]
    for flag in ("--clock", "--loop", "--wait-topics"):
        assert flag in source
    assert source[source.index("--rate") + 1] == "0.5"
    assert f"{topics.IMAGE_RAW}:=/camera/image_raw" in source
    assert f"{topics.TRACKER_POSE}:=/rig1{topics.TRACKER_POSE}" in source
    assert plan.recorder is not None
    recorded = set(plan.recorder.subscribes)
    assert {"/rig1" + t for t in (topics.DEPTH_RELATIVE, topics.SCALE, topics.POINTS,
                                  topics.CAMERA_POSE, topics.CAMERA_INFO)} <= recorded
    assert topics.TRUE_DEPTH in recorded  # the ground truth, played unchanged


def test_calibration_handeye_and_param_flags_override_the_file_for_their_node(
    small_bag, tmp_path
):
    bag, params = small_bag
    photometric = bag.parent / "photometric.yaml"  # loaded by the launcher's check
    options = build_parser().parse_args([
        "replay", str(bag), "--params", str(params), "--calibration", str(photometric),
        "--param", "sfs.solve_scale:=0.5", "--param", "flow.max_tracks:=50",
    ])  # fmt: skip
    plan = plan_launch(options)
    commands = {n.node_name: n.command() for n in plan.nodes}
    correction = commands["photometric_correction"]
    # the file first, the overrides after it (later wins in rcl)
    assert correction.index("--params-file") < correction.index(
        f"calibration_file:={photometric.resolve()}"
    )
    assert "solve_scale:=0.5" in commands["sfs"] and "max_tracks:=50" in commands["flow"]
    assert plan.warnings == []  # the file names the hand-eye file
    bare = plan_launch(build_parser().parse_args(["live"]))
    assert [w.split(":")[0] for w in bare.warnings] == [
        "no calibration_file for endo-photometric-correction",
        "no handeye_file for endo-tracker-bridge",
    ]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["live", "--param", "nosuchnode.x:=1"])


@pytest.mark.ros
def test_replay_with_record_runs_the_whole_graph_and_records_every_output(small_bag, tmp_path):
    bag, params = small_bag
    out = tmp_path / "out.mcap"
    launcher = Launcher(["replay", str(bag), "--params", str(params), "--record", str(out),
                         "--rate", "0.25", "--log-dir", str(tmp_path / "logs")])  # fmt: skip
    try:
        code = launcher.finish(180)
    finally:
        launcher.kill()
    assert code == 0, launcher.output
    # every node's lines, prefixed with its name
    for name in ("endo-photometric-correction", "endo-sfs", "endo-tracker-bridge", "endo-flow"):
        assert re.search(rf"^\[{name}\s*\] .*DDS: domain", launcher.output, re.M), name
    up = launcher.output.index("every node is up")
    assert launcher.output.index("kernels ready") < up
    with BagReader(bag) as reader:
        frames = reader.topics[topics.IMAGE_RAW].message_count
        poses = reader.topics[topics.TRACKER_POSE].message_count
    counts = count_messages(out)
    assert counts[topics.CAMERA_INFO] == frames, counts  # played into the recorder
    # the launcher's own count of each output at the end (issue 13: exit 1 when one is empty)
    assert f"outputs ({frames} frames played):" in launcher.output
    assert f"endo-sfs {topics.DEPTH_RELATIVE}: {counts[topics.DEPTH_RELATIVE]} from" in (
        launcher.output
    )
    # One output per input of each node. A node starved of CPU on a loaded
    # machine loses an input frame now and then on its best-effort (sensor
    # data) subscription and says so ("lost in transport"); that is the node's
    # input QoS, not the launch, so 90 % is required here. Flow also drops the
    # frames that fall in the simulated tracker's dropouts (no pose to scale
    # them with; measured 37-41 of 45 at 0.5x and load ~30): 75 %. Played at 0.25x: a
    # starved node has twice the time per frame.
    for topic, inputs, share in ((topics.IMAGE_CORRECTED, frames, 0.9),
                                 (topics.DEPTH_RELATIVE, frames, 0.9),
                                 (topics.SCALE, frames, 0.75), (topics.CAMERA_POSE, poses, 0.9),
                                 (topics.MARKER_POSE, poses, 0.9)):  # fmt: skip
        assert share * inputs <= counts[topic] <= inputs, (topic, counts)
    for topic in (topics.DEPTH, topics.POINTS, topics.MAP):
        assert counts[topic] > 0, (topic, counts)


@pytest.mark.ros
def test_respawn_brings_a_killed_node_back_and_sigterm_stops_everything(small_bag, tmp_path):
    bag, params = small_bag
    out = tmp_path / "loop.mcap"
    launcher = Launcher(["replay", str(bag), "--params", str(params), "--record", str(out),
                         "--loop", "--respawn", "--log-dir", str(tmp_path / "logs")])  # fmt: skip
    try:
        launcher.wait_for("every node is up", 120)
        deadline = time.monotonic() + 60
        while count_messages(out, partial=True)[topics.DEPTH_RELATIVE] < 5:
            assert time.monotonic() < deadline, launcher.output
            time.sleep(0.5)
        children = _children(launcher.process.pid)
        os.kill(children["endo-sfs"], signal.SIGKILL)
        died = launcher.wait_for(r"endo-sfs exited with code -9", 30)
        restarted = launcher.wait_for(r"restarting endo-sfs \(restart 1\)", 30, died)
        launcher.wait_for(r"^\[endo-sfs\s*\] .*kernels ready", 60, restarted)
        before = count_messages(out, partial=True)[topics.DEPTH_RELATIVE]
        deadline = time.monotonic() + 60
        while count_messages(out, partial=True)[topics.DEPTH_RELATIVE] < before + 10:
            assert time.monotonic() < deadline, launcher.output
            time.sleep(0.5)
        survivors = _children(launcher.process.pid)
        assert survivors["endo-sfs"] != children["endo-sfs"]
        for name in ("endo-photometric-correction", "endo-flow", "endo-tracker-bridge"):
            assert survivors[name] == children[name], name  # the others were not restarted
        launcher.process.send_signal(signal.SIGTERM)
        assert launcher.finish(60) == 0, launcher.output
    finally:
        launcher.kill()
    assert "SIGTERM: stopping the graph" in launcher.output
    for pid in survivors.values():
        assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text()
    counts = count_messages(out)  # finalised: readable without partial
    assert counts[topics.DEPTH_RELATIVE] >= before + 10


@pytest.mark.ros
def test_a_node_that_cannot_start_is_reported_and_stops_the_launch(small_bag, tmp_path):
    _, params = small_bag
    document = yaml.safe_load(params.read_text())
    # A value out of range is refused by endo-launch before any start
    # (test_launch_guards.py); a warm-up camera file only the node reads is not.
    document["/**/sfs"]["ros__parameters"]["warm_up_camera_file"] = str(params)
    broken = tmp_path / "broken.yaml"
    broken.write_text(yaml.safe_dump(document))
    launcher = Launcher(["live", "--params", str(broken), "--log-dir", str(tmp_path / "logs")])
    try:
        code = launcher.finish(120)
    finally:
        launcher.kill()
    assert code == 1, launcher.output
    assert "endo-sfs exited with code 2" in launcher.output
    assert "warm_up_camera_file" in launcher.output.split("endo-sfs exited with code 2", 1)[1]
