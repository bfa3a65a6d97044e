"""The demo's last part: ``endo-process`` on the bag the live graph played, side by side.

``endo-process`` runs the live nodes' cores over every frame without DDS
(:mod:`endo_process`); it is run here as a user runs it, in its own process,
with the calibrations and settings the live graph had (the nodes' parameter
file from :func:`endo_process.simulated.write_simulated_parameters`, the
same settings :func:`endo_bringup.demo.graph_settings_for` gives the
nodes). It draws ``report.png`` and writes its summary JSON; both
recordings are scored by :func:`endo_process.accuracy.score_recording`, so
the two columns are the same figures computed the same way.

endo_process depends on endo_bringup (its scoring pairs streams with
:mod:`endo_process.evaluation`), so it is imported only when this part runs.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from endo_bringup.graph import OfflineStep, _run_step
from endo_bringup.process_group import console_script

if TYPE_CHECKING:
    from endo_process.accuracy import Accuracy


@dataclass
class OfflineRun:
    """``endo-process`` on the phantom bag: its step, output, figure, summary and scores.

    summary: endo-process's ``--summary-json`` document (None when it did
    not finish); accuracy: its output scored against the truth.
    """

    step: OfflineStep
    output: Path
    report_png: Path
    summary: dict[str, Any] | None
    accuracy: Accuracy | None


def run_endo_process(
    bag: Path,
    photometric: Path,
    handeye: Path,
    out_dir: Path,
    env: dict[str, str],
    solve_scale: float,
) -> OfflineRun:
    """``endo-process`` on ``bag`` into ``out_dir/offline.mcap``, ``report.png``, its JSON.

    The SFS node's solve_scale is the live graph's; roughness and the
    tracker registration come from the simulator's truth as for the nodes.
    """
    from endo_process.accuracy import score_recording
    from endo_process.simulated import write_simulated_parameters

    params = write_simulated_parameters(bag, out_dir / "endo3d.yaml")
    output, figure = out_dir / "offline.mcap", out_dir / "report.png"
    summary_path = out_dir / "offline_summary.json"
    argv = [
        console_script("endo-process"), str(bag), "-o", str(output),
        "--calibration", str(photometric), "--handeye", str(handeye),
        "--params", str(params), "--solve-scale", repr(float(solve_scale)),
        "--report", str(figure), "--summary-json", str(summary_path),
        "--quiet", "--overwrite",
    ]  # fmt: skip
    step = _run_step(argv, output, env, out_dir / "logs" / "endo-process.log")
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    accuracy = score_recording(output) if step.return_code == 0 else None
    return OfflineRun(step, output, figure, summary, accuracy)


def side_by_side(live: Accuracy | None, offline: Accuracy | None) -> list[tuple[str, str, str]]:
    """(figure, live value, offline value) for every accuracy figure either has."""
    from endo_process.summary import accuracy_rows

    live_rows = dict(accuracy_rows(live)) if live is not None else {}
    offline_rows = dict(accuracy_rows(offline)) if offline is not None else {}
    names = list(dict.fromkeys([*live_rows, *offline_rows]))
    return [(n, live_rows.get(n, "-"), offline_rows.get(n, "-")) for n in names]


def print_side_by_side(run: OfflineRun, live: Accuracy | None, live_flow_frames: int) -> None:
    """endo-process's outcome, then each figure for the live graph and offline."""
    status = "ok" if run.step.return_code == 0 else f"FAILED (exit {run.step.return_code})"
    print(f"  endo-process     {status} in {run.step.seconds:.1f} s -> {run.output}")
    if run.step.return_code != 0:
        print("    " + run.step.output.strip()[-2000:].replace("\n", "\n    "))
    if run.summary is not None:
        frames = run.summary["frames"]
        speed = run.summary["speed"]
        print(
            f"    offline: {frames['through_flow']} of {frames['in_recording']} frames through "
            f"flow ({live_flow_frames} live), {speed['frames_per_second']:.1f} frames/s, "
            f"{speed['real_time_factor']:.2f}x real time"
        )
    if run.report_png.exists():
        print(f"    report: {run.report_png}")
    for name, live_value, offline_value in side_by_side(live, run.accuracy):
        print(f"    {name}\n      live:    {live_value}\n      offline: {offline_value}")


def write_summary(
    path: Path,
    *,
    ok: bool,
    problems: list[str],
    settings: dict[str, Any],
    stages: list[dict[str, Any]],
    calibration: dict[str, Any] | None,
    live: Accuracy | None,
    offline: OfflineRun | None,
    timing: dict[str, Any] | None = None,
) -> None:
    """``summary.json``: every figure the demo printed, machine-readable (strict JSON).

    live: the live recording's accuracy (the layout of endo-process's
    ``accuracy`` member); offline: endo-process's whole summary document;
    timing: the live graph's frames, skips, rates, latency, CPU and RSS
    (:class:`endo_bringup.graph_monitor.GraphFigures` as a dict; NaN as null).
    ``acceptance`` holds the bars and, for each recording, the figures judged
    against them (:func:`endo_bringup.acceptance.acceptance_document`): the
    numbers behind ``fell_short``'s sentences.
    """
    from endo_bringup.acceptance import AccuracyBars, acceptance_document
    from endo_process.summary import _finite, accuracy_document

    def judged(accuracy: Accuracy | None) -> dict[str, Any] | None:
        return None if accuracy is None else acceptance_document(accuracy)

    document = {
        "format": "endo3d.demo_summary",
        "version": 1,
        "ok": ok,
        "fell_short": problems,
        "settings": settings,
        "calibration": _finite(calibration),
        "live": {"stages": stages, "accuracy": accuracy_document(live),
                 "timing": _finite(timing)},
        "offline": None if offline is None else offline.summary,
        "acceptance": _finite({
            "bars": asdict(AccuracyBars()),
            "live": judged(live),
            "offline": None if offline is None else judged(offline.accuracy),
        }),
    }
    path.write_text(json.dumps(document, indent=1, allow_nan=False) + "\n")
