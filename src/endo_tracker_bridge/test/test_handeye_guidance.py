"""endo-handeye that guides: board size detection, square size from the tracker, report, provenance.

* ``endo-handeye bags/handeye.mcap -o handeye.yaml`` with no other flag
  detects the 8×5 board, estimates its 4 mm squares from the tracker and
  calibrates within the acceptance bars of test_handeye_bag.py (1 mm, 0.5°,
  2 ms) against the bag's ground truth; the YAML records where it came from.
* a wrong ``--board`` stops with one line naming the board to pass.
* the report figure's content, on the synthetic recording with outliers.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from endo_io.pose import rigid_transform
from endo_tracker_bridge.handeye import calibrate_hand_eye
from endo_tracker_bridge.handeye_cli import main
from endo_tracker_bridge.handeye_file import HandEyeCalibration
from endo_tracker_bridge.handeye_report import handeye_figure
from endo_tracker_bridge.synthetic import BOARD, CAMERA, synthetic_recording

REPO = Path(__file__).resolve().parents[3]
BAG = REPO / "bags" / "handeye.mcap"
TRUTH = BAG.with_name("handeye.ground_truth.yaml")
needs_bag = pytest.mark.skipif(not BAG.exists(), reason=f"{BAG} not found")


@needs_bag
def test_the_sample_command_needs_no_board_flags(tmp_path, capsys, caplog):
    output, report = tmp_path / "handeye.yaml", tmp_path / "handeye.png"
    assert main([str(BAG), "-o", str(output), "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "board: 8x5 inner corners (detected)" in printed
    truth = yaml.safe_load(TRUTH.read_text())
    tracker = truth["tracker"]
    with caplog.at_level(logging.INFO, logger="endo_tracker_bridge.handeye_file"):
        calibration = HandEyeCalibration.load(output)
    delta = np.linalg.inv(np.asarray(tracker["T_marker_camera"])) @ calibration.T_marker_camera
    translation_mm = 1e3 * float(np.linalg.norm(delta[:3, 3]))
    rotation_deg = math.degrees(Rotation.from_matrix(delta[:3, :3]).magnitude())
    offset_ms = (calibration.time_offset_ns * 1e-9 - tracker["latency_s"]) * 1e3
    board = calibration.provenance["board"]
    square_error = board["square_mm"] / (truth["scene"]["checkerboard"]["square_m"] * 1e3) - 1
    print(f"no flags: {translation_mm:.3f} mm, {rotation_deg:.3f} deg, offset {offset_ms:+.3f} ms, "
          f"square {board['square_mm']:.3f} mm ({100 * square_error:+.2f} %)")
    assert translation_mm <= 1.0 and rotation_deg <= 0.5 and abs(offset_ms) <= 2.0
    assert abs(square_error) <= 0.02
    assert board["inner_corners"] == "8x5" and board["size_source"] == "detected"
    assert board["square_source"].startswith("estimated")
    # provenance: the bag, its topics, camera_info, the run
    data = BAG.read_bytes()
    source = calibration.provenance["input"]
    assert source["file"] == "handeye.mcap" and source["size_bytes"] == len(data)
    assert source["sha256"] == hashlib.sha256(data).hexdigest()
    assert calibration.provenance["topics"]["pose"] == "/tracker/pose"
    assert calibration.provenance["camera_info"]["width"] == 640
    assert calibration.provenance["tool"]["command_line"].startswith("endo-handeye ")
    assert "from handeye.mcap" in caplog.text
    # round trip
    calibration.save(tmp_path / "again.yaml")
    assert HandEyeCalibration.load(tmp_path / "again.yaml").provenance == calibration.provenance
    import cv2

    image = cv2.imread(str(report))
    assert image is not None and image.shape[1] >= 1200 and image.std() > 10


@needs_bag
def test_a_wrong_board_names_the_one_to_pass(tmp_path, capsys):
    output = tmp_path / "handeye.yaml"
    assert main([str(BAG), "-o", str(output), "--board", "9x6", "--square-mm", "4"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1
    assert "board 9x6 is not found" in error[0] and "pass --board 8x5" in error[0]
    assert not output.exists()


def test_old_handeye_files_still_load(tmp_path, caplog):
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump({"T_marker_camera": np.eye(4).tolist(), "time_offset_s": 0.01}))
    with caplog.at_level(logging.INFO, logger="endo_tracker_bridge.handeye_file"):
        calibration = HandEyeCalibration.load(path)
    assert calibration.provenance == {} and calibration.time_offset_ns == 10_000_000
    assert "no provenance recorded" in caplog.text


def test_report_content():
    views, stamps, poses = synthetic_recording(seed=2, duration_s=6.0)
    views = views[::2]
    bad = [3, 11]
    for k in bad:
        wrong = views[k].T_camera_target @ rigid_transform([0.0, 0.0, 0.2], [0.004, -0.003, 0.0])
        views[k] = type(views[k])(views[k].stamp_ns, views[k].corners, wrong, 0.1)
    result = calibrate_hand_eye(views, stamps, poses, BOARD, CAMERA)
    assert not result.view_used[bad].any()
    figure = handeye_figure(result, {"board": {"inner_corners": "9x6", "square_mm": 5.0}})
    axes = {ax.get_label(): ax for ax in figure.axes}
    # per-view residuals: every view plotted, the rejected ones marked
    marks = [line for line in axes["views"].lines if line.get_marker() in ("o", "x")]
    assert sum(len(line.get_xdata()) for line in marks) == len(views)
    rejected = len(views) - result.views_used  # the 2 outliers and views without tracker poses
    assert sum("rejected" in t.get_text() for t in axes["views"].texts) == rejected
    assert axes["views"].get_ylim()[0] == 0.0
    # residual distribution of the used views' corners
    counts = sum(patch.get_height() for patch in axes["distribution"].patches)
    assert counts == result.views_used * BOARD.columns * BOARD.rows
    # the offset search curve with its minimum
    curve = axes["offset"].lines[0]
    np.testing.assert_allclose(curve.get_xdata(), result.coarse_offsets_ms)
    chosen = [line for line in axes["offset"].lines if "chosen offset" in line.get_label()]
    assert chosen and chosen[0].get_xdata()[0] == pytest.approx(result.time_offset_ns / 1e6)
    for name in ("views", "distribution", "tracker", "offset"):
        assert axes[name].get_legend() is not None
    text = "\n".join(t.get_text() for t in axes["text"].texts)
    for field in ("board: 9x6", "views used", "time offset", "reprojection RMS",
                  f"rejected views ({len(views) - result.views_used})"):
        assert field in text, field
    import matplotlib.pyplot as plt

    plt.close(figure)
