"""A camera that changes resolution mid-stream: the pipeline re-plans, never locks out.

Before, the Lucas–Kanade tracker kept the previous frame of the old size and
every later frame failed in OpenCV ("prevPyr" assertion): one camera_info
change stopped the flow step for good.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from endo_flow.cloud import binned_camera
from endo_flow.pipeline import FlowFrame, FlowOptions, FlowPipeline
from endo_flow.tracking import TrackingOptions
from endo_sim.sequences import SimulationConfig, build_sequence

STEP_NS = 33_333_333


def _frames(first_ns: int, count: int = 6) -> list[FlowFrame]:
    sequence = build_sequence(SimulationConfig(
        scene="abdomen", width=160, height=120, fps=30.0, duration_s=1.0, seed=2
    ))
    frames = []
    for k in range(count):
        pose = sequence.trajectory.pose_at(int(sequence.frame_times_ns[k]))
        rendered = sequence.renderer.render(sequence.scene_of_frame(k), pose,
                                            np.random.default_rng(k))
        frames.append(FlowFrame(
            first_ns + k * STEP_NS, rendered.irradiance[..., 0].astype(np.float32),
            (rendered.depth / 0.04).astype(np.float32), sequence.renderer.camera, pose,
        ))
    return frames


def _binned(frame: FlowFrame, first_ns: int) -> FlowFrame:
    """The same view from the camera binned 2x2 (80x60), later on the same clock."""
    half = (frame.camera.width // 2, frame.camera.height // 2)
    return FlowFrame(
        first_ns + frame.stamp_ns, cv2.resize(frame.image, half, interpolation=cv2.INTER_AREA),
        cv2.resize(frame.depth_relative, half, interpolation=cv2.INTER_NEAREST),
        binned_camera(frame.camera, 2), frame.T_world_camera,
    )


def test_a_new_resolution_restarts_the_tracks_and_every_frame_is_processed():
    # tracking at full resolution: the binned frames are small
    pipeline = FlowPipeline(FlowOptions(tracking=replace(TrackingOptions(), downsample=1)))
    first = _frames(10**18)
    second = [_binned(frame, len(first) * STEP_NS) for frame in first]
    outputs = [pipeline.process(frame) for frame in first + second]
    assert len(outputs) == 12 and pipeline.camera_changes == 1
    tracks = [out.diagnostics.tracks for out in outputs]
    assert min(tracks[7:]) > 8  # tracking resumed on the new size
    assert pipeline.resets == 0  # no clock jump: the scale filter and the map stay
