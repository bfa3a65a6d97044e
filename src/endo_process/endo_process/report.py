"""``endo-process --report report.png``: one figure of a scored run.

Panels (matplotlib, Agg):

* top row, the last frame that has ground truth and metric depth: the
  corrected image, the relative depth, the metric depth, and the error map
  ``|depth − truth| / truth``;
* bottom left, that frame's world points in 3-D, coloured by their distance
  to the true surface (:func:`endo_process.accuracy.cloud_distances`);
* bottom middle, the scale over time with its ±1σ band (``exp(±std ln s)``)
  and the oracle scale;
* bottom right, the photometric calibration: the inverse response g(v) and
  the light map L(x).

Without ground truth (a real rig's recording) the top row is the last frame
with metric depth, its points are coloured by world z, and the error panel
says there is no truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from endo_calib.calibration import PhotometricCalibration
from endo_io import topics
from endo_io.bag import BagReader
from endo_io.bag.streams import read_depth_frames, read_pose_stream
from endo_io.camera import CameraModel
from endo_io.pointcloud import pointcloud2_to_xyz
from endo_process.accuracy import Accuracy, cloud_distances, messages_at, read_scale_stream


def _frame_stamp(accuracy: Accuracy, recording: Path) -> int | None:
    """The frame the top row shows: the last one scored against the truth.

    Without ground truth (a real rig's recording), the last frame with metric
    depth, else with relative depth: the frames are drawn all the same (they
    were "not available" before, on every recording without truth). An
    endo-process output logs each frame at its header stamp, so the log
    times name the frames without decoding them.
    """
    for errors in (accuracy.metric, accuracy.relative):
        if errors:
            return max(errors)
    with BagReader(recording) as reader:
        for topic in (topics.DEPTH, topics.DEPTH_RELATIVE):
            if topic in reader.topics:
                stamps = [message.log_time_ns for message in reader.messages([topic])]
                if stamps:
                    return max(stamps)
    return None


def _range(image: np.ndarray | None) -> dict[str, Any]:
    """Colour limits at the 2nd and 98th percentiles (the far lumen would take the scale)."""
    if image is None or not np.isfinite(image).any():
        return {}
    low, high = np.nanpercentile(image, [2.0, 98.0])
    return {"vmin": float(low), "vmax": float(high)}


def _image(
    axis: Any,
    image: np.ndarray | None,
    title: str,
    unit: str,
    *,
    missing: str = "not available",
    **style: Any,
) -> None:
    """One image panel; ``unit`` labels its colour bar, ``missing`` says why there is no image."""
    axis.set_title(title, fontsize=9)
    axis.axis("off")
    if image is None:
        axis.text(0.5, 0.5, missing, ha="center", va="center", transform=axis.transAxes)
        return
    shown = axis.imshow(image, **style)
    plt.colorbar(shown, ax=axis, fraction=0.046, pad=0.02).set_label(unit, fontsize=8)


def write_report_figure(
    recording: Path, accuracy: Accuracy, calibration: Path, path: Path
) -> Path:
    """Draw the figure of a run's output ``recording`` into ``path`` (PNG); returns ``path``."""
    figure = plt.figure(figsize=(16, 8.5), constrained_layout=True)
    grid = figure.add_gridspec(2, 4)
    stamp = _frame_stamp(accuracy, recording)
    frames: dict[str, np.ndarray | None] = dict.fromkeys(
        ("image", "relative", "metric", "truth"), None
    )
    if stamp is not None:
        for key, topic in (("image", topics.IMAGE_CORRECTED), ("relative", topics.DEPTH_RELATIVE),
                           ("metric", topics.DEPTH), ("truth", topics.TRUE_DEPTH)):  # fmt: skip
            frames[key] = read_depth_frames(recording, topic, {stamp},
                                            irradiance=key == "image").get(stamp)
    scale_stamps, scale = read_scale_stream(recording)
    start = int(scale_stamps[0]) if len(scale_stamps) else (stamp or 0)
    # The top row is one frame: the first panel says which, the others say "that frame".
    when = "" if stamp is None else f" at t = {(stamp - start) / 1e9:.2f} s"
    _image(figure.add_subplot(grid[0, 0]), frames["image"], f"corrected image{when}",
           "linear irradiance", cmap="gray")  # fmt: skip
    _image(figure.add_subplot(grid[0, 1]), frames["relative"], "relative depth (SFS; white: none)",
           "relative depth (no unit)", cmap="viridis", **_range(frames["relative"]))  # fmt: skip
    metric, truth = frames["metric"], frames["truth"]
    at_stamp = scale[scale_stamps == stamp] if stamp is not None else scale[:0]
    used = f", scale {at_stamp[0]:.4g} m per unit" if np.isfinite(at_stamp).any() else ""
    _image(figure.add_subplot(grid[0, 2]), metric, f"metric depth{used}", "depth (m)",
           cmap="viridis", **_range(truth if truth is not None else metric))  # fmt: skip
    error = None
    if metric is not None and truth is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            error = np.abs(metric - truth) / truth
    title = "|depth − truth| / truth"
    if stamp is not None and stamp in accuracy.metric:
        title += f" (here AbsRel {accuracy.metric[stamp].abs_rel:.3f})"
    _image(figure.add_subplot(grid[0, 3]), error, title, "relative error (fraction)",
           missing="not available" if accuracy.has_truth else "no ground truth in the recording",
           cmap="magma", vmin=0.0, vmax=0.3)  # fmt: skip

    cloud_axis = figure.add_subplot(grid[1, 0:2], projection="3d")
    _cloud_panel(cloud_axis, recording, stamp, truth)
    _scale_panel(figure.add_subplot(grid[1, 2]), recording, accuracy)
    _calibration_panel(figure, grid[1, 3], calibration)
    figure.suptitle(f"endo-process: {Path(recording).name}\n{headline(accuracy)}", fontsize=12)
    figure.savefig(path, dpi=90)
    plt.close(figure)
    return Path(path)


def _frames(count: int) -> str:
    """How many ground-truth frames a mean is over (the truth may be sparse: 3 of 90)."""
    return f"mean of {count} truth frame{'s' if count != 1 else ''}"


def headline(accuracy: Accuracy) -> str:
    """The run's key accuracy figures on one line (the figure's subtitle); "" without truth.

    Each mean says over how many ground-truth frames it is.
    """
    parts: list[str] = []
    if accuracy.metric:
        errors = list(accuracy.metric.values())
        parts.append(f"metric depth AbsRel {np.mean([e.abs_rel for e in errors]):.3f}, "
                     f"MAE {np.mean([e.mae for e in errors]) * 1e3:.1f} mm "
                     f"({_frames(len(errors))})")  # fmt: skip
    elif accuracy.relative:
        relative = np.mean([e.abs_rel for e in accuracy.relative.values()])
        parts.append(f"relative depth AbsRel {relative:.3f} ({_frames(len(accuracy.relative))})")
    if accuracy.cloud_rms_m:
        rms = np.mean(list(accuracy.cloud_rms_m.values())) * 1e3
        parts.append(f"cloud RMS {rms:.1f} mm ({_frames(len(accuracy.cloud_rms_m))})")
    if accuracy.scale is not None:
        error = accuracy.scale.relative_error[np.isfinite(accuracy.scale.relative_error)]
        if len(error):
            parts.append(f"final scale {error[-1]:+.1%} vs the truth")
    poses = accuracy.poses
    if poses is not None and poses.compared:
        parts.append(f"camera pose {np.median(poses.position_mm):.2f} mm / "
                     f"{np.median(poses.rotation_deg):.2f}° (median)")  # fmt: skip
    return " · ".join(parts)


def _cloud_panel(axis: Any, recording: Path, stamp: int | None, truth: np.ndarray | None) -> None:
    """That frame's world points, coloured by their distance to the true surface.

    Without the truth at that frame (a recording of a real rig) they are
    coloured by their world z, and the title says so.
    """
    axis.set_title("world points of that frame (2nd-98th percentile box), distance to the true "
                   "surface (mm)", fontsize=9)  # fmt: skip
    if stamp is None:
        return
    cloud = messages_at(recording, topics.POINTS, {stamp}).get(stamp)
    info = messages_at(recording, topics.CAMERA_INFO, {stamp}).get(stamp)
    if cloud is None:
        axis.text2D(0.5, 0.5, "not available", ha="center", transform=axis.transAxes)
        return
    points, _ = pointcloud2_to_xyz(cloud)
    points = points.reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        axis.text2D(0.5, 0.5, "no finite point", ha="center", transform=axis.transAxes)
        return
    millimetres = points * 1e3
    true_stamps, true_poses = read_pose_stream(recording, topics.TRUE_CAMERA_POSE)
    if truth is not None and info is not None and stamp in set(true_stamps.tolist()):
        pose = true_poses[true_stamps.tolist().index(stamp)]
        colour = cloud_distances(points, truth, CameraModel.from_camera_info(info), pose) * 1e3
        label, low_colour = "distance to the true surface (mm)", 0.0
    else:
        axis.set_title("world points of that frame (2nd-98th percentile box), coloured by "
                       "world z (mm): no ground truth", fontsize=9)  # fmt: skip
        colour = millimetres[:, 2]
        label, low_colour = "world z (mm)", float(np.percentile(colour, 2))
    # The view spans the bulk of the surface: a few far points in the lumen
    # would otherwise shrink it to a corner of the box.
    low, high = np.percentile(millimetres, [2.0, 98.0], axis=0)
    inside = np.all((millimetres >= low) & (millimetres <= high), axis=1)
    top = max(low_colour + 1e-3, float(np.percentile(colour, 98)))
    shown = axis.scatter(*millimetres[inside].T, c=colour[inside], s=0.5, cmap="turbo",
                         vmin=low_colour, vmax=top)  # fmt: skip
    axis.view_init(elev=20.0, azim=-60.0)
    axis.set_xlabel("x (mm)")
    axis.set_ylabel("y (mm)")
    axis.set_zlabel("z (mm)")
    plt.colorbar(shown, ax=axis, fraction=0.03, pad=0.08).set_label(label, fontsize=8)


def _scale_panel(axis: Any, recording: Path, accuracy: Accuracy) -> None:
    axis.set_title("scale over time", fontsize=9)
    stamps, scale, log_std = read_scale_stream(recording, with_std=True)
    if len(stamps) == 0:
        axis.text(0.5, 0.5, "no scale topic", ha="center", transform=axis.transAxes)
        return
    t = (stamps - stamps[0]) / 1e9
    axis.plot(t, scale, color="C0", label="estimate")
    axis.fill_between(t, scale * np.exp(-log_std), scale * np.exp(log_std), color="C0",
                      alpha=0.25, label="±1σ")  # fmt: skip
    if np.isfinite(accuracy.oracle_scale):
        axis.axhline(accuracy.oracle_scale, color="k", ls="--", label="oracle (truth)")
        finite = scale[np.isfinite(scale)]
        if len(finite):
            span = np.percentile(np.abs(finite / accuracy.oracle_scale - 1.0), 95)
            margin = accuracy.oracle_scale * max(0.05, 1.3 * span)
            axis.set_ylim(accuracy.oracle_scale - margin, accuracy.oracle_scale + margin)
    axis.set_xlabel("time from the first frame (s)")
    axis.set_ylabel("metres per unit of relative depth")
    axis.legend(fontsize=8)


def _calibration_panel(figure: Any, cell: Any, calibration: Path) -> None:
    inner = cell.subgridspec(2, 1)
    response, light = figure.add_subplot(inner[0]), figure.add_subplot(inner[1])
    cal = PhotometricCalibration.load(calibration)
    g = cal.inverse_response
    response.plot(np.arange(len(g)), g if g.ndim == 1 else g[:, 1])
    response.set_title("calibration: inverse response g(v)", fontsize=9)
    response.set_xlabel("raw value")
    response.set_ylabel("irradiance")
    light_map = cal.light_map if cal.light_map.ndim == 2 else cal.light_map[..., 1]
    _image(light, light_map, "light map L(x)", "relative to its peak", cmap="inferno",
           vmin=0.0, vmax=1.0)  # fmt: skip
