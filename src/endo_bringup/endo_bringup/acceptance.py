"""What the demo calls OK: every stage kept every frame, and the accuracy bars hold.

ROS-free: works on the stage counts of a run (:class:`endo_bringup.graph.StageCount`)
and on a scored recording (:class:`endo_process.accuracy.Accuracy`, the same
scoring ``endo-process`` prints). Each check returns plain sentences naming
what fell short, with the figure and the bar, so the demo can print them as
they are; an empty list means the check passed.

The accuracy bars are endo_flow's (issue 11) for the colon, the phantom's
scene: the scale converges within 1 s of the camera's first 2 mm of motion
and from then on is within 2 % of the oracle scale
(:func:`endo_sfs.evaluation.sequence_scale`), and
the metric AbsRel (no per-frame scaling) is within 0.01 of the oracle-scaled
AbsRel. Its cloud bar (1.5 mm) is for the abdomen; on the colon the cloud's
RMS is reported, not judged. The camera pose bound is the demo's own smoke
bound (tests/test_demo_graph.py), not an issue 11 bar.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from endo_bringup.graph import StageCount
from endo_io.pose import motion_onset
from endo_io.stamp import NS_PER_S

if TYPE_CHECKING:
    # endo_process depends on endo_bringup (its scoring pairs streams with
    # endo_process.evaluation): only the type is needed here, not the package.
    from endo_process.accuracy import Accuracy


@dataclass(frozen=True)
class AccuracyBars:
    """The bars a scored recording must meet.

    scale_relative_error: largest |s / s_oracle − 1| after convergence;
    convergence_s, motion_m: the scale samples from ``convergence_s`` (bag
    time, seconds) after the true camera first stands ``motion_m`` (metres)
    from its first pose count as converged (issue 11: within 1 s of 2 mm of
    motion); without a true trajectory, from ``convergence_s`` after the
    first usable sample;
    metric_oracle_gap: largest |metric AbsRel − oracle-scaled AbsRel| (means
    over the truth frames with metric depth); position_mm, rotation_deg:
    largest camera pose error (the demo's bound).
    """

    scale_relative_error: float = 0.02
    convergence_s: float = 1.0
    metric_oracle_gap: float = 0.01
    position_mm: float = 2.0
    rotation_deg: float = 0.5
    motion_m: float = 0.002


def frame_shortfalls(
    rows: Iterable[StageCount],
    per_frame: Collection[str],
    skipped: Mapping[str, int | None] | None = None,
) -> list[str]:
    """Stages that let out fewer messages than came in, on their per-frame outputs.

    rows: the run's stage report; per_frame: the topics that carry one
    message per input message (the others, e.g. the periodic map, are not
    judged here); skipped: stage -> stale frames it skipped for a newer one
    (its /diagnostics, :mod:`endo_bringup.graph_monitor`), named in the
    sentence when known: the stage was slower than the playback.
    """
    skipped = skipped or {}
    problems = []
    for row in rows:
        if row.topic in per_frame and row.count_out < row.count_in:
            count = skipped.get(row.stage)
            why = f" (skipped {count} stale frames: slower than the playback)" if count else ""
            problems.append(
                f"{row.stage} kept {row.count_out} of {row.count_in} frames on {row.topic}{why}"
            )
    return problems


def convergence_start_ns(accuracy: Accuracy, bars: AccuracyBars) -> tuple[int | None, str]:
    """(stamp from which the scale counts as converged, what it is counted from).

    ``bars.convergence_s`` after the true camera first stood ``bars.motion_m``
    from its first pose; without a true trajectory, after the first usable
    scale sample. (None, why) when neither exists.
    """
    wait_ns = round(bars.convergence_s * NS_PER_S)
    if accuracy.true_positions is not None:
        stamps, positions = accuracy.true_positions
        onset = motion_onset(positions, bars.motion_m)
        if onset is None:
            return None, f"the camera never moved {bars.motion_m * 1e3:g} mm"
        return int(stamps[onset]) + wait_ns, (
            f"{bars.convergence_s:g} s after {bars.motion_m * 1e3:g} mm of motion"
        )
    track = accuracy.scale
    if track is None or not np.isfinite(track.relative_error).any():
        return None, "no usable scale sample"
    first = int(track.stamps_ns[np.isfinite(track.relative_error)][0])
    return first + wait_ns, f"{bars.convergence_s:g} s after its first estimate"


def converged_scale_error(accuracy: Accuracy, bars: AccuracyBars) -> np.ndarray:
    """(K',) relative scale errors of the samples from :func:`convergence_start_ns` on.

    A sample from then on without a usable value (NaN: no estimate yet) is an
    infinite error: the scale had not converged when it had to.
    """
    track = accuracy.scale
    start, _ = convergence_start_ns(accuracy, bars)
    if track is None or start is None:
        return np.empty(0)
    error = np.asarray(track.relative_error[track.stamps_ns >= start], np.float64)
    return np.where(np.isfinite(error), error, np.inf)


def _seconds_after(accuracy: Accuracy, start_ns: int, missing: np.ndarray) -> str:
    """Seconds from ``start_ns`` to the first judged sample flagged in ``missing``."""
    assert accuracy.scale is not None  # judged samples exist
    judged = accuracy.scale.stamps_ns[accuracy.scale.stamps_ns >= start_ns]
    return f"{(int(judged[np.argmax(missing)]) - start_ns) / NS_PER_S:.2f}"


def metric_oracle_gap(accuracy: Accuracy) -> tuple[float, float, int]:
    """(mean metric AbsRel, mean oracle-scaled AbsRel, frames) over the frames with both."""
    stamps = sorted(set(accuracy.metric) & set(accuracy.oracle))
    if not stamps:
        return float("nan"), float("nan"), 0
    metric = float(np.mean([accuracy.metric[s].abs_rel for s in stamps]))
    oracle = float(np.mean([accuracy.oracle[s].abs_rel for s in stamps]))
    return metric, oracle, len(stamps)


def accuracy_shortfalls(accuracy: Accuracy, bars: AccuracyBars | None = None) -> list[str]:
    """Every bar ``accuracy`` misses, as one sentence each with the figure and the bar."""
    bars = bars or AccuracyBars()
    problems: list[str] = []
    if not accuracy.has_truth:
        return ["the recording has no ground truth to score against"]
    converged = converged_scale_error(accuracy, bars)
    start, since = convergence_start_ns(accuracy, bars)
    if start is None:
        problems.append(f"the scale cannot be judged: {since}")
    elif len(converged) == 0:
        problems.append(f"no scale sample from {since} on")
    else:
        missing = ~np.isfinite(converged)
        if missing.any():
            problems.append(
                f"the scale had no estimate at {int(missing.sum())} of {len(converged)} samples "
                f"from {since} on (the first {_seconds_after(accuracy, start, missing)} s later)"
            )
        finite = np.abs(converged[~missing])
        worst = float(np.max(finite)) if len(finite) else 0.0
        if worst > bars.scale_relative_error:
            problems.append(
                f"scale up to {worst:.1%} from the oracle from {since} on "
                f"(bar {bars.scale_relative_error:.0%}; {len(finite)} samples)"
            )
    metric, oracle, frames = metric_oracle_gap(accuracy)
    if frames == 0:
        problems.append("no metric depth at any ground-truth frame")
    elif abs(metric - oracle) > bars.metric_oracle_gap:
        problems.append(
            f"metric AbsRel {metric:.4f} is {abs(metric - oracle):.4f} from the oracle-scaled "
            f"{oracle:.4f} (bar {bars.metric_oracle_gap:g}; {frames} frames)"
        )
    poses = accuracy.poses
    if poses is None or poses.compared == 0:
        problems.append("no camera pose could be compared with the ground truth")
    else:
        position, rotation = float(np.max(poses.position_mm)), float(np.max(poses.rotation_deg))
        if position > bars.position_mm or rotation > bars.rotation_deg:
            problems.append(
                f"camera pose error up to {position:.2f} mm / {rotation:.3f} deg "
                f"(bound {bars.position_mm:g} mm / {bars.rotation_deg:g} deg)"
            )
    return problems


def acceptance_document(accuracy: Accuracy, bars: AccuracyBars | None = None) -> dict[str, Any]:
    """The figures :func:`accuracy_shortfalls` judges, as JSON-able data (summary.json).

    Keys carry their unit (``_ns``, ``_mm``, ``_deg``); errors without one are
    fractions (0.02 = 2 %). ``scale_worst_relative_error`` is the largest
    |s / s_oracle − 1| over the judged samples that have an estimate (None
    when none has); ``scale_samples_without_estimate`` counts the others.
    ``metric_abs_rel_mean`` and ``oracle_abs_rel_mean`` are means over the
    ``metric_frames`` truth frames that have both (so the oracle's mean can
    differ from the accuracy's ``oracle_abs_rel_mean`` over every truth
    frame). ``ok`` is :func:`accuracy_shortfalls` finding nothing.
    """
    bars = bars or AccuracyBars()
    document: dict[str, Any] = {
        "ok": not accuracy_shortfalls(accuracy, bars),
        "scale_judged_from_ns": None,
        "scale_judged_from": "",
        "scale_judged_samples": 0,
        "scale_samples_without_estimate": 0,
        "scale_worst_relative_error": None,
        "metric_frames": 0,
        "metric_abs_rel_mean": None,
        "oracle_abs_rel_mean": None,
        "metric_oracle_gap": None,
        "pose_position_max_mm": None,
        "pose_rotation_max_deg": None,
    }
    if not accuracy.has_truth:
        return document
    start, since = convergence_start_ns(accuracy, bars)
    converged = converged_scale_error(accuracy, bars)
    finite = np.abs(converged[np.isfinite(converged)])
    document.update(
        scale_judged_from_ns=start,
        scale_judged_from=since,
        scale_judged_samples=len(converged),
        scale_samples_without_estimate=int(np.count_nonzero(~np.isfinite(converged))),
        scale_worst_relative_error=float(np.max(finite)) if len(finite) else None,
    )
    metric, oracle, frames = metric_oracle_gap(accuracy)
    if frames:
        document.update(
            metric_frames=frames,
            metric_abs_rel_mean=metric,
            oracle_abs_rel_mean=oracle,
            metric_oracle_gap=abs(metric - oracle),
        )
    poses = accuracy.poses
    if poses is not None and poses.compared:
        document.update(
            pose_position_max_mm=float(np.max(poses.position_mm)),
            pose_rotation_max_deg=float(np.max(poses.rotation_deg)),
        )
    return document
