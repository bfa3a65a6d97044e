"""KeyframeWindow.views (one sorted search over the window) against the plain per-keyframe loop."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from endo_flow.keyframes import Keyframe, KeyframeWindow, TrackViews
from endo_io.pose import rigid_transform


def reference_views(frames: list[Keyframe], ids: np.ndarray, current: Keyframe | None,
                    pose_of: Callable[[Keyframe], np.ndarray] | None) -> TrackViews:
    """The straightforward gather: each keyframe in turn, searchsorted on its ids."""
    frames = [f if pose_of is None else f.with_pose(pose_of(f)) for f in frames]
    if current is not None:
        if frames and frames[-1].stamp_ns == current.stamp_ns:
            frames.pop()
        frames.append(current.sorted_by_id())
    n, v = len(ids), len(frames)
    centres, directions, axes = np.zeros((n, v, 3)), np.zeros((n, v, 3)), np.zeros((n, v, 3))
    relative, valid = np.full((n, v), np.nan), np.zeros((n, v), bool)
    for k, frame in enumerate(frames):
        centres[:, k] = frame.T_world_camera[:3, 3]
        axes[:, k] = frame.T_world_camera[:3, 2]
        if len(frame.ids) == 0:
            continue
        at = np.minimum(np.searchsorted(frame.ids, ids), len(frame.ids) - 1)
        seen = frame.ids[at] == ids
        directions[seen, k] = frame.rays[at[seen]] @ frame.T_world_camera[:3, :3].T
        if frame.relative is not None:
            relative[seen, k] = frame.relative[at[seen]]
        valid[:, k] = seen
    return TrackViews(centres, directions, valid, axes, relative)


def _keyframe(rng: np.random.Generator, stamp: int, ids: np.ndarray, with_relative: bool
              ) -> Keyframe:
    rays = rng.normal(size=(len(ids), 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    T = rigid_transform(rng.normal(0.0, 0.3, 3), rng.normal(0.0, 0.01, 3))
    relative = rng.uniform(1.0, 2.0, len(ids)) if with_relative else None
    return Keyframe(stamp, T, ids, rays, relative)


def _assert_same(got: TrackViews, want: TrackViews) -> None:
    np.testing.assert_array_equal(got.valid, want.valid)
    np.testing.assert_allclose(got.directions, want.directions, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(got.centres, want.centres)
    assert got.axes is not None and want.axes is not None
    np.testing.assert_array_equal(got.axes, want.axes)
    assert got.relative is not None and want.relative is not None
    np.testing.assert_array_equal(got.relative, want.relative)


def test_views_equal_the_per_keyframe_loop():
    rng = np.random.default_rng(5)
    window = KeyframeWindow(capacity=6, min_step_m=0.0, max_age_ns=10**12)
    smoothed = {}

    def pose_of(frame: Keyframe) -> np.ndarray:
        return smoothed.setdefault(frame.stamp_ns, rigid_transform(
            rng.normal(0.0, 0.3, 3), rng.normal(0.0, 0.01, 3)))

    for step in range(12):
        # ids drawn from a moving range, unsorted, some keyframes empty or without relative
        alive = rng.choice(np.arange(5 * step, 5 * step + 40), rng.integers(0, 25), replace=False)
        frame = _keyframe(rng, step, alive.astype(np.int64), with_relative=step % 4 != 1)
        query = rng.permutation(np.arange(5 * step - 10, 5 * step + 45)).astype(np.int64)
        for current, poses in ((None, None), (frame, None), (frame, pose_of)):
            got = window.views(query, current, poses)
            want = reference_views(list(window.keyframes), query, current, poses)
            _assert_same(got, want)
        window.add(frame)
        # the newest keyframe is also the current frame: counted once
        _assert_same(window.views(query, frame, pose_of),
                     reference_views(list(window.keyframes), query, frame, pose_of))
        if step == 7:
            window.scale_relative(0.5)  # a gain step: the table must follow
    # the pipeline's case: the current frame's ids are the query, in the same order
    current = _keyframe(rng, 99, rng.permutation(np.arange(40, 80)).astype(np.int64), True)
    _assert_same(window.views(current.ids, current, pose_of),
                 reference_views(list(window.keyframes), current.ids, current, pose_of))
