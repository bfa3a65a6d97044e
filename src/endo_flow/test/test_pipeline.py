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


def test_area_balanced_observation_estimates_the_whole_image_scale():
    """SFS 4 % deep at the centre and 4 % shallow at the rim, the tracks crowded at the rim.

    Each half of the disc's area carries half the pixels, so the scale that
    fits the image is the mean of the two biases (0); the tracks' plain
    mean follows their distribution.
    """
    from endo_flow.pipeline import area_balanced_weights
    from endo_flow.scale import observe_log_ratios

    rng = np.random.default_rng(1)
    radius = 240.0
    # 10 tracks inside rho² < 0.5 (inner ring), 40 outside (outer ring)
    rho = np.concatenate([np.sqrt(rng.uniform(0.0, 0.5, 10)), np.sqrt(rng.uniform(0.5, 1.0, 40))])
    phi = rng.uniform(0.0, 2 * np.pi, 50)
    uv = np.stack([320 + radius * rho * np.cos(phi), 240 + radius * rho * np.sin(phi)], axis=1)
    log_ratio = np.where(rho**2 < 0.5, -0.04, 0.04) + 0.005 * rng.standard_normal(50)
    plain = observe_log_ratios(log_ratio, np.ones(50))
    weights = area_balanced_weights(uv, np.ones(50), (320.0, 240.0), radius, rings=2)
    balanced = observe_log_ratios(log_ratio, weights)
    assert plain is not None and balanced is not None
    assert plain.log_scale > 0.02  # the rim's bias
    assert abs(balanced.log_scale) < 0.005
    np.testing.assert_allclose(weights[rho**2 < 0.5].sum(), weights[rho**2 >= 0.5].sum())
    # one zone: the weights are the input's
    same = area_balanced_weights(uv, np.arange(50.0), (320.0, 240.0), radius, rings=1)
    np.testing.assert_array_equal(same, np.arange(50.0))


def test_column_nanmedian_matches_numpy():
    from endo_flow.pipeline import column_nanmedian

    rng = np.random.default_rng(2)
    values = rng.normal(size=(41, 12))
    values[rng.random(values.shape) < 0.4] = np.nan
    values[:, 3] = np.nan  # a view no track was seen in
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        expected = np.nanmedian(values, axis=0)
    np.testing.assert_allclose(column_nanmedian(values), expected, equal_nan=True)
    assert np.isnan(column_nanmedian(np.empty((0, 3)))).all()


def test_keyframe_samples_follow_a_gain_step():
    """After ρ × g the kept views' depth_relative is divided by √g, like the new frames'."""
    from endo_flow.keyframes import Keyframe, KeyframeWindow

    window = KeyframeWindow(capacity=5, min_step_m=0.0)
    rays = np.tile([0.0, 0.0, 1.0], (3, 1))
    for k in range(3):
        window.add(Keyframe(k, np.eye(4), np.array([7, 8, 9]), rays, np.array([1.0, 2.0, 4.0])))
    window.scale_relative(1.2**-0.5)
    views = window.views(np.array([8]))
    assert views.relative is not None
    np.testing.assert_allclose(views.relative[0], 2.0 / np.sqrt(1.2))


@pytest.mark.parametrize(("gate", "views"), [("none", "all"), ("baseline", "all"),
                                             ("rays", "keyframes")])
def test_reprojection_observation_gives_the_scale(moving, kit, gate, views):
    """``scale_observation: reprojection`` converges to the true scale with true poses.

    No parallax gate, or the baseline one; with the tracker's noise it stays
    near the truth.

    Measured (last frame): true poses 0.04 / 0.01 / 0.01 %, tracker noise
    seed 1 1.5 / 1.4 / 1.3 % (no gate / baseline gate / keyframes only).
    """
    options = kit.options(scale_observation="reprojection", parallax_gate=gate,
                          reprojection_views=views)
    for poses, bar in ((moving.poses, 0.01), (kit.tracked_poses(moving.poses, seed=1), 0.03)):
        pipe = FlowPipeline(options)
        outputs = [pipe.process(frame) for frame in moving.frames(poses)]
        errors = [abs(o.scale.value / kit.S_TRUE - 1.0) for o in outputs if o.scale.usable]
        assert outputs[-1].scale.usable and errors[-1] < bar, (gate, errors[-1])


