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
    converged = converged_scale_error(good, 1.0)
    # samples 10.. are usable; converged from 1 s (30 frames) later: 90 − 40 samples
    assert len(converged) == 50
    np.testing.assert_allclose(converged, 0.015)
    metric, oracle, frames = metric_oracle_gap(good)
    assert frames == 3 and metric == oracle
    assert accuracy_shortfalls(good) == []

    bad = _accuracy(scale_error=0.04, metric_factor=1.1)
    problems = accuracy_shortfalls(bad)
    assert len(problems) == 2
    assert problems[0].startswith("scale after convergence up to 4.0% from the oracle (bar 2%")
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
        "the scale never converged (1 s after its first estimate)",
        "no metric depth at any ground-truth frame",
    ]


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
