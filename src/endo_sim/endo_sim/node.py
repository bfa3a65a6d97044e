"""``endo-sim live``: the simulator as a stand-in camera driver and tracker.

Publishes, in real time on the wall clock, what the offline bags contain:
``/endoscope/image_raw`` and ``/endoscope/camera_info`` at the sequence's
frame rate, ``/tracker/pose`` at the tracker's rate (stamp = now, pose =
the true pose ``latency`` earlier, plus noise, with occlusion dropouts),
``/ground_truth/camera_pose``, optionally ``/ground_truth/depth``, and
``/calibration/gray_level`` for the gray-card sequence. Bounded sequences
(gray card, hand–eye) loop.

Frames are rendered on a worker thread (the numba kernels release the GIL),
so the tracker timer keeps its rate while a frame renders. When rendering
falls behind, frames are skipped rather than delayed: frame k is always
stamped t0 + k/fps; skipped frames are counted on ``/diagnostics``.
All publishers are reliable (QoS overridable by parameters).
"""

from __future__ import annotations

import threading
from typing import Any

from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float32

from endo_io import topics
from endo_io.diagnostics import InputHealth
from endo_io.pose import matrix_to_pose
from endo_io.qos import create_reliable_publisher
from endo_sim.bagout import frame_messages, image_noise_rng, tracker_rng
from endo_sim.sequences import Sequence
from endo_sim.trajectory import NS_PER_S


class SimulatorNode(Node):
    """Publishes a :class:`~endo_sim.sequences.Sequence` live (see the module docstring)."""

    def __init__(self, sequence: Sequence, **kwargs: Any) -> None:
        super().__init__("endo_sim", **kwargs)
        self.sequence = sequence
        self.declare_parameter(
            "publish_depth",
            True,
            ParameterDescriptor(
                description="Publish /ground_truth/depth (32FC1, 1.2 MB per frame)."
            ),
        )
        self.declare_parameter(
            "time_scale",
            1.0,
            ParameterDescriptor(
                description="Simulated seconds per wall-clock second (1: real time).",
                floating_point_range=[FloatingPointRange(from_value=0.05, to_value=4.0, step=0.0)],
            ),
        )
        self._publish_depth = bool(self.get_parameter("publish_depth").value)
        self._time_scale = float(self.get_parameter("time_scale").value)
        types = {
            topics.IMAGE_RAW: Image,
            topics.CAMERA_INFO: CameraInfo,
            topics.TRUE_DEPTH: Image,
            topics.TRUE_CAMERA_POSE: PoseStamped,
            topics.TRACKER_POSE: PoseStamped,
        }
        if sequence.gray_levels is not None:
            types[topics.GRAY_LEVEL] = Float32
        self._outputs = {
            topic: create_reliable_publisher(self, msg_type, topic)
            for topic, msg_type in types.items()
        }
        self.frames = InputHealth(self, "rendered frames")
        self.tracker = InputHealth(self, "tracker samples")
        self._image_rng = image_noise_rng(sequence.config.seed)
        self._tracker_rng = tracker_rng(sequence.config.seed)
        self._occluded = False
        self._skipped = 0
        self._start_ns = self.get_clock().now().nanoseconds
        self._stop = threading.Event()
        model = sequence.config.tracker
        self._tracker_timer = self.create_timer(
            1.0 / model.rate_hz, self.tracker.guard(self._on_tracker)
        )
        self._worker = threading.Thread(
            target=self._render_loop, name="endo_sim_render", daemon=True
        )
        self._worker.start()

    def _simulated_ns(self, wall_ns: int) -> int:
        """Simulated time since the start for a wall-clock time, looped over the sequence."""
        elapsed = round((wall_ns - self._start_ns) * self._time_scale)
        return elapsed % self.sequence.duration_ns

    def _render_loop(self) -> None:
        period_ns = NS_PER_S / self.sequence.config.fps
        frame_times = self.sequence.frame_times_ns
        last = -1
        render = self.frames.guard(self._render_frame)
        while not self._stop.is_set():
            now = self.get_clock().now().nanoseconds
            index = int((now - self._start_ns) * self._time_scale // period_ns)
            if index <= last:
                wait_ns = self._start_ns + (last + 1) * period_ns / self._time_scale - now
                self._stop.wait(max(wait_ns, 0.0) / NS_PER_S)
                continue
            if last >= 0 and index > last + 1:
                self._skipped += index - last - 1
                self.frames.set_value("skipped_frames", self._skipped)
            last = index
            stamp_ns = self._start_ns + round(index * period_ns / self._time_scale)
            render(index % len(frame_times), stamp_ns)

    def _render_frame(self, k: int, stamp_ns: int) -> None:
        sequence = self.sequence
        pose = sequence.trajectory.pose_at(int(sequence.frame_times_ns[k]))
        frame = sequence.renderer.render(sequence.scene_of_frame(k), pose, self._image_rng)
        for message in frame_messages(sequence, k, frame, stamp_ns):
            if message.topic == topics.TRUE_DEPTH and not self._publish_depth:
                continue
            self._outputs[message.topic].publish(message.message)

    def _on_tracker(self) -> None:
        model = self.sequence.config.tracker
        now = self.get_clock().now().nanoseconds
        # Markov occlusions: start with rate r, end with mean length m, per tick.
        dt = 1.0 / model.rate_hz
        if self._occluded:
            self._occluded = self._tracker_rng.random() >= dt / model.dropout_mean_s
        else:
            self._occluded = self._tracker_rng.random() < model.dropout_rate_hz * dt
        if self._occluded:
            return
        sample_ns = self._simulated_ns(now - model.latency_ns)
        camera_pose = self.sequence.trajectory.pose_at(sample_ns)
        marker = model.add_noise(model.true_marker_poses(camera_pose[None]), self._tracker_rng)[0]
        marker[:3, 3] *= model.unit_scale
        pose = matrix_to_pose(marker, now, topics.TRACKER_FRAME)
        self._outputs[topics.TRACKER_POSE].publish(pose)

    def close(self) -> None:
        """Stop the render thread (called by run_node on shutdown)."""
        self._stop.set()
        self._worker.join(timeout=5.0)