def test_live_cloud_decimated_map_at_full_resolution(moving, kit):
    """The output's cloud takes every 4th pixel; the map fuses every pixel, from the same depth."""
    pipe = FlowPipeline(kit.options())
    assert (pipe.options.cloud_decimation, pipe.options.map_decimation) == (4, 1)
    every_third = FlowPipeline(kit.options(map_every=3))
    with_points = 0
    for frame in moving.frames(moving.poses):
        out = pipe.process(frame)
        other = every_third.process(frame)
        if out.depth is None:
            assert out.diagnostics.map_points == 0
            continue
        in_range = np.isfinite(out.depth) & (out.depth >= 1e-3) & (out.depth <= 0.3)
        assert len(out.points) == out.diagnostics.cloud_points == in_range[::4, ::4].sum()
        assert out.diagnostics.map_points == in_range.sum()
        # map_every changes what the map takes, never the output's cloud
        np.testing.assert_array_equal(other.points, out.points)
        expected = in_range.sum() if with_points % 3 == 0 else 0
        assert other.diagnostics.map_points == expected
        with_points += 1
    assert with_points > 20
    # every 3rd frame at full resolution: about a third of the points
    total, taken = pipe.voxel_map, every_third.voxel_map
    assert total is not None and taken is not None
    fused = int(total.points().count.sum())
    assert 0.3 < taken.points().count.sum() / fused < 0.37
    # fewer points, and a surface covered nearly as well (the frames overlap at 30 fps)
    assert len(taken) > 0.8 * len(total)


def test_a_deferred_map_fusion_gives_the_same_map_and_outputs(moving, kit):
    """The live node fuses the map after publishing (process(defer_map=True)): same map."""
    at_once = FlowPipeline(kit.options(map_every=3))
    deferred = FlowPipeline(kit.options(map_every=3))
    fused_points = 0
    for k, frame in enumerate(moving.frames(moving.poses)):
        a = at_once.process(frame)
        b = deferred.process(frame, defer_map=True)
        assert b.diagnostics.map_points == 0  # nothing fused inside process
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.scale.value, b.scale.value)
        fused_points += a.diagnostics.map_points
        if k % 2:  # the odd frames fused right away, the even ones by the next process()
            deferred.fuse_deferred_map()
    deferred.fuse_deferred_map()
    one, other = at_once.voxel_map, deferred.voxel_map
    assert one is not None and other is not None and len(one) == len(other)
    assert fused_points > 0 and int(other.points().count.sum()) == fused_points
    np.testing.assert_array_equal(one.voxel_keys(), other.voxel_keys())
    np.testing.assert_array_equal(one.points().count, other.points().count)
    np.testing.assert_allclose(one.points().points, other.points().points, rtol=0, atol=0)
    assert deferred.fuse_deferred_map() == 0  # nothing left


