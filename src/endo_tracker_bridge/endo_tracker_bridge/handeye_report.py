"""The hand–eye report figure (``endo-handeye --report handeye.png``).

Four panels and a column of text:

1. the reprojection residual of each board view (RMS corner error of the
   board projected through tracker pose and calibration), views used and
   views rejected told apart, against the image time;
2. the distribution of the corner residuals of the views used;
3. the tracker residual of each view (mm; degrees on the right axis);
4. the clock-offset search: the coarse cost against the offset, with the
   chosen offset marked;
5. text: inputs (bag, size, digest, topics, camera_info, board) and results
   (T_marker_camera, offset, residuals, views used and rejected).

Drawn with matplotlib's Agg backend, so it needs no display.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from endo_tracker_bridge.handeye import MS, HandEyeResult


def write_handeye_report(
    result: HandEyeResult, path: str | Path, inputs: dict[str, Any] | None = None
) -> Path:
    """Draw the report of a hand–eye calibration into a PNG; returns the path written.

    Args:
        result: what :func:`endo_tracker_bridge.handeye.calibrate_hand_eye` returned.
        path: the PNG (parent directories are created).
        inputs: the calibration's provenance (:mod:`endo_io.provenance`), shown as text.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    figure = handeye_figure(result, inputs)
    figure.savefig(out, dpi=80)
    plt.close(figure)
    return out


def handeye_figure(result: HandEyeResult, inputs: dict[str, Any] | None = None) -> plt.Figure:
    """The figure of :func:`write_handeye_report` (the caller closes it).

    Axes are labelled "views", "distribution", "tracker", "offset" and "text".
    """
    used = np.asarray(result.view_used, dtype=bool)
    stamps = np.asarray(result.view_stamps_ns, dtype=np.int64)
    seconds = (stamps - stamps.min()) * 1e-9 if stamps.size else stamps.astype(float)
    reprojection = np.asarray(result.view_reprojection_px, dtype=float)
    rejected = ~used

    figure = plt.figure(figsize=(18, 9))
    grid = figure.add_gridspec(2, 3, width_ratios=[1, 1, 0.8])
    ax_views = figure.add_subplot(grid[0, 0], label="views")
    ax_hist = figure.add_subplot(grid[0, 1], label="distribution")
    ax_tracker = figure.add_subplot(grid[1, 0], label="tracker")
    ax_offset = figure.add_subplot(grid[1, 1], label="offset")
    ax_text = figure.add_subplot(grid[:, 2], label="text")
    colours = matplotlib.colormaps["viridis"]

    ax_views.plot(seconds[used], reprojection[used], "o", color=colours(0.3), label="used")
    if rejected.any():
        # a view without a tracker pose around it has no residual: drawn on the axis
        shown = np.where(np.isfinite(reprojection), reprojection, 0.0)
        ax_views.plot(seconds[rejected], shown[rejected], "x", color="tab:red", ms=8,
                      label=f"rejected ({int(rejected.sum())})", clip_on=False)
        for index in np.flatnonzero(rejected):
            note = "rejected" if np.isfinite(reprojection[index]) else "rejected: no tracker pose"
            ax_views.annotate(note, (seconds[index], shown[index]), textcoords="offset points",
                              xytext=(4, 4), fontsize=7, color="tab:red")
    ax_views.axhline(result.reprojection_rms_px, color="0.4", ls="--",
                     label=f"RMS of used views {result.reprojection_rms_px:.2f} px")
    top = np.nanmax(reprojection) if np.isfinite(reprojection).any() else 1.0
    ax_views.set(xlabel="image time (s from the first view)", ylabel="RMS corner error (px)",
                 title="reprojection through tracker + calibration, per view",
                 ylim=(0.0, 1.1 * float(top)))
    ax_views.legend(fontsize=8)

    corners = np.asarray(result.corner_residuals_px, dtype=float)
    corners = corners[np.isfinite(corners)]
    if corners.size:
        ax_hist.hist(corners, bins=40, color=colours(0.6), edgecolor="none",
                     label=f"{corners.size} corners of {int(used.sum())} views")
        for q, style in ((50, ":"), (95, "--")):
            value = float(np.percentile(corners, q))
            ax_hist.axvline(value, color="0.3", ls=style, label=f"{q}th percentile {value:.2f} px")
        ax_hist.set_xlim(0.0, float(corners.max()) * 1.05)
    ax_hist.set(xlabel="corner error (px)", ylabel="corners", title="residual distribution")
    ax_hist.legend(fontsize=8)

    translation = np.asarray(result.view_translation_mm, dtype=float)
    rotation = np.asarray(result.view_rotation_deg, dtype=float)
    ax_tracker.plot(seconds[used], translation[used], "o", color=colours(0.3),
                    label="translation (mm), used")
    if rejected.any():
        ax_tracker.plot(seconds[rejected], translation[rejected], "x", color="tab:red", ms=8,
                        label="translation (mm), rejected")
    ax_rotation = ax_tracker.twinx()
    ax_rotation.set_label("tracker rotation")
    ax_rotation.plot(seconds, rotation, "s", mfc="none", color=colours(0.8), ms=4,
                     label="rotation (°)")
    ax_tracker.set(xlabel="image time (s from the first view)",
                   ylabel="marker pose residual (mm)",
                   title="tracker residual per view (measured vs predicted marker pose)")
    ax_rotation.set_ylabel("rotation residual (°)")
    if np.isfinite(translation).any():
        ax_tracker.set_ylim(0.0, 1.1 * float(np.nanmax(translation)))
    if np.isfinite(rotation).any():
        ax_rotation.set_ylim(0.0, 1.1 * float(np.nanmax(rotation)))
    lines = ax_tracker.get_legend_handles_labels()
    twin = ax_rotation.get_legend_handles_labels()
    ax_tracker.legend(lines[0] + twin[0], lines[1] + twin[1], fontsize=8)

    offsets = np.asarray(result.coarse_offsets_ms, dtype=float)
    costs = np.asarray(result.coarse_costs, dtype=float)
    finite = np.isfinite(costs)
    ax_offset.plot(offsets[finite], costs[finite], "-", color=colours(0.4),
                   label="coarse search (median whitened residual)")
    chosen_ms = result.time_offset_ns / MS
    if finite.any():
        ax_offset.axvline(chosen_ms, color="tab:red", ls="--",
                          label=f"chosen offset {chosen_ms:.2f} ms (fine search)")
        coarse_best = int(np.argmin(np.where(finite, costs, np.inf)))
        ax_offset.plot(offsets[coarse_best], costs[coarse_best], "v", color="tab:red", ms=9,
                       label=f"coarse minimum {offsets[coarse_best]:.0f} ms")
        ax_offset.set_yscale("log")
        ax_offset.set_xlim(float(offsets.min()), float(offsets.max()))
    ax_offset.set(xlabel="clock offset (ms): tracker_stamp = camera_time + offset",
                  ylabel="cost (log)", title="time-offset search")
    ax_offset.legend(fontsize=8, loc="upper center")

    ax_text.axis("off")
    ax_text.text(0.0, 1.0, "\n".join(handeye_text(result, inputs)), va="top", ha="left",
                 family="monospace", fontsize=7.5, transform=ax_text.transAxes)
    figure.suptitle("endo-handeye: hand–eye and clock calibration")
    figure.tight_layout()
    return figure


