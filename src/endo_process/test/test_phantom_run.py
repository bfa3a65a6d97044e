"""endo-process over the whole phantom bag: accuracy against the truth, and --jobs agreement.

Thresholds: relative depth AbsRel (median-scaled) as issue 5's bar for the
SFS stage (≤ 0.08 on the mean; measured 0.0797 at solve_scale 0.5 here,
tuned on this bag by the SFS work; the held-out seed-7 rendering gave 0.081
at full resolution, docs/sfs.md); camera poses within the tracker's noise
through the hand–eye lever arm (measured median 0.35 mm, 0.08°). The flow
figures (metric depth, cloud, scale) are endo_flow's; the bounds here are
loose checks of the wiring with real numbers (measured on this bag: metric
AbsRel 0.0796, 0.0006 from the oracle-scaled figure, cloud RMS 3.1 mm,
final scale −4.1 % from the oracle), not endo_flow's acceptance bars.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pytest

from endo_io import topics
from endo_io.bag import BagReader
from endo_io.bag.streams import read_depth_frames
from endo_process.accuracy import Accuracy, messages_at, read_scale_stream, score_recording
from endo_process.report import headline, write_report_figure
from endo_process.runner import LOOP_STAGES, ProcessOptions, ProcessReport, process_bag
from endo_process.summary import summary_document
from endo_sfs.options import DEFAULT_TOLERANCE, agreement_bound

from .conftest import PHANTOM, process_first_frames


@pytest.fixture(scope="module")
def full_run(
    calibrations: tuple[Path, Path], phantom_params: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[ProcessReport, Path]:
    """All 90 frames at solve_scale 0.5 with the default --jobs 2: two workers taking turns."""
    output = tmp_path_factory.mktemp("full") / "phantom.mcap"
    report = process_bag(ProcessOptions(
        bag=PHANTOM, output=output, calibration=calibrations[0], handeye=calibrations[1],
        params=phantom_params, solve_scale=0.5, jobs=2, progress=False,
        ply=output.with_suffix(".ply"),
    ))  # fmt: skip
    return report, output


#: Frames of the one-chain run the other --jobs are compared with.
CHAIN_FRAMES = 18


@pytest.fixture(scope="module")
def one_chain(
    calibrations: tuple[Path, Path], phantom_params: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    """The first frames with --jobs 1: one warm-started chain in this process."""
    output = tmp_path_factory.mktemp("one") / "one.mcap"
    return process_first_frames(output, calibrations, phantom_params, CHAIN_FRAMES)


def assert_same_depth_to_the_solver_tolerance(one: Path, other: Path) -> None:
    """Every relative depth of ``one`` matches ``other``'s to the solver's tolerance."""
    bound = agreement_bound(DEFAULT_TOLERANCE)
    first = read_depth_frames(one, topics.DEPTH_RELATIVE)
    second = read_depth_frames(other, topics.DEPTH_RELATIVE, set(first))
    assert sorted(first) == sorted(second)
    compared = beyond = 0
    for stamp in first:
        a, b = first[stamp], second[stamp]
        np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
        valid = np.isfinite(a)
        relative = np.abs(a[valid] - b[valid]) / a[valid]
        # The sweeps stop at the default tolerance τ in ln r; two solves of a
        # frame from other starts differ within its documented spread
        # (endo_sfs.options.agreement_bound; docs/sfs.md, "Speed").
        assert np.percentile(relative, 99.9) <= bound.p999
        assert relative.max() <= bound.largest
        assert np.median(relative) <= bound.median
        compared += relative.size
        beyond += int(np.count_nonzero(relative > 1e-2))
    # bound.largest (10·√τ = 0.1) holds for any single pixel; beyond 1 % only a
    # rare few may go: 12 of 6.9 M pixels over the phantom's 90 frames at 0.5
    # (docs/sfs.md, "Speed", session 14), so a defect that puts one pixel per
    # frame a few % off fails here (review, session 14).
    assert beyond <= 1e-5 * compared, (beyond, compared)


def test_every_frame_is_processed_and_the_truth_copied(full_run: tuple[ProcessReport, Path]):
    report, output = full_run
    assert report.frames_in == report.frames_shaded == 90
    assert not report.dropped and report.damage is None and not report.interrupted
    # The first image (t = 0) is before the first tracker sample (4 ms): no pose.
    assert report.frames_with_pose == 89
    assert dict(report.without_pose) == {"PoseBeforeStreamError": 1}
    with BagReader(output) as reader:
        counts = {name: info.message_count for name, info in reader.topics.items()}
    assert counts[topics.IMAGE_CORRECTED] == counts[topics.DEPTH_RELATIVE] == 90
    assert counts[topics.CAMERA_INFO] == 90
    assert counts[topics.CAMERA_POSE] == 180
    assert counts[topics.TRUE_DEPTH] == 3 and counts[topics.TRUE_CAMERA_POSE] == 90
    # Flow: every frame, metric depth once the scale is usable, one map at the end.
    assert report.frames_flow == 90 and not report.flow_dropped
    assert counts[topics.SCALE] == 90
    assert 40 <= counts[topics.DEPTH] == report.frames_metric < 90
    assert counts[topics.POINTS] >= counts[topics.DEPTH] - 1
    assert counts[topics.MAP] == 1 and report.map_points > 10_000
    # Where the time went: every step of the loop was timed, and the workers'
    # correction and SFS steps came back with their frames; the steps fit in the loop.
    assert set(report.stage_seconds) <= set(LOOP_STAGES)
    assert all(report.stage_seconds[name] > 0.0 for name in ("read", "shading", "write", "flow"))
    assert sum(report.stage_seconds.values()) <= report.seconds
    # Their CPU in the loop's thread: the same steps, within the process's loop CPU.
    assert set(report.stage_cpu_seconds) == set(report.stage_seconds)
    assert report.stage_cpu_seconds["flow"] > 0.0
    assert sum(report.stage_cpu_seconds.values()) <= report.loop_cpu_seconds + 1e-3
    assert 0.0 < report.first_frame_seconds < report.seconds
    assert report.steady_real_time_factor > 0.0
    assert report.shading_seconds["correct"] > 0.0
    assert report.shading_seconds["sfs.sweeps"] < report.shading_seconds["solve"]


def read_ply_vertices(path: Path) -> np.ndarray:
    """The vertex table of a binary little-endian PLY as a structured array."""
    types = {"float": "<f4", "uchar": "u1", "uint": "<u4"}
    with path.open("rb") as stream:
        fields, count = [], 0
        while (line := stream.readline().decode("ascii").strip()) != "end_header":
            words = line.split()
            if words[:2] == ["element", "vertex"]:
                count = int(words[2])
            elif words[0] == "property":
                fields.append((words[2], types[words[1]]))
        return np.frombuffer(stream.read(), dtype=fields, count=count)


def test_points_as_live_and_the_map_at_full_resolution(
    full_run: tuple[ProcessReport, Path],
) -> None:
    """Offline as live: points every 4th pixel, the map every pixel of every 8th frame."""
    report, output = full_run
    depths = read_depth_frames(output, topics.DEPTH)
    clouds = messages_at(output, topics.POINTS, set(depths))
    assert len(clouds) >= len(depths) - 1
    in_range_per_frame = []
    for stamp in sorted(clouds):
        depth = depths[stamp]
        in_range = np.isfinite(depth) & (depth >= 1e-3) & (depth <= 0.3)
        # the live topic's cloud_decimation (4): one point per 4x4 block's corner in range
        assert clouds[stamp].width * clouds[stamp].height == in_range[::4, ::4].sum() > 0  # type: ignore[attr-defined]
        in_range_per_frame.append(int(in_range.sum()))
    # the map: every pixel in range (map_decimation 1) of every 8th frame with points
    # (map_every 8, the live node's), none evicted
    vertices = read_ply_vertices(output.with_suffix(".ply"))
    assert len(vertices) == report.ply_vertices == report.map_points
    fused = sum(in_range_per_frame[::8])
    assert int(vertices["count"].sum()) == fused > 0.3 * 640 * 480 * len(in_range_per_frame[::8])
    # ~10-60 points per 1 mm voxel at the phantom's 20-60 mm (a 640x480 pixel is ~0.1 mm there)
    assert fused > 5 * len(vertices)


def assert_same_accuracy(streamed: Accuracy, read_back: Accuracy) -> None:
    """Every figure of two scorings equal, to the bit."""
    assert streamed.truth_frames == read_back.truth_frames
    for name in ("relative", "oracle", "metric", "cloud_rms_m"):
        assert getattr(streamed, name) == getattr(read_back, name), name
    assert streamed.oracle_scale == read_back.oracle_scale
    assert streamed.poses is not None and read_back.poses is not None
    assert (streamed.poses.compared, streamed.poses.missing) == (
        read_back.poses.compared, read_back.poses.missing)  # fmt: skip
    np.testing.assert_array_equal(streamed.poses.position_mm, read_back.poses.position_mm)
    np.testing.assert_array_equal(streamed.poses.rotation_deg, read_back.poses.rotation_deg)
    assert streamed.scale is not None and read_back.scale is not None
    np.testing.assert_array_equal(streamed.scale.stamps_ns, read_back.scale.stamps_ns)
    np.testing.assert_array_equal(streamed.scale.scale, read_back.scale.scale)
    assert streamed.true_positions is not None and read_back.true_positions is not None
    for mine, theirs in zip(streamed.true_positions, read_back.true_positions, strict=True):
        np.testing.assert_array_equal(mine, theirs)


def test_accuracy_against_the_ground_truth(full_run: tuple[ProcessReport, Path]) -> None:
    accuracy = score_recording(full_run[1])
    # endo-process scored its output as it wrote it: the same figures as reading it back
    assert full_run[0].accuracy is not None
    assert_same_accuracy(full_run[0].accuracy, accuracy)
    assert len(accuracy.relative) == 3
    abs_rel = [e.abs_rel for e in accuracy.relative.values()]
    assert np.mean(abs_rel) <= 0.08 and max(abs_rel) <= 0.085, abs_rel
    assert min(e.coverage for e in accuracy.relative.values()) > 0.8
    # The relative depth's unit: √ρ·(true depth) for albedo × light ρ; one scale fits all.
    assert 0.005 < accuracy.oracle_scale < 0.05
    poses = accuracy.poses
    assert poses is not None and poses.compared == 89
    assert np.median(poses.position_mm) < 0.6 and np.percentile(poses.position_mm, 95) < 1.2
    assert np.median(poses.rotation_deg) < 0.15
    # Metric depth (no scaling) at the truth frames the scale has reached.
    assert len(accuracy.metric) >= 2
    metric = np.mean([e.abs_rel for e in accuracy.metric.values()])
    oracle = np.mean([accuracy.oracle[s].abs_rel for s in accuracy.metric])
    assert metric <= 0.10 and abs(metric - oracle) <= 0.02, (metric, oracle)
    assert all(e.mae < 0.01 for e in accuracy.metric.values())  # metres
    assert len(accuracy.cloud_rms_m) >= 2 and max(accuracy.cloud_rms_m.values()) < 0.005
    assert accuracy.scale is not None
    error = accuracy.scale.relative_error
    assert abs(error[np.isfinite(error)][-1]) < 0.10
    # --summary-json carries the same figures, as strict JSON.
    document = json.loads(json.dumps(summary_document(full_run[0], accuracy), allow_nan=False))
    assert document["frames"]["with_pose"] == 89
    assert document["accuracy"]["metric_abs_rel_mean"] == pytest.approx(metric)
    assert document["accuracy"]["pose"]["compared"] == 89
    assert len(document["accuracy"]["scale"]["value"]) == 90
    scale = document["accuracy"]["scale"]
    assert scale["final_relative_error"] == pytest.approx(error[np.isfinite(error)][-1])
    assert scale["usable_frames"] == np.isfinite(error).sum()
    assert document["tracker"]["pose_buffer_events"] == {}


def test_report_figure(
    full_run: tuple[ProcessReport, Path],
    calibrations: tuple[Path, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import endo_process.report

    accuracy = score_recording(full_run[1])
    drawn: list[Any] = []
    monkeypatch.setattr(endo_process.report.plt, "close", drawn.append)  # keep it to read
    figure = write_report_figure(full_run[1], accuracy, calibrations[0], tmp_path / "report.png")
    # The subtitle gives the headline figures, the same numbers as the summary,
    # and says over how many truth frames each mean is (the phantom has 3 of 90).
    line = headline(accuracy)
    metric = np.mean([e.abs_rel for e in accuracy.metric.values()])
    frames = len(accuracy.metric)
    assert f"metric depth AbsRel {metric:.3f}" in line
    assert f"mm (mean of {frames} truth frames)" in line
    rms_mm = np.mean(list(accuracy.cloud_rms_m.values())) * 1e3
    assert f"cloud RMS {rms_mm:.1f} mm (mean of {len(accuracy.cloud_rms_m)} truth frames)" in line
    assert "final scale" in line and "camera pose" in line
    # Every colour bar says what its colours are, in which unit; the metric depth
    # names the scale of its frame (the flow's estimate at that stamp).
    (shown,) = drawn
    titles = [axis.get_title() for axis in shown.axes]
    labels = {axis.get_ylabel() for axis in shown.axes} | {axis.get_zlabel()
              for axis in shown.axes if hasattr(axis, "get_zlabel")}  # fmt: skip
    assert {"linear irradiance", "relative depth (no unit)", "depth (m)",
            "relative error (fraction)", "distance to the true surface (mm)",
            "relative to its peak"} <= labels  # fmt: skip
    stamp = max(accuracy.metric)
    stamps, scale = read_scale_stream(full_run[1])
    used = scale[stamps == stamp][0]
    assert f"metric depth, scale {used:.4g} m per unit" in titles
    assert f"corrected image at t = {(stamp - stamps[0]) / 1e9:.2f} s" in titles
    assert f"|depth − truth| / truth (here AbsRel {accuracy.metric[stamp].abs_rel:.3f})" in titles
    monkeypatch.undo()
    plt.close(shown)
    image = plt.imread(figure)
    assert image.shape[0] > 600 and image.shape[1] > 1200
    assert image[..., :3].std() > 0.1  # drawn, not blank


def test_report_of_a_recording_without_ground_truth_draws_its_frames(
    calibrations: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A real rig's recording has no ground truth: its frames were all "not available".

    The top row showed no corrected image, no relative and no metric depth and the
    3-D panel no point, although the output held them all; now the last frame with
    metric depth is drawn, its points coloured by world z, the error panel says why
    it is empty.
    """
    import endo_process.report
    from endo_io.bag import BagWriter

    bag = tmp_path / "rig.mcap"  # the phantom's first 40 frames without /ground_truth/*
    with BagReader(PHANTOM) as reader, BagWriter(bag) as writer:
        kept = [t for t in reader.topics if not t.startswith("/ground_truth")]
        for name in kept:
            writer.add_topic(name, reader.topics[name].msgtype)
        images = 0
        for message in reader.messages(kept):
            images += message.topic == topics.IMAGE_RAW
            if images > 40:
                break
            writer.write(message.topic, message.data, message.log_time_ns)
    output = tmp_path / "rig_out.mcap"
    process_bag(ProcessOptions(
        bag=bag, output=output, calibration=calibrations[0], handeye=calibrations[1],
        solve_scale=0.5, jobs=1, progress=False,
    ))  # fmt: skip
    accuracy = score_recording(output)
    assert not accuracy.has_truth
    with BagReader(output) as reader:
        last_metric = max(m.log_time_ns for m in reader.messages([topics.DEPTH]))
    drawn: list[Any] = []
    monkeypatch.setattr(endo_process.report.plt, "close", drawn.append)
    write_report_figure(output, accuracy, calibrations[0], tmp_path / "report.png")
    (shown,) = drawn
    panels = {axis.get_title(): axis for axis in shown.axes if axis.get_title()}
    stamps = read_scale_stream(output)[0]
    image = panels[f"corrected image at t = {(last_metric - stamps[0]) / 1e9:.2f} s"]
    assert len(image.images) == 1
    assert len(panels["relative depth (SFS; white: none)"].images) == 1
    (metric,) = [axis for title, axis in panels.items() if title.startswith("metric depth, scale")]
    assert len(metric.images) == 1
    error = panels["|depth − truth| / truth"]
    assert [t.get_text() for t in error.texts] == ["no ground truth in the recording"]
    labels = {axis.get_ylabel() for axis in shown.axes}
    assert "world z (mm)" in labels
    monkeypatch.undo()
    plt.close(shown)


