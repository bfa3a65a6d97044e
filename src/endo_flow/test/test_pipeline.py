"""FlowPipeline on rendered abdomen frames: scale, metric depth and world points vs truth."""

from __future__ import annotations

import numpy as np
import pytest

from endo_flow.errors import FlowInputError, NoFeaturesError
from endo_flow.pipeline import FlowFrame, FlowPipeline
from endo_flow.scale import ScaleState
from endo_io.errors import ClockJumpError, PoseError
from endo_io.pose import invert_transform, transform_points


def test_true_poses_give_the_scale_depth_and_cloud(moving, kit):
    pipe = FlowPipeline(kit.options())
    outputs = [pipe.process(frame) for frame in moving.frames(moving.poses)]
    last = outputs[-1]
    assert last.scale.usable and last.scale.state == ScaleState.TRACKING
    assert abs(last.scale.value / kit.S_TRUE - 1.0) < 0.01
    truth = moving.depths[-1]
    ok = np.isfinite(truth) & np.isfinite(last.depth)
    assert ok.mean() > 0.5
    assert np.median(np.abs(last.depth[ok] / truth[ok] - 1.0)) < 0.01
    # the world cloud lies on the true surface: back into the camera, its depth is the truth
    local = transform_points(invert_transform(moving.poses[-1]), last.points)
    uv = moving.camera.project(local)
    col, row = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    z_true = truth[row, col]
    assert len(last.points) > 1000 and last.intensity.dtype == np.uint8
    assert np.nanmedian(np.abs(local[:, 2] - z_true)) < 0.5e-3
    assert len(pipe.voxel_map) > 1000
    first_usable = next(i for i, o in enumerate(outputs) if o.depth is not None)
    assert all(o.depth is None and not o.scale.usable for o in outputs[:first_usable])


def test_bad_frames_raise_one_named_error_and_the_pipeline_continues(moving, kit):
    frames = moving.frames(moving.poses)
    pipe = FlowPipeline(kit.options())
    for frame in frames[:5]:
        pipe.process(frame)
    f = frames[5]
    with pytest.raises(FlowInputError, match="camera_info is 320x240"):
        pipe.process(FlowFrame(f.stamp_ns, f.image, f.depth_relative[:-2], f.camera,
                               f.T_world_camera))
    bad_pose = f.T_world_camera.copy()
    bad_pose[0, 3] = np.nan
    with pytest.raises(PoseError):
        pipe.process(FlowFrame(f.stamp_ns, f.image, f.depth_relative, f.camera, bad_pose))
    black = np.zeros_like(f.image)
    with pytest.raises(NoFeaturesError):
        pipe.process(FlowFrame(f.stamp_ns, black, f.depth_relative, f.camera, f.T_world_camera))
    out = pipe.process(frames[6])
    assert out.diagnostics.tracks > 50  # re-seeded after the black frame
    with pytest.raises(ClockJumpError):
        pipe.process(frames[0])
    assert pipe.resets == 1 and len(pipe.window) == 0
    assert pipe.process(frames[1]).diagnostics.seeded > 50
