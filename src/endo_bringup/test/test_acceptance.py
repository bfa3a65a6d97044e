"""The demo's OK: frames kept per stage, and the accuracy bars on a scored recording."""

from __future__ import annotations

import numpy as np
import pytest

from endo_bringup.acceptance import (
    AccuracyBars,
    accuracy_shortfalls,
    converged_scale_error,
    frame_shortfalls,
    metric_oracle_gap,
)
from endo_bringup.graph import StageCount
from endo_io import topics
from endo_process.accuracy import Accuracy, ScaleTrack
from endo_process.evaluation import PoseComparison
from endo_sfs.evaluation import depth_error

T0 = 1_000_000_000_000
FRAME_NS = 33_333_334  # 30 frames: just over 1 s


def _accuracy(scale_error: float, metric_factor: float) -> Accuracy:
    """A colon-like scoring: 90 scale samples, 3 truth frames, poses within 0.5 mm."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.02, 0.08, (3, 40, 50)).astype(np.float32)
    relative = truth * np.float32(1.05) * rng.normal(1.0, 0.05, truth.shape).astype(np.float32)
    stamps = [T0 + k * 30 * FRAME_NS for k in range(3)]
    accuracy = Accuracy(truth_frames=3, oracle_scale=0.02)
    for stamp, t, r in zip(stamps, truth, relative, strict=True):
        oracle = r / np.float32(1.05)
        accuracy.oracle[stamp] = depth_error(oracle, t, scaling="none")
        accuracy.metric[stamp] = depth_error(oracle * np.float32(metric_factor), t, scaling="none")
    scale = np.full(90, 0.02 * (1.0 + scale_error))
    scale[:10] = np.nan  # initialising
    scale[10:20] = 0.03  # far off before convergence: not judged
    accuracy.scale = ScaleTrack(T0 + FRAME_NS * np.arange(90, dtype=np.int64), scale, 0.02)
    accuracy.poses = PoseComparison(89, 1, np.full(89, 0.4), np.full(89, 0.1))
    return accuracy


def test_bars_pass_within_and_fail_outside() -> None:
    good = _accuracy(scale_error=0.015, metric_factor=1.0)
    converged = converged_scale_error(good, AccuracyBars())
    # no true trajectory: samples 10.. are usable; converged from 1 s (30
    # frames) later: 90 − 40 samples
    assert len(converged) == 50
    np.testing.assert_allclose(converged, 0.015)
    metric, oracle, frames = metric_oracle_gap(good)
    assert frames == 3 and metric == oracle
    assert accuracy_shortfalls(good) == []

    bad = _accuracy(scale_error=0.04, metric_factor=1.1)
    problems = accuracy_shortfalls(bad)
    assert len(problems) == 2
    assert problems[0].startswith(
        "scale up to 4.0% from the oracle from 1 s after its first estimate on (bar 2%"
    )
    metric, oracle, _ = metric_oracle_gap(bad)
    assert metric - oracle > 0.05  # 10 % too deep everywhere
    assert problems[1].startswith(f"metric AbsRel {metric:.4f} is ")
    # a looser bar admits both
    assert accuracy_shortfalls(bad, AccuracyBars(0.05, 1.0, 0.2)) == []


def test_missing_outputs_are_named() -> None:
    assert accuracy_shortfalls(Accuracy()) == [
        "the recording has no ground truth to score against"
    ]
    empty = _accuracy(0.0, 1.0)
    empty.metric.clear()
    empty.scale = None
    assert accuracy_shortfalls(empty) == [
        "the scale cannot be judged: no usable scale sample",
        "no metric depth at any ground-truth frame",
    ]


def _moving(accuracy: Accuracy, onset_frame: int) -> Accuracy:
    """``accuracy`` with a true trajectory still until ``onset_frame``, then 0.5 mm a frame."""
    stamps = T0 + FRAME_NS * np.arange(90, dtype=np.int64)
    x = 5e-4 * np.clip(np.arange(90) - (onset_frame - 4), 0, None)  # 2 mm at onset_frame
    accuracy.true_positions = (stamps, np.stack([x, np.zeros(90), np.full(90, 0.1)], axis=1))
    return accuracy


def test_convergence_is_judged_from_the_true_motion() -> None:
    # the camera reaches 2 mm at frame 5: judged from frame 5 + 30 = 35 on
    early = _moving(_accuracy(scale_error=0.015, metric_factor=1.0), onset_frame=5)
    assert len(converged_scale_error(early, AccuracyBars())) == 90 - 35
    assert accuracy_shortfalls(early) == []
    # still far off at frame 35 (the 0.03 samples run to frame 19): caught
    early.scale.scale[30:40] = 0.03  # type: ignore[union-attr]
    assert accuracy_shortfalls(early)[0].startswith(
        "scale up to 50.0% from the oracle from 1 s after 2 mm of motion on (bar 2%; 55 samples"
    )
    # no estimate yet 1 s after the motion: an infinite error, said plainly
    late = _moving(_accuracy(scale_error=0.015, metric_factor=1.0), onset_frame=5)
    late.scale.scale[:40] = np.nan  # type: ignore[union-attr]
    assert np.isinf(converged_scale_error(late, AccuracyBars())).sum() == 5
    assert accuracy_shortfalls(late) == [
        "the scale had no estimate at 5 of 55 samples from 1 s after 2 mm of motion on "
        "(the first 0.00 s later)"
    ]
    # a reset late in the run: named with its time, and the worst finite error still judged
    late.scale.scale[:40] = 0.02 * 1.015  # type: ignore[union-attr]
    late.scale.scale[60] = np.nan  # type: ignore[union-attr]
    late.scale.scale[70] = 0.02 * 1.03  # type: ignore[union-attr]
    assert accuracy_shortfalls(late)[:2] == [
        "the scale had no estimate at 1 of 55 samples from 1 s after 2 mm of motion on "
        "(the first 0.83 s later)",
        "scale up to 3.0% from the oracle from 1 s after 2 mm of motion on (bar 2%; 54 samples)",
    ]
    # a camera that never moves 2 mm cannot show a converged scale
    still = _moving(_accuracy(scale_error=0.015, metric_factor=1.0), onset_frame=200)
    never = "the scale cannot be judged: the camera never moved 2 mm"
    assert accuracy_shortfalls(still)[0] == never


def test_frame_shortfalls_judge_per_frame_outputs_only() -> None:
    rows = [
        StageCount("endo-sfs", topics.DEPTH_RELATIVE, 90, 66, 0),
        StageCount("endo-flow", topics.SCALE, 66, 66, 0),
        StageCount("endo-flow", topics.MAP, 66, 5, 0),
    ]
    per_frame = {topics.DEPTH_RELATIVE, topics.SCALE}
    assert frame_shortfalls(rows, per_frame) == [
        f"endo-sfs kept 66 of 90 frames on {topics.DEPTH_RELATIVE}"
    ]
    # with the node's skip count (its /diagnostics), the sentence says why
    assert frame_shortfalls(rows, per_frame, {"endo-sfs": 24, "endo-flow": 0}) == [
        f"endo-sfs kept 66 of 90 frames on {topics.DEPTH_RELATIVE} "
        "(skipped 24 stale frames: slower than the playback)"
    ]


def test_summary_json_and_side_by_side(tmp_path) -> None:
    import json

    from endo_bringup.live_vs_offline import side_by_side, write_summary

    live = _accuracy(scale_error=0.04, metric_factor=1.1)
    offline = _accuracy(scale_error=0.015, metric_factor=1.0)
    offline.cloud_rms_m = {T0: 0.003}
    rows = {name: (a, b) for name, a, b in side_by_side(live, offline)}
    assert rows["cloud-to-truth RMS"][0] == "-"
    assert rows["cloud-to-truth RMS"][1].startswith("3.00 mm")
    live_metric, offline_metric = rows["metric depth AbsRel (no scaling)"]
    assert live_metric != offline_metric
    path = tmp_path / "summary.json"
    problems = accuracy_shortfalls(live)
    write_summary(
        path, ok=False, problems=problems, settings={"playback_rate": 0.25}, stages=[],
        calibration={"residual": float("nan")}, live=live, offline=None,
    )  # fmt: skip
    document = json.loads(path.read_text())
    assert document["ok"] is False and document["fell_short"] == problems
    assert document["calibration"] == {"residual": None}  # strict JSON: no NaN
    scale = document["live"]["accuracy"]["scale"]["relative_error"]
    assert scale[:10] == [None] * 10 and scale[-1] == pytest.approx(0.04)


def test_summary_json_holds_the_judged_figures_and_the_bars(tmp_path) -> None:
    """Every number of fell_short's sentences is in summary.json, not only in the sentences."""
    import json

    from endo_bringup.live_vs_offline import write_summary

    live = _accuracy(scale_error=0.04, metric_factor=1.1)
    live.poses = PoseComparison(89, 1, np.linspace(0.1, 2.5, 89), np.full(89, 0.1))
    problems = accuracy_shortfalls(live)
    path = tmp_path / "summary.json"
    write_summary(
        path, ok=False, problems=problems, settings={}, stages=[], calibration=None,
        live=live, offline=None,
    )  # fmt: skip
    acceptance = json.loads(path.read_text())["acceptance"]
    assert acceptance["bars"] == {
        "scale_relative_error": 0.02, "convergence_s": 1.0, "metric_oracle_gap": 0.01,
        "position_mm": 2.0, "rotation_deg": 0.5, "motion_m": 0.002,
    }  # fmt: skip
    judged = acceptance["live"]
    assert acceptance["offline"] is None
    assert judged["ok"] is False
    # "scale up to 4.0% ... (bar 2%; 50 samples)": samples 40..89 (1 s after the first estimate)
    assert judged["scale_worst_relative_error"] == pytest.approx(0.04)
    assert judged["scale_judged_samples"] == 50
    assert judged["scale_samples_without_estimate"] == 0
    assert judged["scale_judged_from_ns"] == T0 + 10 * FRAME_NS + 1_000_000_000
    assert judged["scale_judged_from"] == "1 s after its first estimate"
    metric, oracle, frames = metric_oracle_gap(live)
    assert frames == 3
    assert (judged["metric_frames"], judged["metric_abs_rel_mean"]) == (frames, metric)
    assert judged["oracle_abs_rel_mean"] == oracle
    assert judged["metric_oracle_gap"] == pytest.approx(abs(metric - oracle))
    assert f"{judged['metric_oracle_gap']:.4f}" in problems[1]
    assert judged["pose_position_max_mm"] == pytest.approx(2.5)
    assert judged["pose_rotation_max_deg"] == pytest.approx(0.1)
    assert "camera pose error up to 2.50 mm" in problems[2]
    # a recording that meets every bar says so
    write_summary(
        path, ok=True, problems=[], settings={}, stages=[], calibration=None,
        live=_accuracy(scale_error=0.015, metric_factor=1.0), offline=None,
    )  # fmt: skip
    good = json.loads(path.read_text())["acceptance"]["live"]
    assert good["ok"] is True and good["scale_worst_relative_error"] == pytest.approx(0.015)
