"""Warming the flow pipeline up before a node's first frame.

A process's first frames pay for what later ones find ready: OpenCV's
feature detection and pyramidal Lucas–Kanade buffers at the frame's size, and
the numba kernels of triangulation, of the world cloud and of the voxel map,
loaded from the kernel cache at their first use (the map's insert alone took 154 ms on the
phantom's first cloud in a fresh process; at 0.25× playback the node skipped
the 4 frames after it).
:func:`warm_up_pipeline` runs that work on synthetic frames of the stream's
camera in a throw-away pipeline and map, so that a node calling it before it
subscribes processes its first real frame as fast as any later one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time

import cv2
import numpy as np

from endo_flow.cloud import binned_camera, world_clouds
from endo_flow.errors import FlowError
from endo_flow.pipeline import FlowFrame, FlowOptions, FlowPipeline
from endo_flow.voxel_map import VoxelMap
from endo_io.camera import CameraModel

#: Synthetic frames the throw-away pipeline tracks through.
WARM_UP_FRAMES = 3
#: Capacity of the throw-away map (the real one is allocated by its pipeline).
WARM_UP_VOXELS = 4096
#: Camera motion between synthetic frames, metres along x.
_STEP_M = 1e-3
#: Image shift between synthetic frames, pixels.
_SHIFT_PX = 2
#: Peak gain of the synthetic highlight over the texture.
_HIGHLIGHT_GAIN = 4.0


def _texture(width: int, height: int, seed: int = 0) -> np.ndarray:
    """(height, width + shifts) float32 smooth random texture in [0.1, 1], one highlight."""
    rng = np.random.default_rng(seed)
    noise = rng.random((height, width + _SHIFT_PX * WARM_UP_FRAMES), dtype=np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 2.0)
    low, high = float(blurred.min()), float(blurred.max())
    texture = 0.1 + 0.9 * (blurred - low) / max(high - low, 1e-6)
    # a specular highlight: the tracker masks it (endo_sfs.highlights labels its region)
    y, x = np.mgrid[0:height, 0 : texture.shape[1]]
    sigma = max(2.0, min(width, height) / 40.0)
    texture *= 1.0 + _HIGHLIGHT_GAIN * np.exp(
        -((x - width / 2) ** 2 + (y - height / 2) ** 2) / (2.0 * sigma**2))
    return texture.astype(np.float32)


def warm_up_pipeline(options: FlowOptions, camera: CameraModel) -> float:
    """Track synthetic frames of ``camera`` and fuse a synthetic cloud, then forget them.

    Args:
        options: the settings the real pipeline runs with (tracking
            resolution, pyramid levels, voxel size).
        camera: the camera of the frames to come (its size).

    Returns:
        Seconds taken.
    """
    start = time.perf_counter()
    width, height = camera.width, camera.height
    texture = _texture(width, height)
    depth = np.ones((height, width), np.float32)
    pipeline = FlowPipeline(dataclasses.replace(options, map_enabled=False))
    for index in range(WARM_UP_FRAMES):
        shift = _SHIFT_PX * index
        pose = np.eye(4)
        pose[0, 3] = _STEP_M * index
        frame = FlowFrame(1 + index * 33_333_333, texture[:, shift : shift + width], depth,
                          camera, pose)
        with contextlib.suppress(FlowError):  # what a frame lacked does not matter: it ran
            pipeline.process(frame)
    # a metric depth inside the cloud's range: the world cloud and the map insert run
    metric = np.full((height, width), 0.5 * (options.cloud_min_depth_m + options.cloud_max_depth_m),
                     np.float32)  # fmt: skip
    # both clouds, as a fused frame makes them: the ray tables of the binned
    # models (shared by geometry, endo_flow.cloud.binned_camera) are computed here
    decimations = (options.cloud_decimation, options.map_decimation)
    _, (points, grey, normals) = world_clouds(
        metric, texture[:, :width], binned_camera(camera, math.gcd(*decimations)), np.eye(4),
        decimations=decimations, min_depth_m=options.cloud_min_depth_m,
        max_depth_m=options.cloud_max_depth_m, white=1.0, gamma=options.tracking.gamma,
    )
    voxel_map = VoxelMap(options.voxel_size_m, WARM_UP_VOXELS)
    voxel_map.insert(points, grey, normals)
    voxel_map.points(1)
    voxel_map.published_records(1)  # the map message's kernel
    return time.perf_counter() - start
