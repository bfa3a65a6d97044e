"""The summary table ``endo-process`` prints at the end of a run."""

from __future__ import annotations

from collections import Counter

import numpy as np

from endo_process.accuracy import Accuracy
from endo_process.runner import ProcessReport


def _causes(counter: Counter[str]) -> str:
    return ", ".join(f"{n} {cause}" for cause, n in counter.most_common()) or "none"


def _rows(report: ProcessReport) -> list[tuple[str, str]]:
    rows = [
        ("images in the recording", f"{report.frames_total}"),
        ("images read", f"{report.frames_in}"),
        ("frames with relative depth", f"{report.frames_shaded}"),
        ("frames dropped or without depth", _causes(report.dropped)),
        ("frames with a camera pose", f"{report.frames_with_pose}"),
        ("frames without a pose (no world points)", _causes(report.without_pose)),
        ("frames through flow / with metric depth",
         f"{report.frames_flow} / {report.frames_metric}"),
        ("frames refused by flow", _causes(report.flow_dropped)),
        ("map points (last state)", f"{report.map_points}"),
        ("tracker samples", f"{report.tracker_samples}"),
        ("tracker samples rejected", _causes(report.tracker_rejected)),
        ("camera poses written", f"{report.poses_written}"),
        ("wall time (frames)", f"{report.seconds:.2f} s (setup {report.setup_seconds:.2f} s)"),
        ("speed", f"{report.frames_per_second:.1f} frames/s, "
         f"{report.real_time_factor:.2f}x real time"),
        ("SFS solve, median per frame", f"{report.median_solve_ms:.1f} ms"),
    ]
    if report.damage:
        rows.append(("input damage", report.damage))
    if report.interrupted:
        rows.append(("interrupted", "yes (output finalised)"))
    if report.ply_vertices:
        rows.append(("PLY vertices", f"{report.ply_vertices}"))
    if report.output is not None:
        written = sum(report.written.values())
        rows.append(("output", f"{report.output} ({written} messages)"))
    return rows


def _spread(values: list[float], unit: float = 1.0, digits: int = 4, name: str = "") -> str:
    array = np.asarray(values, dtype=np.float64) * unit
    suffix = f" {name}" if name else ""
    return (f"{array.mean():.{digits}f}{suffix} (min {array.min():.{digits}f}, "
            f"max {array.max():.{digits}f}, {len(array)} frames)")  # fmt: skip


def accuracy_rows(accuracy: Accuracy) -> list[tuple[str, str]]:
    """The accuracy figures as (name, value) rows; empty without ground truth."""
    rows: list[tuple[str, str]] = []
    if accuracy.relative:
        rows.append(("relative depth AbsRel (median-scaled)",
                     _spread([e.abs_rel for e in accuracy.relative.values()])))  # fmt: skip
        coverage = [e.coverage for e in accuracy.relative.values()]
        rows.append(("relative depth coverage", _spread(coverage, digits=3)))
        rows.append(("oracle scale (one fit, whole sequence)",
                     f"{accuracy.oracle_scale:.6g} m per unit"))  # fmt: skip
    if accuracy.oracle:
        rows.append(("oracle-scaled depth AbsRel",
                     _spread([e.abs_rel for e in accuracy.oracle.values()])))  # fmt: skip
    if accuracy.metric:
        errors = list(accuracy.metric.values())
        mae = _spread([e.mae for e in errors], 1e3, 2, "mm")
        rows.append(("metric depth MAE (no scaling)", mae))
        rows.append(("metric depth AbsRel (no scaling)", _spread([e.abs_rel for e in errors])))
    elif accuracy.truth_frames:
        rows.append(("metric depth", "no /endoscope/depth at the ground-truth frames"))
    if accuracy.cloud_rms_m:
        rows.append(("cloud-to-truth RMS",
                     _spread(list(accuracy.cloud_rms_m.values()), 1e3, 2, "mm")))  # fmt: skip
    if accuracy.scale is not None:
        error = accuracy.scale.relative_error
        finite = np.flatnonzero(np.isfinite(error))
        if len(finite):
            last_half = error[finite[len(finite) // 2 :]]
            rows.append(("scale error vs oracle",
                         f"first {error[finite[0]]:+.1%}, median of the last half "
                         f"{np.median(last_half):+.1%}, final {error[finite[-1]]:+.1%} "
                         f"({len(finite)} of {len(error)} frames usable)"))  # fmt: skip
    poses = accuracy.poses
    if poses is not None and poses.compared:
        rows.append(("camera pose error",
                     f"position median {np.median(poses.position_mm):.2f} mm "
                     f"(p95 {np.percentile(poses.position_mm, 95):.2f}), rotation median "
                     f"{np.median(poses.rotation_deg):.3f} deg (p95 "
                     f"{np.percentile(poses.rotation_deg, 95):.3f}); {poses.compared} compared, "
                     f"{poses.missing} without an estimate"))  # fmt: skip
    return rows


def format_report(report: ProcessReport, accuracy: Accuracy | None = None) -> str:
    """The run (and its accuracy, when scored) as a two-column text table."""
    rows = _rows(report)
    if accuracy is not None and accuracy.has_truth:
        rows.append(("-- against ground truth", ""))
        rows += accuracy_rows(accuracy)
    width = max(len(name) for name, _ in rows)
    lines = ["endo-process summary", "-" * (width + 40)]
    lines += [f"{name:<{width}}  {value}" for name, value in rows]
    return "\n".join(lines)
