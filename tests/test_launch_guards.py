"""``endo-launch``'s guards, found by a new user's probe (issue 13): each small and fast.

* a second graph in the same ROS domain is refused before anything starts
  (exit 2, one line naming what runs there and the domain);
* ``kill -9`` of the launcher takes its children with it (PR_SET_PDEATHSIG),
  for a bare :class:`ProcessGroup` and for ``endo-launch`` itself;
* a replay's source waits only for the topics a node reads (not ``/clock``);
* bad source arguments (``--rate 0``, an unknown scene) are refused before
  anything starts, also under ``--dry-run``; so are the nodes' parameters
  and calibration files (checked as the nodes check them at start);
* a replay with ``--record`` ends with each node output's count against what
  came in (the demo's stage counts), and an output that got nothing is a
  warning and a failed run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from endo_bringup.graph import PLAYED_TOPICS
from endo_bringup.launcher import build_parser, output_counts, plan_launch
from endo_io import topics
from endo_io.bag import BagReader, BagWriter

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "bags" / "phantom_colon.mcap"
LAUNCH = str(Path(sys.executable).parent / "endo-launch")
REPLAY = str(Path(sys.executable).parent / "endo-replay")
RECORD = str(Path(sys.executable).parent / "endo-record")


def _launch(*argv: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([LAUNCH, *argv], capture_output=True, text=True, timeout=timeout_s)


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while (alive := [p for p in pids if _alive(p)]) and time.monotonic() < deadline:
        time.sleep(0.1)
    return alive


# ---------------------------------------------------------------- bad arguments


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["replay", str(BAG), "--rate", "0"], "--rate must be > 0, got 0.0"),
        (["replay", str(BAG), "--rate", "nan"], "--rate must be > 0, got nan"),
        (["sim", "nosuchscene"], "invalid choice: 'nosuchscene'"),
        (["sim", "--sim-arg=--fps=abc"], "--fps"),
    ],
)
def test_bad_source_arguments_are_refused_before_anything_starts(
    argv: list[str], says: str, tmp_path: Path
) -> None:
    for extra in (["--dry-run"], ["--log-dir", str(tmp_path / "logs")]):
        done = _launch(*argv, *extra)
        assert done.returncode == 2, (done.stdout, done.stderr)
        assert done.stdout == ""  # no command line printed, nothing started
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and says in lines[0], done.stderr
        assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize(
    ("files", "argv", "says"),
    [
        ({"p.yaml": "a: [1, 2\n"}, ["--params", "p.yaml"],
         "endo-photometric-correction: cannot start with these ROS arguments: failed to "
         "initialize rcl: Couldn't parse params file"),
        ({"p.yaml": "/**/sfs:\n  ros__parameters: {solve_scale: 0}\n"}, ["--params", "p.yaml"],
         "endo-sfs: parameter solve_scale: 0 is out of range [0.1, 1]"),
        ({"p.yaml": "sfs:\n  ros__parameters: {solve_scal: 0.5}\n"}, ["--params", "p.yaml"],
         "endo-sfs: parameter solve_scal: sfs has no such parameter (did you mean solve_scale?)"),
        ({}, ["--param", "sfs.solve_scale:=0"],
         "endo-sfs: parameter solve_scale: 0 is out of range [0.1, 1]"),
        ({}, ["--param", "flow.map_every:=x"],
         "endo-flow: parameter map_every: expected an integer"),
        ({"c.yaml": "format: nothing\n"}, ["--calibration", "c.yaml"],
         "endo-photometric-correction: "),  # + "<path> is not an endo3d photometric calibration"
        ({"h.yaml": "a: 1\n"}, ["--handeye", "h.yaml"], "endo-tracker-bridge: "),
        ({"p.yaml": "/**/photometric_correction:\n"
                    "  ros__parameters: {calibration_file: /no/c.yaml}\n"},
         ["--params", "p.yaml"],
         "endo-photometric-correction: calibration file /no/c.yaml not found"),
    ],
)
def test_the_nodes_configuration_is_checked_before_anything_starts(
    files: dict[str, str], argv: list[str], says: str, tmp_path: Path
) -> None:
    # --dry-run printed the command lines for each of these (and a parameter file
    # that does not parse was a yaml traceback); the real start found them only
    # once the nodes had started (a node exiting 2, the launch stopped), a
    # calibration that does not load not at all (the correction node runs on,
    # dropping every frame).
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    argv = [str(tmp_path / a) if a in files else a for a in argv]
    for extra in (["--dry-run"], ["--log-dir", str(tmp_path / "logs")]):
        done = _launch("live", *argv, *extra)
        assert done.returncode == 2, (done.stdout, done.stderr)
        assert done.stdout == ""  # no command line printed, nothing started
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("endo-launch: LaunchError: " + says), lines
        for name in ("c.yaml", "h.yaml"):
            if name in files:  # the node's own loader's line, naming the file
                assert str(tmp_path / name) in lines[0], lines
        assert not (tmp_path / "logs").exists()


# ---------------------------------------------------------------- the source waits for nodes


def test_the_replay_waits_for_the_nodes_inputs_only(tmp_path: Path) -> None:
    plan = plan_launch(build_parser().parse_args(["replay", str(BAG), "--namespace", "rig"]))
    assert plan.source is not None
    argv = list(plan.source.arguments)
    waited = argv[argv.index("--wait-topics") + 1 : argv.index("--wait-timeout")]
    # bag topics (the source remaps them itself), every one a node reads, with the number of
    # subscriptions to match (correction; sfs and flow; the bridge); no truth, no /clock
    assert waited == [f"{topics.IMAGE_RAW}=1", f"{topics.CAMERA_INFO}=2",
                      f"{topics.TRACKER_POSE}=1"]
    read = [t for node in plan.nodes for t in node.subscribes]
    for item in waited:
        topic, count = item.split("=")
        assert read.count("/rig" + topic) == int(count)
    # recorded: the recorder's subscriptions count too, the truth it records among them
    plan = plan_launch(build_parser().parse_args(
        ["replay", str(BAG), "--record", str(tmp_path / "o.mcap")]))
    assert plan.source is not None
    argv = list(plan.source.arguments)
    waited = argv[argv.index("--wait-topics") + 1 : argv.index("--wait-timeout")]
    assert f"{topics.CAMERA_INFO}=3" in waited and f"{topics.TRUE_DEPTH}=1" in waited


@pytest.mark.ros
def test_endo_replay_plays_without_waiting_for_clock_subscribers(tmp_path: Path) -> None:
    """One subscriber on the image topic, none on /clock: no wait, no warning."""
    recording = tmp_path / "images.mcap"
    recorder = subprocess.Popen([RECORD, "--topics", topics.IMAGE_RAW, "-o", str(recording)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        done = subprocess.run(
            [REPLAY, str(BAG), "--topics", topics.IMAGE_RAW, "--rate", "5", "--clock",
             "--wait-for-subscribers", "1", "--wait-topics", topics.IMAGE_RAW,
             "--wait-timeout", "60"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        recorder.send_signal(signal.SIGINT)
        recorder.wait(30)
    assert done.returncode == 0, done.stderr
    assert "did not reach" not in done.stdout + done.stderr
    with BagReader(recording) as reader:  # it played to the one subscriber that was there
        assert reader.topics[topics.IMAGE_RAW].message_count > 0
    refused = subprocess.run([REPLAY, str(BAG), "--topics", topics.IMAGE_RAW, "--wait-topics",
                              topics.CAMERA_INFO], capture_output=True, text=True)  # fmt: skip
    assert refused.returncode == 2 and "not among --topics" in refused.stderr


@pytest.mark.ros
def test_endo_replay_waits_for_each_topics_count_of_subscribers(tmp_path: Path) -> None:
    """TOPIC=N: N subscriptions of that topic; one recorder of two waited for is a warning."""
    recording = tmp_path / "images.mcap"
    recorder = subprocess.Popen([RECORD, "--topics", topics.IMAGE_RAW, "-o", str(recording)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip

    def replay(count: int) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [REPLAY, str(BAG), "--topics", topics.IMAGE_RAW, topics.CAMERA_INFO, "--rate", "5",
             "--wait-topics", f"{topics.IMAGE_RAW}={count}", "--wait-timeout", "20"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip

    try:
        matched, lacking = replay(1), replay(2)
    finally:
        recorder.send_signal(signal.SIGINT)
        recorder.wait(30)
    assert matched.returncode == 0, matched.stderr
    # one subscriber is there: played at once (camera_info, not listed, is not waited for)
    assert "did not reach" not in matched.stdout + matched.stderr
    assert lacking.returncode == 0, lacking.stderr
    assert f"playing although {topics.IMAGE_RAW} (1 of 2) did not reach" in lacking.stderr
    refused = subprocess.run(
        [REPLAY, str(BAG), "--topics", topics.IMAGE_RAW, "--wait-topics", f"{topics.IMAGE_RAW}=2x"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert refused.returncode == 2 and "expected TOPIC or TOPIC=N" in refused.stderr


# ---------------------------------------------------------------- children die with the parent


def test_a_killed_process_group_owner_takes_its_children_along(tmp_path: Path) -> None:
    owner = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import os, sys, time
            from pathlib import Path
            from endo_bringup.process_group import ProcessGroup
            group = ProcessGroup(dict(os.environ), Path({str(tmp_path)!r}))
            for name in ("a", "b"):
                group.start(name, ["sleep", "600"], new_session=True)
            print(" ".join(str(p.pid) for p in group.processes.values()), flush=True)
            time.sleep(600)
        """)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert owner.stdout is not None
    pids = [int(p) for p in owner.stdout.readline().split()]
    assert len(pids) == 2 and all(_alive(p) for p in pids)
    owner.kill()
    owner.wait()
    assert _wait_gone(pids, 5.0) == []


