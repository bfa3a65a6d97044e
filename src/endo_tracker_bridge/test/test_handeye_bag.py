"""Acceptance: endo-handeye on the simulator's hand–eye bag, against its ground truth.

The bag (``bags/handeye.mcap``, written by ``endo-sim render handeye``) holds
rendered checkerboard images, camera_info and tracker poses with 0.25 mm /
0.1° RMS noise, dropouts and a latency; ``handeye.ground_truth.yaml`` beside
it holds the true T_marker_camera and latency. Done means: translation error
≤ 1 mm, rotation error ≤ 0.5°, time-offset error ≤ 2 ms, residuals reported.

``ENDO_HANDEYE_BAG`` points the test at another bag with its ground truth.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from endo_tracker_bridge.handeye_cli import main
from endo_tracker_bridge.handeye_file import HandEyeCalibration

REPO = Path(__file__).resolve().parents[3]
BAG = Path(os.environ.get("ENDO_HANDEYE_BAG", REPO / "bags" / "handeye.mcap"))
TRUTH = BAG.with_name(BAG.stem + ".ground_truth.yaml")


@pytest.mark.skipif(not BAG.exists(), reason=f"{BAG} not found (endo-sim render handeye writes it)")
def test_handeye_on_the_simulated_bag(tmp_path, capsys):
    truth = yaml.safe_load(TRUTH.read_text())
    tracker = truth["tracker"]
    board = truth["scene"]["checkerboard"]
    columns, rows = board["inner_corners"]
    output = tmp_path / "handeye.yaml"
    output.write_text("# a previous calibration\n")  # replaced: --overwrite
    arguments = [str(BAG), "-o", str(output), "--board", f"{columns}x{rows}"]
    arguments += ["--square-mm", str(board["square_m"] * 1e3), "--pose-unit", tracker["units"]]
    arguments += ["--max-views", "300", "--overwrite"]
    assert main(arguments) == 0
    print(capsys.readouterr().out)

    calibration = HandEyeCalibration.load(output)
    X_true = np.asarray(tracker["T_marker_camera"], dtype=np.float64)
    delta = np.linalg.inv(X_true) @ calibration.T_marker_camera
    translation_error_mm = 1e3 * float(np.linalg.norm(delta[:3, 3]))
    rotation_error_deg = math.degrees(Rotation.from_matrix(delta[:3, :3]).magnitude())
    offset_error_ms = (calibration.time_offset_ns * 1e-9 - tracker["latency_s"]) * 1e3
    print(
        f"hand-eye error {translation_error_mm:.3f} mm, {rotation_error_deg:.3f} deg; "
        f"time offset error {offset_error_ms:+.3f} ms; residuals {calibration.residuals}"
    )
    assert translation_error_mm <= 1.0
    assert rotation_error_deg <= 0.5
    assert abs(offset_error_ms) <= 2.0

    # residuals are reported and agree with the simulated tracker's noise
    residuals = calibration.residuals
    noise_mm = tracker["position_noise_rms_m"] * 1e3
    assert 0.3 * noise_mm < residuals["translation_rms_mm"] < 2.0 * noise_mm
    assert 0.3 * tracker["rotation_noise_rms_deg"] < residuals["rotation_rms_deg"]
    assert residuals["rotation_rms_deg"] < 2.0 * tracker["rotation_noise_rms_deg"]
    assert math.isfinite(residuals["reprojection_rms_px"])
    assert set(calibration.details["closed_form"]) == {"tsai", "park", "daniilidis"}
    assert calibration.views_used >= 20


@pytest.mark.skipif(not BAG.exists(), reason=f"{BAG} not found (endo-sim render handeye writes it)")
def test_an_existing_output_is_refused_without_overwrite(tmp_path, capsys):
    # -o used to replace whatever it named, after the whole calibration: the user's
    # previous hand-eye file, or, misnamed, their photometric calibration.
    output = tmp_path / "handeye.yaml"
    output.write_text("# the user's calibration\n")
    assert main([str(BAG), "-o", str(output), "--board", "8x5"]) == 2
    error = capsys.readouterr().err.strip()
    assert error == f"endo-handeye: OutputExistsError: {output} exists; --overwrite replaces it"
    assert output.read_text() == "# the user's calibration\n"


@pytest.mark.skipif(not BAG.exists(), reason=f"{BAG} not found (endo-sim render handeye writes it)")
def test_an_image_topic_of_another_type_is_one_line_and_exit_2(tmp_path, capsys):
    # It used to end in an AttributeError traceback ('PoseStamped' object has no attribute
    # 'encoding'): a bag whose image topic is a driver's pose topic, say.
    from endo_io.bag import BagReader, BagWriter

    retyped = tmp_path / "retyped.mcap"
    with BagReader(BAG) as reader, BagWriter(retyped) as writer:
        pose_type = reader.topics["/tracker/pose"].msgtype
        for name, info in reader.topics.items():
            writer.add_topic(name, pose_type if name == "/endoscope/image_raw" else info.msgtype)
        poses = [m.data for m in reader.messages(topics=["/tracker/pose"])][:3]
        for message in reader.messages(topics=["/endoscope/camera_info", "/tracker/pose"]):
            writer.write(message.topic, message.data, message.log_time_ns)
            if len(poses) and message.topic == "/endoscope/camera_info":
                writer.write("/endoscope/image_raw", poses.pop(), message.log_time_ns)
    output = tmp_path / "handeye.yaml"
    assert main([str(retyped), "-o", str(output)]) == 2
    error = capsys.readouterr().err.strip()
    assert error == (
        f"endo-handeye: TopicTypeError: {retyped}: /endoscope/image_raw holds "
        "geometry_msgs/msg/PoseStamped, not sensor_msgs/msg/Image"
    )
    assert not output.exists()


@pytest.mark.skipif(not BAG.exists(), reason=f"{BAG} not found (endo-sim render handeye writes it)")
def test_tracker_samples_without_a_pose_are_left_out_and_counted(tmp_path, capsys):
    # A tracker reports NaN while the tool is out of view: one such sample used to end the
    # calibration with "PoseError: pose position is not finite" and exit 2.
    from endo_io.bag import BagReader, BagWriter, deserialize, serialize

    spoilt_bag = tmp_path / "nan_poses.mcap"
    spoilt = 0
    with BagReader(BAG) as reader, BagWriter(spoilt_bag) as writer:
        for name, info in reader.topics.items():
            writer.add_topic(name, info.msgtype)
        seen = 0
        for message in reader.messages():
            data = message.data
            if message.topic == "/tracker/pose":
                seen += 1
                if seen % 50 == 0:
                    pose = deserialize(message)
                    pose.pose.position.x = pose.pose.orientation.w = math.nan
                    data, spoilt = serialize(pose), spoilt + 1
            writer.write(message.topic, data, message.log_time_ns)
    truth = yaml.safe_load(TRUTH.read_text())
    board = truth["scene"]["checkerboard"]
    output = tmp_path / "handeye.yaml"
    arguments = [str(spoilt_bag), "-o", str(output), "--board", "x".join(
        str(n) for n in board["inner_corners"]), "--square-mm", str(board["square_m"] * 1e3),
        "--pose-unit", truth["tracker"]["units"], "--max-views", "300"]  # fmt: skip
    assert main(arguments) == 0
    error = capsys.readouterr().err.strip()
    assert error.startswith(
        f"endo-handeye: warning: left out {spoilt} tracker samples that give no pose; the "
        "first: PoseError: "
    ), error
    assert len(error.splitlines()) == 1 and spoilt >= 30
    delta = np.linalg.inv(np.asarray(truth["tracker"]["T_marker_camera"])) @ (
        HandEyeCalibration.load(output).T_marker_camera
    )
    assert 1e3 * float(np.linalg.norm(delta[:3, 3])) <= 1.0
    assert math.degrees(Rotation.from_matrix(delta[:3, :3]).magnitude()) <= 0.5
