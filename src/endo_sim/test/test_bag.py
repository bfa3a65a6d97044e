"""Bags: topics, types, encodings, frames, ground-truth files, determinism, CLI."""

from __future__ import annotations

import filecmp
from pathlib import Path

import numpy as np
import pytest
import yaml

from endo_io.bag import BagReader, deserialize
from endo_io.image import image_to_array
from endo_io.pose import pose_to_matrix
from endo_io.stamp import stamp_to_ns
from endo_sim.bagout import write_bag
from endo_sim.cli import main
from endo_sim.photometry import Photometry
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.tracker import TrackerModel

SMALL = {"width": 96, "height": 72, "fps": 10.0, "seed": 3}
EXPECTED_TYPES = {
    "/endoscope/image_raw": "sensor_msgs/msg/Image",
    "/endoscope/camera_info": "sensor_msgs/msg/CameraInfo",
    "/ground_truth/depth": "sensor_msgs/msg/Image",
    "/ground_truth/camera_pose": "geometry_msgs/msg/PoseStamped",
    "/tracker/pose": "geometry_msgs/msg/PoseStamped",
}


def read_all(path: Path) -> tuple[dict, dict[str, list]]:
    with BagReader(path) as bag:
        topics = {name: info.msgtype for name, info in bag.topics.items()}
        messages: dict[str, list] = {name: [] for name in topics}
        last = -1
        for m in bag.messages():
            assert m.log_time_ns >= last  # log-time order
            last = m.log_time_ns
            messages[m.topic].append((m.log_time_ns, deserialize(m)))
    return topics, messages


def test_colon_bag_topics_types_frames_and_ground_truth(tmp_path: Path) -> None:
    config = SimulationConfig(
        scene="colon", duration_s=0.5, depth_every=2, tracker=TrackerModel(units="mm"), **SMALL
    )
    summary = write_bag(build_sequence(config), tmp_path / "run.mcap")
    topics, messages = read_all(summary.bag_path)
    assert topics == EXPECTED_TYPES
    assert len(messages["/endoscope/image_raw"]) == 5
    assert len(messages["/ground_truth/depth"]) == 3
    for log_time, image in messages["/endoscope/image_raw"]:
        assert image.encoding == "mono8" and image.header.frame_id == "endoscope_optical_frame"
        assert stamp_to_ns(image.header.stamp) == log_time
        assert (image.width, image.height) == (96, 72)
    for _, depth in messages["/ground_truth/depth"]:
        assert depth.encoding == "32FC1" and depth.header.frame_id == "endoscope_optical_frame"
        d = image_to_array(depth)
        assert np.isnan(d[0, 0]) and np.all((d[np.isfinite(d)] > 0.005) & (d[np.isfinite(d)] < 0.5))
    info = messages["/endoscope/camera_info"][0][1]
    assert info.header.frame_id == "endoscope_optical_frame" and info.width == 96
    poses = [pose_to_matrix(m)[0] for _, m in messages["/ground_truth/camera_pose"]]
    assert all(m.header.frame_id == "world" for _, m in messages["/ground_truth/camera_pose"])
    trackers = messages["/tracker/pose"]
    assert 20 <= len(trackers) <= 30 and all(m.header.frame_id == "tracker" for _, m in trackers)
    # Tracker positions are in millimetres: the marker sits ~1 m from the tracker.
    distance = np.linalg.norm(pose_to_matrix(trackers[0][1])[0][:3, 3])
    assert 500.0 < distance < 2000.0
    truth = yaml.safe_load((tmp_path / "run.ground_truth.yaml").read_text())
    assert truth["tracker"]["units"] == "mm" and truth["tracker"]["latency_s"] == 0.025
    assert len(truth["tracker"]["T_marker_camera"]) == 4
    # The stored camera pose is the one the trajectory gives.
    sequence = build_sequence(config)
    np.testing.assert_allclose(
        poses[2], sequence.trajectory.pose_at(int(sequence.frame_times_ns[2])), atol=1e-9
    )
    lut = np.load(tmp_path / "run.inverse_response.npy")
    assert lut.shape == (256,) and lut[-1] == pytest.approx(1.0)
    assert np.load(tmp_path / "run.light_map.npy").shape == (72, 96)
    assert (tmp_path / "run.camera.yaml").exists()


def test_same_seed_same_bytes(tmp_path: Path) -> None:
    config = SimulationConfig(scene="abdomen", duration_s=0.3, **SMALL)
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        write_bag(build_sequence(config), tmp_path / name / "run.mcap")
    for suffix in (
        ".mcap",
        ".ground_truth.yaml",
        ".camera.yaml",
        ".inverse_response.npy",
        ".light_map.npy",
    ):
        assert filecmp.cmp(
            tmp_path / "a" / f"run{suffix}", tmp_path / "b" / f"run{suffix}", shallow=False
        )
    other = SimulationConfig(scene="abdomen", duration_s=0.3, **{**SMALL, "seed": 4})
    write_bag(build_sequence(other), tmp_path / "c.mcap")
    assert not filecmp.cmp(tmp_path / "a" / "run.mcap", tmp_path / "c.mcap", shallow=False)


