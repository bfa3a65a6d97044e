"""The summary ``endo-process`` prints at the end of a run, as a table and as JSON."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from endo_process.accuracy import Accuracy
from endo_process.damage import damage_document, damage_line
from endo_process.runner import ProcessReport
from endo_sfs.evaluation import DepthError


def _causes(counter: Counter[str]) -> str:
    return ", ".join(f"{n} {cause}" for cause, n in counter.most_common()) or "none"


def drop_lines(report: ProcessReport) -> list[str]:
    """One line per cause: dropped frames, rejected tracker samples, pose buffer events, flow.

    A pose buffer event is a tracker clock jump (ClockJumpError) or a pose it refused.

    Each names the count, the cause and the first such item's message, e.g.
    ``20 frames dropped, CalibrationMismatchError: image 640x480 bgr8 ...``.
    """
    lines = []
    for what, counter in (("frames dropped", report.dropped),
                          ("tracker samples rejected", report.tracker_rejected),
                          ("poses refused or reset by the pose buffer",
                           report.pose_buffer_events),
                          ("frames refused by flow", report.flow_dropped)):  # fmt: skip
        for cause, n in counter.most_common():
            lines.append(f"{n} {what}, {cause}: {report.reasons.get(cause, '')}".rstrip(": "))
    return lines


def _rows(report: ProcessReport) -> list[tuple[str, str]]:
    rows = [
        ("images in the recording", f"{report.frames_total}"),
        ("images read", f"{report.frames_in}"),
        ("frames with relative depth", f"{report.frames_shaded}"),
        ("frames dropped or without depth", _causes(report.dropped)),
    ]
    if report.frames_in_flight:
        rows.append(("frames in flight at the stop, not written", f"{report.frames_in_flight}"))
    rows += [
        ("frames with a camera pose", f"{report.frames_with_pose}"),
        ("frames without a pose (no world points)", _causes(report.without_pose)),
        ("frames through flow / with metric depth",
         f"{report.frames_flow} / {report.frames_metric}"),
        ("frames refused by flow", _causes(report.flow_dropped)),
        ("map points (last state)", f"{report.map_points}"),
    ]
    if report.saturated_pixels:
        rows.append(("corrected pixels above the 16UC1 range (saturated)",
                     f"{report.saturated_pixels}"))
    rows += [
        ("tracker samples", f"{report.tracker_samples}"),
        ("tracker samples rejected", _causes(report.tracker_rejected)),
        ("poses refused or reset by the pose buffer", _causes(report.pose_buffer_events)),
        ("camera poses written", f"{report.poses_written}"),
        ("wall time (frames)", f"{report.seconds:.2f} s (setup {report.setup_seconds:.2f} s)"),
        ("speed", f"{report.frames_per_second:.1f} frames/s, "
         f"{report.real_time_factor:.2f}x real time"),
        ("SFS solve, median per frame", f"{report.median_solve_ms:.1f} ms"),
    ]
    line = damage_line(report.input_damage, report.frames_in, report.recording_start_ns,
                       "interrupted" if report.interrupted else "--max-frames")  # fmt: skip
    if line:
        rows.append(("input damage", line.removeprefix("error: ").removeprefix("note: ")))
    if report.undecodable:
        rows.append(("undecodable messages skipped", _causes(report.undecodable)))
    if report.interrupted:
        rows.append(("interrupted", "yes (output finalised)"))
    if report.ply_vertices:
        rows.append(("PLY vertices", f"{report.ply_vertices}"))
    elif report.ply_error:
        rows.append(("PLY", f"not written ({report.ply_error})"))
    if report.output is not None:
        written = sum(report.written.values())
        rows.append(("output", f"{report.output} ({written} messages)"))
        if report.write_failure:
            rows.append(("output write failed", f"{report.lost} messages lost; the file reads "
                         "to its last complete chunk (endo-bag recover makes a complete copy)"))
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


def _per_frame(errors: dict[int, DepthError]) -> list[dict[str, float]]:
    return [
        {"stamp_ns": stamp, "abs_rel": e.abs_rel, "mae_m": e.mae, "p95_rel": e.p95_rel,
         "coverage": e.coverage, "scale": e.scale}
        for stamp, e in sorted(errors.items())
    ]  # fmt: skip


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def _finite(value: Any) -> Any:
    """The value with every NaN or infinity (nested) replaced by None (JSON has neither)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def summary_document(report: ProcessReport, accuracy: Accuracy | None) -> dict[str, Any]:
    """Every figure of the summary as plain JSON-able data (``--summary-json``).

    Lengths in metres, angles in degrees, times in seconds (``*_ms``:
    milliseconds), stamps in integer ns; None where a figure does not apply.
    """
    document: dict[str, Any] = {
        "format": "endo3d.process_summary",
        "version": 1,
        "output": str(report.output) if report.output else None,
        "frames": {
            "in_recording": report.frames_total, "read": report.frames_in,
            "with_relative_depth": report.frames_shaded, "with_pose": report.frames_with_pose,
            "through_flow": report.frames_flow, "with_metric_depth": report.frames_metric,
            "dropped": dict(report.dropped), "without_pose": dict(report.without_pose),
            "refused_by_flow": dict(report.flow_dropped),
            "in_flight_not_written": report.frames_in_flight,
        },
        "tracker": {
            "samples": report.tracker_samples, "rejected": dict(report.tracker_rejected),
            "pose_buffer_events": dict(report.pose_buffer_events),
            "camera_poses": report.poses_written,
        },
        "map_points": report.map_points,
        "ply_vertices": report.ply_vertices,
        "speed": {
            "seconds": report.seconds, "setup_seconds": report.setup_seconds,
            "recording_seconds": report.bag_seconds,
            "frames_per_second": report.frames_per_second,
            "real_time_factor": report.real_time_factor,
            "median_solve_ms": report.median_solve_ms,
        },
        "damage": report.damage,
        "damage_after_max_frames": report.damage_beyond,
        "input_damage": damage_document(report.input_damage, report.recording_start_ns),
        "undecodable": dict(report.undecodable),
        "interrupted": report.interrupted,
        "written": dict(report.written),
        "write_failure": report.write_failure or None,
        "lost": report.lost,
        "accuracy": None,
    }  # fmt: skip
    document["accuracy"] = accuracy_document(accuracy)
    return _finite(document)


