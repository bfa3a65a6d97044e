"""The summary table ``endo-process`` prints at the end of a run."""

from __future__ import annotations

from collections import Counter

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
        ("frames without a pose (skipped by flow)", _causes(report.without_pose)),
        ("tracker samples", f"{report.tracker_samples}"),
        ("tracker samples rejected", _causes(report.tracker_rejected)),
        ("camera poses written", f"{report.poses_written}"),
        ("wall time (frames)", f"{report.seconds:.2f} s (setup {report.setup_seconds:.2f} s)"),
        ("speed", f"{report.frames_per_second:.1f} frames/s, "
                  f"{report.real_time_factor:.2f}x real time"),  # fmt: skip
        ("SFS solve, median per frame", f"{report.median_solve_ms:.1f} ms"),
    ]
    if report.damage:
        rows.append(("input damage", report.damage))
    if report.interrupted:
        rows.append(("interrupted", "yes (output finalised)"))
    if report.output is not None:
        written = sum(report.written.values())
        rows.append(("output", f"{report.output} ({written} messages)"))
    return rows


def format_report(report: ProcessReport) -> str:
    """The run as a two-column text table."""
    rows = _rows(report)
    width = max(len(name) for name, _ in rows)
    lines = ["endo-process summary", "-" * (width + 40)]
    lines += [f"{name:<{width}}  {value}" for name, value in rows]
    return "\n".join(lines)