def test_one_and_two_jobs_agree_to_the_solver_tolerance(
    full_run: tuple[ProcessReport, Path], one_chain: Path
) -> None:
    """Two workers warm-start each frame from the frame two back: the same fixed point."""
    assert_same_depth_to_the_solver_tolerance(one_chain, full_run[1])
    # The flow step sees depths that differ that little: its scale follows.
    scale_one = read_scale_stream(one_chain)
    scale_two = read_scale_stream(full_run[1])
    both = np.isfinite(scale_one[1]) & np.isfinite(scale_two[1][:CHAIN_FRAMES])
    assert both.sum() >= 5
    np.testing.assert_array_equal(scale_one[0], scale_two[0][:CHAIN_FRAMES])
    np.testing.assert_allclose(scale_one[1][both], scale_two[1][:CHAIN_FRAMES][both], rtol=1e-3)


def test_turns_of_several_frames_agree_to_the_solver_tolerance(
    calibrations: tuple[Path, Path], phantom_params: Path, one_chain: Path, tmp_path: Path
) -> None:
    """--chunk-frames 4: turns of four frames, each started cold, still the same depth."""
    output = tmp_path / "turns.mcap"
    report = process_bag(ProcessOptions(
        bag=PHANTOM, output=output, calibration=calibrations[0], handeye=calibrations[1],
        params=phantom_params, solve_scale=0.5, jobs=2, chunk_frames=4, max_frames=12,
        progress=False,
    ))  # fmt: skip
    assert report.frames_shaded == 12
    assert_same_depth_to_the_solver_tolerance(output, one_chain)
