"""Synthetic inputs for the endo_flow tests: rendered abdomen frames with ground truth.

Frames are rendered by endo_sim's renderer (textured abdominal wall, Oren–Nayar,
specular lobe, sensor noise) at 320×240 so the tests stay fast; the corrected
image is the noise-free irradiance divided by the true light map, and
depth_relative is the true depth divided by a known scale (what a perfect SFS
would give). Poses: the true camera poses, or the ones a tracker with 0.25 mm /
0.1° noise and a hand–eye error of 1 mm / 0.3° gives (endo_sim's tracker model,
composed with endo_tracker_bridge's chain).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import pytest

from endo_flow.keyframes import TrackViews
from endo_flow.pipeline import FlowFrame, FlowOptions
from endo_flow.tracking import TrackingOptions
from endo_io.camera import CameraModel
from endo_io.pose import invert_transform, rigid_transform
from endo_sim.sequences import SimulationConfig, build_sequence
from endo_sim.tracker import TrackerModel
from endo_tracker_bridge.composition import compose_camera_pose

WIDTH, HEIGHT, FPS = 320, 240, 30.0
#: the scale a perfect SFS output is off by in these tests (depth_relative = depth / S_TRUE)
S_TRUE = 0.04
#: hand–eye error of the issue: 1 mm, 0.3°
HANDEYE_ERROR = rigid_transform(np.radians(0.3) * np.array([0.6, 0.0, 0.8]),
                                1e-3 * np.array([0.0, 0.6, 0.8]))


def synthetic_track_views(
    points: np.ndarray, centres: np.ndarray, *, angle_noise: float = 0.0, seed: int = 0,
    scale: float | None = None,
) -> TrackViews:
    """Every point seen from every centre by cameras looking along +z (world axes).

    Args:
        points: (N, 3) world points, metres.
        centres: (V, 3) camera centres, metres.
        angle_noise: standard deviation of the Gaussian noise added to each unit ray, radians.
        seed: seed of that noise.
        scale: with a scale, the views carry the optical axes and the exact
            depth_relative (z depth / scale) that the reprojection fit needs.

    Returns:
        The (N, V) views, all valid.
    """
    rng = np.random.default_rng(seed)
    n, v = len(points), len(centres)
    c = np.broadcast_to(centres, (n, v, 3)).copy()
    d = points[:, None, :] - c
    relative = d[..., 2] / scale if scale is not None else None
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    if angle_noise:
        d += rng.normal(0.0, angle_noise, d.shape)
        d /= np.linalg.norm(d, axis=2, keepdims=True)
    if scale is None:
        return TrackViews(c, d, np.ones((n, v), bool))
    axes = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, v, 3)).copy()
    return TrackViews(c, d, np.ones((n, v), bool), axes, relative)


@dataclasses.dataclass
class Rendered:
    """A rendered sequence: camera, stamps (N,) ns, true poses (N,4,4), images, true depths."""

    camera: CameraModel
    stamps: np.ndarray
    poses: np.ndarray
    images: list[np.ndarray]
    depths: list[np.ndarray]

    def frames(self, poses: np.ndarray | list[np.ndarray | None],
               scale: float | np.ndarray = S_TRUE) -> list[FlowFrame]:
        """FlowFrames with depth_relative = depth / scale (scale per frame or one)."""
        scales = np.broadcast_to(np.asarray(scale, np.float64), (len(self.stamps),))
        return [
            FlowFrame(int(t), img, (d / s).astype(np.float32), self.camera,
                      None if T is None else np.asarray(T))
            for t, img, d, s, T in zip(self.stamps, self.images, self.depths, scales, poses,
                                       strict=True)
        ]


def _render(poses: np.ndarray, seed: int) -> Rendered:
    config = SimulationConfig(scene="abdomen", width=WIDTH, height=HEIGHT, fps=FPS,
                              duration_s=max(1.0, len(poses) / FPS), seed=seed)
    seq = build_sequence(config)
    rng = np.random.default_rng(seed)
    images, depths = [], []
    for T in poses:
        frame = seq.renderer.render(seq.scenes[0], T, rng)
        valid = seq.renderer.mask & np.isfinite(frame.depth)
        corrected = np.where(valid, frame.irradiance[..., 0] / seq.renderer.light_map, np.nan)
        images.append(corrected.astype(np.float32))
        depths.append(frame.depth)
    stamps = seq.config.start_ns + np.round(np.arange(len(poses)) * 1e9 / FPS).astype(np.int64)
    return Rendered(seq.camera, stamps, np.asarray(poses), images, depths)


def abdomen_trajectory(count: int, seed: int = 3) -> np.ndarray:
    """(count, 4, 4) true poses along endo_sim's abdomen sweep (5–16 mm/s)."""
    config = SimulationConfig(scene="abdomen", width=WIDTH, height=HEIGHT, fps=FPS,
                              duration_s=max(1.0, count / FPS), seed=seed)
    seq = build_sequence(config)
    times = np.round(np.arange(count) * 1e9 / FPS).astype(np.int64)
    return seq.trajectory.poses_at(times)


def tracked_poses(true_poses: np.ndarray, seed: int = 0, *, noise: bool = True,
                  handeye_error: bool = True) -> np.ndarray:
    """Camera poses as the tracker bridge would give them (noise, hand–eye error)."""
    model = TrackerModel()
    marker = model.true_marker_poses(true_poses)
    if noise:
        marker = model.add_noise(marker, np.random.default_rng(seed))
    X = model.T_marker_camera @ HANDEYE_ERROR if handeye_error else model.T_marker_camera
    return compose_camera_pose(invert_transform(model.T_tracker_world), marker, X)


def flow_options(**changes: object) -> FlowOptions:
    """Pipeline options for 320×240 frames (tracked at full resolution)."""
    return dataclasses.replace(
        FlowOptions(tracking=TrackingOptions(downsample=1, flatten_sigma_px=4.0)), **changes)


_CACHE: dict[tuple[str, int], Rendered] = {}


@pytest.fixture(scope="session")
def render() -> Callable[[str, np.ndarray, int], Rendered]:
    """Render (and cache by name) a sequence of true poses."""

    def make(name: str, poses: np.ndarray, seed: int = 3) -> Rendered:
        key = (name, seed)
        if key not in _CACHE:
            _CACHE[key] = _render(poses, seed)
        return _CACHE[key]

    return make


@pytest.fixture(scope="session")
def moving(render: Callable[[str, np.ndarray, int], Rendered]) -> Rendered:
    """2.5 s along the abdomen sweep."""
    return render("moving", abdomen_trajectory(75), 3)


@pytest.fixture(scope="session")
def kit(render: Callable[[str, np.ndarray, int], Rendered]) -> SimpleNamespace:
    """The helpers above, for tests (conftest modules are not importable by name)."""
    return SimpleNamespace(
        S_TRUE=S_TRUE, render=render, abdomen_trajectory=abdomen_trajectory,
        tracked_poses=tracked_poses, options=flow_options,
    )