@pytest.mark.ros
def test_kill_9_of_endo_launch_leaves_no_node_running(tmp_path: Path) -> None:
    launcher = subprocess.Popen([LAUNCH, "live", "--quiet", "--log-dir", str(tmp_path / "logs")],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while len(children := _children(launcher.pid)) < 4:
            assert launcher.poll() is None and time.monotonic() < deadline, children
            time.sleep(0.2)
        launcher.kill()
        launcher.wait()
        assert _wait_gone(children, 10.0) == []
    finally:
        for pid in _children(launcher.pid):
            os.kill(pid, signal.SIGKILL)


# ---------------------------------------------------------------- one graph per domain


@pytest.mark.ros
def test_a_second_graph_in_the_same_domain_is_refused(tmp_path: Path) -> None:
    other = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import rclpy
            from sensor_msgs.msg import Image
            rclpy.init()
            node = rclpy.create_node("sfs")
            node.create_publisher(Image, {topics.DEPTH_RELATIVE!r}, 1)
            print("up", flush=True)
            rclpy.spin(node)
        """)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert other.stdout is not None and other.stdout.readline().strip() == "up"
        done = _launch("live", "--log-dir", str(tmp_path / "logs"))
    finally:
        other.kill()
        other.wait()
    assert done.returncode == 2, (done.stdout, done.stderr)
    line = done.stderr.strip()
    assert len(line.splitlines()) == 1, line
    domain = os.environ.get("ROS_DOMAIN_ID", "0")
    for part in (f"ROS domain {domain}", "/sfs (node)",
                 f"{topics.DEPTH_RELATIVE} (published by /sfs)", "--allow-shared-domain"):
        assert part in line, line
    assert not (tmp_path / "logs").exists()  # nothing was started
    # In another namespace the same node is no conflict: plan only, the probe itself
    from endo_bringup.domain_probe import graph_conflicts

    assert graph_conflicts(["/rig2" + topics.DEPTH_RELATIVE], ["/rig2/sfs"], discovery_s=1.0) == []


def test_a_parameter_file_section_for_no_node_is_named_and_a_misspelt_one_refused(
    tmp_path: Path,
) -> None:
    # rcl ignores both without a word: the graph started with the defaults
    params = tmp_path / "p.yaml"
    params.write_text("/**/sfss:\n  ros__parameters: {solve_scale: 0.5}\n")
    done = _launch("live", "--params", str(params), "--dry-run")
    assert done.returncode == 2 and done.stdout == "", (done.stdout, done.stderr)
    assert done.stderr == (f"endo-launch: LaunchError: --params {params}: section /**/sfss of "
                           "the parameter file applies to no node (did you mean sfs?)\n")
    params.write_text("/rig1/sfs:\n  ros__parameters: {solve_scale: 0.5}\n"
                      "v4l2_camera:\n  ros__parameters: {video_device: /dev/video0}\n")
    done = _launch("live", "--params", str(params), "--calibration", str(tmp_path / "none.yaml"),
                   "--dry-run")  # fmt: skip
    assert done.returncode == 2  # (the calibration is checked after the sections are read)
    done = _launch("live", "--params", str(params), "--dry-run")
    assert done.returncode == 0 and len(done.stdout.splitlines()) == 4, done.stderr
    warned = [line for line in done.stderr.splitlines() if "--params " in line]
    nodes = "/flow, /photometric_correction, /sfs, /tracker_bridge"
    assert warned == [f"endo-launch: warning: --params {params}: section {key} applies to none "
                      f"of the graph's nodes ({nodes}): ignored"
                      for key in ("/rig1/sfs", "v4l2_camera")]  # fmt: skip
    # in the namespace /rig1 the section is the SFS node's
    done = _launch("live", "--params", str(params), "--namespace", "/rig1", "--dry-run")
    assert done.returncode == 0 and "/rig1/sfs applies" not in done.stderr, done.stderr


# ---------------------------------------------------------------- outputs at the end


def _recording(path: Path, counts: dict[str, int]) -> Path:
    with BagWriter(path) as writer:
        for topic, count in counts.items():
            writer.add_topic(topic, "std_msgs/msg/Empty")
            for i in range(count):
                writer.write(topic, b"\x00\x01\x00\x00", 1_000 + i)
    return path


def test_the_end_of_a_replay_counts_each_output_and_names_the_missing_ones(tmp_path: Path) -> None:
    plan = plan_launch(build_parser().parse_args(
        ["replay", str(BAG), "--record", str(tmp_path / "x.mcap")]))  # fmt: skip
    with BagReader(BAG) as reader:
        played = {t: reader.topics[t].message_count for t in PLAYED_TOPICS if t in reader.topics}
    frames, poses = played[topics.IMAGE_RAW], played[topics.TRACKER_POSE]
    # the probe's run: 2 of the frames gave a relative depth, flow gave no metric output
    recorded = {topics.IMAGE_CORRECTED: frames, topics.DEPTH_RELATIVE: 2, topics.SCALE: 2,
                topics.DEPTH: 0, topics.POINTS: 0, topics.MAP: 0,
                topics.CAMERA_POSE: poses, topics.MARKER_POSE: poses}  # fmt: skip
    lines, missing = output_counts(plan, played, _recording(tmp_path / "bad.mcap", recorded))
    assert f"endo-sfs {topics.DEPTH_RELATIVE}: 2 from {frames} in" in lines
    assert f"endo-flow {topics.SCALE}: 2 from 2 in" in lines
    assert missing == [f"endo-flow published nothing on {t} (2 messages in)"
                       for t in (topics.DEPTH, topics.POINTS, topics.MAP)]  # fmt: skip
    recorded.update({topics.DEPTH: 1, topics.POINTS: 1, topics.MAP: 1})
    lines, missing = output_counts(plan, played, _recording(tmp_path / "good.mcap", recorded))
    assert missing == [] and len(lines) == 8