def handeye_text(result: HandEyeResult, inputs: dict[str, Any] | None) -> list[str]:
    """The report's text column: inputs, then results, one item a line."""
    inputs = inputs or {}
    lines = ["INPUTS"]
    source = inputs.get("input") or {}
    if source:
        lines += [f"file: {source.get('file')}", f"  {int(source.get('size_bytes', 0)):,} bytes",
                  f"  sha256 {str(source.get('sha256', ''))[:16]}…"]
    for key, value in (inputs.get("topics") or {}).items():
        lines.append(f"topic {key}: {value}")
    camera = inputs.get("camera_info") or {}
    if camera:
        lines.append(f"camera_info: {camera.get('width')}x{camera.get('height')}, "
                     f"{camera.get('distortion_model') or 'no'} distortion")
    board = inputs.get("board") or {}
    if board:
        lines.append(f"board: {board.get('inner_corners')} inner corners")
        lines.append(f"  ({board.get('size_source')})")
        lines.append(f"  square {float(board.get('square_mm', 0.0)):.3f} mm")
        lines.append(f"  ({board.get('square_source')})")
    tool = inputs.get("tool") or {}
    if tool:
        lines.append(f"{tool.get('program')} {tool.get('endo3d_version')}, {tool.get('date')}")
    used = np.asarray(result.view_used, dtype=bool)
    lines += ["", "RESULT", f"method: {result.method}",
              f"views used {result.views_used} of {result.views_total}",
              f"time offset {result.time_offset_ns / MS:.3f} ms",
              f"reprojection RMS {result.reprojection_rms_px:.3f} px",
              f"tracker residual {result.translation_rms_mm:.3f} mm, "
              f"{result.rotation_rms_deg:.3f} deg",
              "T_marker_camera translation (mm):",
              "  " + np.array2string(result.T_marker_camera[:3, 3] * 1e3, precision=3)]
    stamps = np.asarray(result.view_stamps_ns, dtype=np.int64)
    rejected = np.flatnonzero(~used)
    if rejected.size:
        lines.append(f"rejected views ({rejected.size}):")
        for index in rejected[:12]:
            seconds = (stamps[index] - stamps.min()) * 1e-9
            residual = result.view_translation_mm[index]
            why = f"{residual:.2f} mm off" if np.isfinite(residual) else "no tracker pose"
            lines.append(f"  view {index} at {seconds:.2f} s: {why}")
    else:
        lines.append("rejected views: none")
    return lines