def accuracy_document(accuracy: Accuracy | None) -> dict[str, Any] | None:
    """The accuracy figures as plain JSON-able data (None without ground truth).

    The ``accuracy`` member of :func:`summary_document`; ``endo-demo`` writes
    the live recording's with it. Units as there; NaN and infinities become None.
    """
    if accuracy is None or not accuracy.has_truth:
        return None
    scored: dict[str, Any] = {
        "truth_frames": accuracy.truth_frames,
        "relative_abs_rel_mean": _mean([e.abs_rel for e in accuracy.relative.values()]),
        "relative": _per_frame(accuracy.relative),
        "oracle_scale": accuracy.oracle_scale if np.isfinite(accuracy.oracle_scale) else None,
        "oracle_abs_rel_mean": _mean([e.abs_rel for e in accuracy.oracle.values()]),
        "metric_abs_rel_mean": _mean([e.abs_rel for e in accuracy.metric.values()]),
        "metric_mae_m_mean": _mean([e.mae for e in accuracy.metric.values()]),
        "metric": _per_frame(accuracy.metric),
        "cloud_rms_m_mean": _mean(list(accuracy.cloud_rms_m.values())),
        "cloud_rms_m": {str(k): v for k, v in sorted(accuracy.cloud_rms_m.items())},
        "scale": None,
        "pose": None,
    }
    if accuracy.scale is not None:
        track = accuracy.scale
        usable = np.flatnonzero(np.isfinite(track.relative_error))
        summary: dict[str, Any] = {"usable_frames": len(usable)}
        if len(usable):  # the printed row: first, median of the last half, final
            error = track.relative_error
            summary.update(
                first_relative_error=float(error[usable[0]]),
                median_last_half_relative_error=float(
                    np.median(error[usable[len(usable) // 2 :]])
                ),
                final_relative_error=float(error[usable[-1]]),
            )
        scored["scale"] = {
            **summary,
            "stamps_ns": track.stamps_ns.tolist(),
            "value": [None if not np.isfinite(v) else float(v) for v in track.scale],
            "relative_error": [None if not np.isfinite(v) else float(v)
                               for v in track.relative_error],
        }  # fmt: skip
    poses = accuracy.poses
    if poses is not None and poses.compared:
        scored["pose"] = {
            "compared": poses.compared, "missing": poses.missing,
            "position_m_median": float(np.median(poses.position_mm)) * 1e-3,
            "position_m_p95": float(np.percentile(poses.position_mm, 95)) * 1e-3,
            "rotation_deg_median": float(np.median(poses.rotation_deg)),
            "rotation_deg_p95": float(np.percentile(poses.rotation_deg, 95)),
        }  # fmt: skip
    finite: dict[str, Any] = _finite(scored)
    return finite