def test_a_deferred_frame_fused_in_bands_gives_the_same_map(moving, kit):
    """The live node: a band of the deferred frame after each frame (parts=map_every)."""
    at_once = FlowPipeline(kit.options(map_every=3))
    banded = FlowPipeline(kit.options(map_every=3))
    bands = 0
    last_fused = 0  # points of the last frame the map took
    for frame in moving.frames(moving.poses):
        a = at_once.process(frame)
        b = banded.process(frame, defer_map=True)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.scale.value, b.scale.value)
        last_fused = a.diagnostics.map_points or last_fused
        inserted = banded.fuse_deferred_map(parts=3)
        if inserted:  # a third of the frame's rows: never the whole frame in one call
            bands += 1
            assert inserted < 0.6 * last_fused
    while banded.map_pending:
        bands += banded.fuse_deferred_map(parts=3) > 0
    one, other = at_once.voxel_map, banded.voxel_map
    assert one is not None and other is not None and len(one) > 0
    assert bands > 10
    np.testing.assert_array_equal(one.voxel_keys(), other.voxel_keys())
    np.testing.assert_array_equal(one.recency_order(), other.recency_order())
    np.testing.assert_array_equal(one.points().count, other.points().count)
    np.testing.assert_array_equal(one.points().points, other.points().points)
    np.testing.assert_array_equal(one.points().normals, other.points().normals)


def test_bands_left_out_for_a_publish_are_fused_by_the_next_fused_frame(moving, kit):
    """The live node fuses no band in a slot that publishes the map; process() takes the rest.

    The map is the one fused at once, and its revision changes with each change, so the node
    publishes a map that process() changed by itself.
    """
    at_once = FlowPipeline(kit.options(map_every=3))
    banded = FlowPipeline(kit.options(map_every=3))
    rest_in_process = 0
    for k, frame in enumerate(moving.frames(moving.poses)):
        at_once.process(frame)
        voxels = banded.voxel_map
        assert voxels is not None
        before = voxels.revision
        pending = banded.map_pending
        banded.process(frame, defer_map=True)
        if pending and banded.map_pending:  # the rest of the previous one went in process()
            rest_in_process += voxels.revision != before
        if k % 4 == 3:  # the map was published in this slot: no band
            continue
        before = voxels.revision
        if banded.fuse_deferred_map(parts=3):
            assert voxels.revision != before
    while banded.map_pending:
        banded.fuse_deferred_map(parts=3)
    assert rest_in_process > 0
    one, other = at_once.voxel_map, banded.voxel_map
    assert one is not None and other is not None and len(one) > 0
    np.testing.assert_array_equal(one.voxel_keys(), other.voxel_keys())
    np.testing.assert_array_equal(one.recency_order(), other.recency_order())
    np.testing.assert_array_equal(one.points().count, other.points().count)
    np.testing.assert_array_equal(one.points().points, other.points().points)
    np.testing.assert_array_equal(one.points().normals, other.points().normals)
    revision = other.revision
    other.reset()
    assert other.revision != revision


def test_a_map_reset_drops_the_frame_waiting_for_it(moving, kit):
    pipe = FlowPipeline(kit.options(map_every=3))
    for frame in moving.frames(moving.poses):
        pipe.process(frame, defer_map=True)
        if pipe.fuse_deferred_map(parts=3):  # a band in, two still waiting
            break
    else:
        raise AssertionError("no frame was fused")
    voxels = pipe.voxel_map
    assert voxels is not None and len(voxels) > 0
    assert pipe.reset_map() > 0 and len(voxels) == 0
    assert pipe.fuse_deferred_map(parts=3) == 0 and len(voxels) == 0


def test_cloud_options_change_on_the_fly(moving, kit):
    pipe = FlowPipeline(kit.options())
    frames = moving.frames(moving.poses)
    outputs = [pipe.process(frame) for frame in frames[:40]]
    assert outputs[-1].depth is not None
    pipe.set_cloud_options(cloud_decimation=2, map_decimation=4)
    out = pipe.process(frames[40])
    in_range = np.isfinite(out.depth) & (out.depth >= 1e-3) & (out.depth <= 0.3)
    assert len(out.points) == in_range[::2, ::2].sum()
    assert out.diagnostics.map_points == in_range[::4, ::4].sum()
    with pytest.raises(ValueError, match="map_every must be >= 1"):
        pipe.set_cloud_options(map_every=0)
    with pytest.raises(ValueError, match="change on the fly"):
        pipe.set_cloud_options(voxel_size_m=2)
