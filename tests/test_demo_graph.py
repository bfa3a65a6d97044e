"""The demo's graph part end to end: the sample bags through the endo3d graph over DDS.

``endo_bringup.demo.run_graph_stage`` runs ``endo-calibrate`` and
``endo-handeye`` on the gray-card and hand–eye bags, then
``endo-photometric-correction``, ``endo-sfs``, ``endo-tracker-bridge``,
``endo-flow`` and ``endo-record`` as separate processes while ``endo-replay``
plays the phantom bag into them, and scores the recording against the bag's
ground truth (``endo_process.accuracy.score_recording``).

The bounds here are smoke bounds (measured value plus a wide margin, so that
a broken wire fails and ordinary variation does not); the accuracy targets
of each step live in its own package's tests (endo_calib acceptance,
endo_tracker_bridge hand–eye bag test, endo_sfs and tests/test_phantom_sfs.py).
Measured on 2026-11-22 (2-core AMD EPYC): inverse response 0.93 % of full
scale, hand–eye 0.16 mm / 0.03°, median-scaled AbsRel 0.077–0.083 on the three
depth frames with ground truth, camera position error median 0.35 mm and max
0.92 mm, rotation max 0.16°. The flow outputs (2026-12-01, same machine,
loaded by other sessions; full resolution, SFS kept 33/90 frames): final
scale −4.5 % from the oracle, metric depth MAE 8.4 mm and cloud RMS 4.6 mm on
the one truth frame after convergence (endo-process on all frames: −4.1 %,
cloud 3.1 mm). These are smoke bounds too; the demo itself judges issue 11's
bars (endo_bringup.acceptance), which this run does not meet.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from endo_bringup.demo import SAMPLE_BAGS, run_graph_stage
from endo_io import topics

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

BAGS = Path(__file__).resolve().parents[1] / "bags"
#: The stages run with newest_frame off here.
IN_ORDER = ("endo-photometric-correction", "endo-sfs", "endo-flow")

#: Smoke bound on the median-scaled AbsRel of depth_relative (measured ≤ 0.083).
ABS_REL_BOUND = 0.2
#: Bound on the camera position error, mm (measured max 0.92 mm).
POSITION_BOUND_MM = 2.0
#: Bound on the camera rotation error, degrees (measured max 0.16°).
ROTATION_BOUND_DEG = 0.5
#: Bound on |final scale / oracle − 1| (measured 4.5 %).
FINAL_SCALE_BOUND = 0.15
#: Bounds on metric depth MAE and cloud-to-truth RMS, metres (measured 8.4 mm, 4.6 mm).
METRIC_MAE_BOUND_M = 0.015
CLOUD_RMS_BOUND_M = 0.01


@pytest.mark.skipif(
    not all((BAGS / name).exists() for name in SAMPLE_BAGS), reason="sample bags not in bags/"
)
def test_graph_on_the_sample_bags(tmp_path: Path) -> None:
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    assert "ROS_DOMAIN_ID" in env, "run with the test's own ROS_DOMAIN_ID"

    # Every frame in order (no newest-frame skips): a loaded machine delays the frames (up to
    # the 8-deep input queues) instead of skipping the three with ground truth.
    in_order = {name: {"newest_frame": "false"} for name in IN_ORDER}
    # 0.5x, not the demo's 0.25x: at solve_scale 0.5 and in order the rate only sets the time
    report = run_graph_stage(BAGS, tmp_path, env, rate=0.5, solve_scale=0.5,
                             node_parameters=in_order)

    assert report.failures() == []
    # offline calibrations, against the simulator's truth
    scores = report.scores
    assert scores is not None
    assert scores.inverse_response_max_error < 0.02
    assert scores.handeye_translation_mm < 1.0
    assert scores.handeye_rotation_deg < 0.5
    assert abs(scores.time_offset_error_ms) < 2.0

    # every process ended by itself on SIGINT, and every stage produced frames
    run = report.run
    assert run is not None
    assert all(code == 0 for code in run.return_codes.values()), run.return_codes
    counts = report.counts
    played_images = run.played[topics.IMAGE_RAW]
    assert counts[topics.TRUE_CAMERA_POSE] == run.played[topics.TRUE_CAMERA_POSE]
    assert counts[topics.TRUE_DEPTH] == run.played[topics.TRUE_DEPTH]
    # the recorder's subscription is reliable: every corrected frame arrives
    assert counts[topics.IMAGE_CORRECTED] >= 0.9 * played_images
    # the SFS node may skip frames when the machine is busy, but not all
    assert counts[topics.DEPTH_RELATIVE] > 0
    assert counts[topics.CAMERA_POSE] > 0
    # camera_info is recorded beside the images; flow gives one scale per frame it gets
    assert counts[topics.CAMERA_INFO] == run.played[topics.CAMERA_INFO]
    # measured 52 of 67 (a run of 15 consecutive frames lost in flow on a loaded
    # machine: the demo prints it as a shortfall); a smoke bound here
    assert 0.5 * counts[topics.DEPTH_RELATIVE] <= counts[topics.SCALE]
    assert counts[topics.SCALE] <= counts[topics.DEPTH_RELATIVE]
    assert 0 < counts[topics.DEPTH] <= counts[topics.SCALE]
    assert counts[topics.POINTS] > 0 and counts[topics.MAP] > 0

    # the printed figures are timed from this recording (the monitor received no image):
    # the same frames, the latency of each frame's publish at the replay to the recorder
    figures = report.figures
    assert figures is not None and figures.timing == "recording"
    assert figures.frames_played == played_images
    assert figures.stage("endo-photometric-correction").frames_out == counts[
        topics.IMAGE_CORRECTED]
    assert figures.stage("endo-sfs").frames_out == counts[topics.DEPTH_RELATIVE]
    assert figures.stage("endo-flow").frames_out == counts[topics.SCALE]
    assert figures.end_to_end_frames == counts[topics.POINTS]
    correction_p50, end_to_end_p50 = (figures.stage("endo-photometric-correction").latency_ms[0],
                                      figures.end_to_end_ms[0])
    assert 0.0 < correction_p50 < end_to_end_p50

    # relative depth, scale recovered per frame by the median ratio
    assert report.depth_errors, "no depth frame had a ground truth with its stamp"
    for error in report.depth_errors.values():
        assert error.abs_rel < ABS_REL_BOUND
        assert error.coverage > 0.5  # measured 0.84–0.98 (saturated highlights are NaN)

    # /endoscope/pose against /ground_truth/camera_pose at the image stamps
    poses = report.poses
    assert poses is not None
    assert poses.compared >= 0.8 * run.played[topics.TRUE_CAMERA_POSE]
    assert float(np.max(poses.position_mm)) < POSITION_BOUND_MM
    assert float(np.max(poses.rotation_deg)) < ROTATION_BOUND_DEG

    # flow: the scale against the oracle, metric depth and cloud against the truth
    accuracy = report.accuracy
    assert accuracy is not None
    assert 0.005 < accuracy.oracle_scale < 0.05
    assert accuracy.scale is not None
    error = accuracy.scale.relative_error
    assert abs(error[np.isfinite(error)][-1]) < FINAL_SCALE_BOUND
    # the truth frames after the scale converged (none when SFS dropped them)
    assert all(e.mae < METRIC_MAE_BOUND_M for e in accuracy.metric.values())
    # every truth frame with a metric depth has its cloud scored too (session 13's review:
    # the live cloud went unscored and this line held over an empty dict)
    assert accuracy.cloud_rms_m.keys() == accuracy.metric.keys()
    assert all(rms < CLOUD_RMS_BOUND_M for rms in accuracy.cloud_rms_m.values())
