"""With shading workers endo-process's kernels run on one thread: same output, counts restored."""

from __future__ import annotations

from pathlib import Path

import cv2
import numba
import numpy as np
import pytest

from endo_flow.pipeline import FlowFrame, FlowOptions, FlowOutput, FlowPipeline
from endo_io import topics
from endo_io.bag import BagReader, deserialize
from endo_io.camera import CameraModel
from endo_io.errors import PoseLookupError
from endo_io.image import image_to_array
from endo_io.pose import pose_to_matrix
from endo_io.pose_buffer import PoseBuffer
from endo_io.stamp import stamp_to_ns
from endo_process.runner import single_threaded_kernels

from .conftest import process_first_frames

FRAMES = 16


def _counts() -> tuple[int, int]:
    return cv2.getNumThreads(), numba.get_num_threads()


def test_single_threaded_kernels_sets_one_thread_and_restores_the_counts() -> None:
    before = _counts()
    with single_threaded_kernels():
        assert _counts() == (1, 1)
    assert _counts() == before
    with pytest.raises(RuntimeError), single_threaded_kernels():
        raise RuntimeError("the block failed")
    assert _counts() == before


def _flow_frames(run: Path) -> list[FlowFrame]:
    """The run's corrected images and relative depth, with the camera pose at each stamp."""
    with BagReader(run) as bag:
        images = [image_to_array(deserialize(m)) for m in bag.messages([topics.IMAGE_CORRECTED])]
        depth = [deserialize(m) for m in bag.messages([topics.DEPTH_RELATIVE])]
        info = deserialize(next(bag.messages([topics.CAMERA_INFO])))
        poses = PoseBuffer(capacity=6000, max_gap_ns=200_000_000)
        for m in bag.messages([topics.CAMERA_POSE]):
            T, stamp = pose_to_matrix(deserialize(m))
            poses.insert(stamp, T)
    camera = CameraModel.from_camera_info(info)
    frames = []
    for image, message in zip(images, depth, strict=True):
        stamp = stamp_to_ns(message.header.stamp)
        try:
            T = poses.query(stamp)
        except PoseLookupError:  # before the first tracker sample
            T = None
        frames.append(FlowFrame(stamp, image, image_to_array(message), camera, T))
    return frames


def _run(frames: list[FlowFrame]) -> list[FlowOutput]:
    pipeline = FlowPipeline(FlowOptions())
    return [pipeline.process(frame) for frame in frames]


def test_the_flow_step_gives_the_same_output_on_one_thread(
    calibrations: tuple[Path, Path], phantom_params: Path, tmp_path: Path
) -> None:
    run = process_first_frames(tmp_path / "run.mcap", calibrations, phantom_params, FRAMES)
    frames = _flow_frames(run)
    assert sum(frame.T_world_camera is not None for frame in frames) >= FRAMES - 2
    default = _run(frames)
    with single_threaded_kernels():
        single = _run(frames)
    assert sum(len(out.triangulated) for out in default) > 20  # tracking and triangulation ran
    assert min(out.diagnostics.tracks for out in default) > 50
    for a, b in zip(default, single, strict=True):
        assert a.diagnostics.tracks == b.diagnostics.tracks
        assert a.diagnostics.seeded == b.diagnostics.seeded
        np.testing.assert_array_equal(a.triangulated, b.triangulated)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.scale.value, b.scale.value)  # NaN == NaN here
        assert (a.depth is None) == (b.depth is None)
        if a.depth is not None and b.depth is not None:
            np.testing.assert_array_equal(a.depth, b.depth)