def test_graycard_bag_levels_and_12_bit(tmp_path: Path) -> None:
    config = SimulationConfig(
        scene="graycard", frames_per_level=2, photometry=Photometry(bit_depth=12), **SMALL
    )
    summary = write_bag(build_sequence(config), tmp_path / "gray.mcap")
    topics, messages = read_all(summary.bag_path)
    assert topics["/calibration/gray_level"] == "std_msgs/msg/Float32"
    levels = [m.data for _, m in messages["/calibration/gray_level"]]
    np.testing.assert_allclose(levels, np.repeat([0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8], 2), atol=1e-7)
    images = [image_to_array(m) for _, m in messages["/endoscope/image_raw"]]
    assert messages["/endoscope/image_raw"][0][1].encoding == "mono16"
    assert max(int(i.max()) for i in images) <= 4095
    centre = [float(i[30:42, 42:54].mean()) for i in images]
    assert all(b > a for a, b in zip(centre[::2], centre[2::2], strict=False))  # brighter cards
    depth = image_to_array(messages["/ground_truth/depth"][0][1])
    assert depth[36, 48] == pytest.approx(0.0265, abs=1e-6)


def test_cli_render_rgb_and_refuses_to_overwrite(tmp_path: Path, capsys) -> None:
    out = tmp_path / "hand.mcap"
    args = [
        "render",
        "handeye",
        "-o",
        str(out),
        "--width",
        "160",
        "--height",
        "120",
        "--fps",
        "1",
        "--stations",
        "3",
        "--color",
        "--seed",
        "2",
    ]
    assert main(args) == 0
    _topics, messages = read_all(out)
    assert messages["/endoscope/image_raw"][0][1].encoding == "rgb8"
    truth = yaml.safe_load((tmp_path / "hand.ground_truth.yaml").read_text())
    assert truth["scene"]["checkerboard"]["inner_corners"] == [8, 5]
    assert len(truth["scene"]["stations"]["T_world_camera"]) == 3
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err
    assert main([*args, "--overwrite"]) == 0


def test_render_on_a_full_disk_keeps_what_was_written_and_exits_1(tmp_path: Path) -> None:
    # It was exit 2 with one BagError line, no counts and no ground truth. A
    # file size limit stands in for a full disk (EFBIG as ENOSPC).
    import re
    import resource
    import signal
    import subprocess
    import sys

    limit = 3_000_000  # about half the bag: chunks of 1 MiB

    def limited() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = tmp_path / "colon.mcap"
    argv = ["render", "colon", "-o", str(out), "--width", "160", "--height", "120",
            "--duration", "2", "--compression", "none", "-q"]  # fmt: skip
    done = subprocess.run([str(Path(sys.executable).parent / "endo-sim"), *argv],
                          capture_output=True, text=True, timeout=300, preexec_fn=limited,
                          check=False)  # fmt: skip
    assert done.returncode == 1, done.stderr
    errors = done.stderr.strip().splitlines()
    assert len(errors) == 1 and re.fullmatch(
        rf"endo-sim: error: writing stopped after \d+ of 60 frames: {re.escape(str(out))}: "
        r"cannot write \(file size limit: File too large\); the bag holds the \d+ messages "
        r"written before, \d+ not yet on disk are lost", errors[0]
    ), errors
    said = dict(re.findall(r"^  (/\S+): (\d+) messages$", done.stdout, re.M))
    from endo_io.bag import BagCorruptError

    held: dict[str, int] = {}
    with BagReader(out) as reader:  # the counts printed are what the file holds
        try:
            for message in reader.messages():
                held[message.topic] = held.get(message.topic, 0) + 1
        except BagCorruptError:  # raised after the last intact message: the cut
            pass
    assert {t: int(n) for t, n in said.items() if int(n)} == held and held
    truth = yaml.safe_load((tmp_path / "colon.ground_truth.yaml").read_text())
    assert truth is not None


def test_render_to_a_name_without_mcap_makes_a_rosbag2_directory(tmp_path: Path) -> None:
    # -o NAME made "the bag must end in .mcap"; endo-process and endo-record made a
    # rosbag2 directory NAME/ (NAME_0.mcap, metadata.yaml), as `ros2 bag record -o NAME`.
    from endo_sim.ground_truth import ground_truth_of

    out = tmp_path / "colon"
    args = ["render", "colon", "-o", str(out), "--width", "160", "--height", "120",
            "--duration", "1", "-q"]  # fmt: skip
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["colon_0.mcap", "metadata.yaml"]
    with BagReader(out) as reader:
        assert reader.topics["/endoscope/image_raw"].message_count == 30
    truth = ground_truth_of(out)
    assert truth["bag"] == "colon" and (tmp_path / "colon.camera.yaml").is_file()
    # an existing directory is never replaced, --overwrite or not
    assert main([*args, "--overwrite"]) == 2
    assert sorted(p.name for p in out.iterdir()) == ["colon_0.mcap", "metadata.yaml"]
