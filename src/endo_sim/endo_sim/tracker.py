"""Optical/EM tracker simulation: the marker pose the navigation system reports.

The tracker sees a marker rigidly fixed to the endoscope, not the camera.
With the hand–eye transform T_marker_camera (the camera's pose in the marker
frame, the unknown a hand–eye calibration recovers) and the tracker's place
in the world T_tracker_world, the reported pose at true time t is

    T_tracker_marker(t) = T_tracker_world · T_world_camera(t) · T_marker_camera⁻¹

plus measurement noise, sampled at the tracker's own rate (60 Hz) and
stamped with a fixed latency: the message stamped s carries the pose at
s − latency, which the hand–eye tool has to estimate. Occlusions of the
marker drop samples (no message), as line-of-sight trackers do.

Noise model: translation error isotropic Gaussian with 3-D RMS
``position_noise_rms_m`` (per axis RMS/√3); rotation error a rotation vector,
isotropic Gaussian with angle RMS ``rotation_noise_rms_rad`` (per axis
RMS/√3), applied in the marker frame. Defaults 0.25 mm and 0.1° are the
volumetric RMS figures of an NDI Polaris-class optical tracker.

Units: NDI drivers publish millimetres; ``units="mm"`` scales positions of
the published messages by 1000 (orientations are unit quaternions either way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from endo_io.pose import invert_transform, rigid_transform
from endo_sim.errors import SimulationParameterError
from endo_sim.trajectory import NS_PER_S, Trajectory, compose

TRACKER_UNITS = ("m", "mm")


#: Default hand–eye transform: the camera at the tip of a 30 cm rigid scope,
#: seen from a marker clamped to its head, tilted arbitrarily (metres).
DEFAULT_T_MARKER_CAMERA = rigid_transform((0.35, -0.20, 1.10), (0.012, -0.035, 0.300))
#: Default tracker placement: the camera unit 1.3 m from the patient, looking at it.
DEFAULT_T_TRACKER_WORLD = rigid_transform((2.30, 0.25, -0.40), (0.10, -0.15, 1.30))


@dataclass(frozen=True, eq=False)
class TrackerModel:
    """Parameters of the simulated tracker.

    rate_hz: sample rate (60 Hz). latency_s: stamp minus true sample time
    (25 ms, an optical tracker plus its driver). position_noise_rms_m /
    rotation_noise_rms_rad: 3-D RMS errors. dropout_rate_hz: occlusions per
    second (0.3); dropout_mean_s: mean occlusion length (0.15 s, exponential).
    units: "m" or "mm" for published positions. T_marker_camera,
    T_tracker_world: (4, 4) metres (hand–eye and tracker placement).
    phase_s: first tracker sample time after the recording's start.
    """

    rate_hz: float = 60.0
    latency_s: float = 0.025
    position_noise_rms_m: float = 0.25e-3
    rotation_noise_rms_rad: float = math.radians(0.1)
    dropout_rate_hz: float = 0.3
    dropout_mean_s: float = 0.15
    units: str = "m"
    T_marker_camera: np.ndarray = field(default_factory=lambda: DEFAULT_T_MARKER_CAMERA.copy())
    T_tracker_world: np.ndarray = field(default_factory=lambda: DEFAULT_T_TRACKER_WORLD.copy())
    phase_s: float = 0.004

    def __post_init__(self) -> None:
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise SimulationParameterError("tracker rate must be in [1, 1000] Hz")
        if not 0.0 <= self.latency_s <= 1.0:
            raise SimulationParameterError("tracker latency must be in [0, 1] s")
        if self.position_noise_rms_m < 0.0 or self.rotation_noise_rms_rad < 0.0:
            raise SimulationParameterError("tracker noise must be >= 0")
        if self.dropout_rate_hz < 0.0 or self.dropout_mean_s <= 0.0:
            raise SimulationParameterError("dropout rate must be >= 0 and mean length > 0")
        if self.units not in TRACKER_UNITS:
            raise SimulationParameterError(f"tracker units must be one of {TRACKER_UNITS}")
        if not 0.0 <= self.phase_s < 1.0 / self.rate_hz:
            raise SimulationParameterError("tracker phase must be within one sample period")
        for name in ("T_marker_camera", "T_tracker_world"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (4, 4):
                raise SimulationParameterError(f"{name} must be (4, 4)")
            object.__setattr__(self, name, value)

    @property
    def latency_ns(self) -> int:
        """Latency in integer nanoseconds."""
        return round(self.latency_s * NS_PER_S)

    @property
    def unit_scale(self) -> float:
        """Multiplier from metres to the published unit."""
        return 1000.0 if self.units == "mm" else 1.0

    def sample_times_ns(self, duration_ns: int) -> np.ndarray:
        """True sample times (N,) int64 ns since the start, within [0, duration)."""
        period = NS_PER_S / self.rate_hz
        count = math.ceil((duration_ns - self.phase_s * NS_PER_S) / period)
        times = np.round(self.phase_s * NS_PER_S + np.arange(max(count, 0)) * period)
        times = times.astype(np.int64)
        return times[times < duration_ns]

    def true_marker_poses(self, camera_poses: np.ndarray) -> np.ndarray:
        """T_tracker_marker (N, 4, 4) metres from T_world_camera (N, 4, 4), noise-free."""
        return self.T_tracker_world @ camera_poses @ invert_transform(self.T_marker_camera)

    def visibility(self, times_ns: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(N,) bool: False while the marker is occluded (alternating exponential spells)."""
        visible = np.ones(times_ns.shape, dtype=bool)
        if self.dropout_rate_hz == 0.0 or times_ns.size == 0:
            return visible
        t = 0.0
        end = float(times_ns.max()) / NS_PER_S
        seconds = times_ns.astype(np.float64) / NS_PER_S
        while t <= end:
            t += rng.exponential(1.0 / self.dropout_rate_hz)
            length = rng.exponential(self.dropout_mean_s)
            visible &= ~((seconds >= t) & (seconds < t + length))
            t += length
        return visible

    def add_noise(self, marker_poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Noisy copies of T_tracker_marker (N, 4, 4) (see the module docstring)."""
        n = marker_poses.shape[0]
        position = marker_poses[:, :3, 3] + rng.normal(
            0.0, self.position_noise_rms_m / math.sqrt(3.0), (n, 3)
        )
        rotvec = rng.normal(0.0, self.rotation_noise_rms_rad / math.sqrt(3.0), (n, 3))
        rotation = marker_poses[:, :3, :3] @ Rotation.from_rotvec(rotvec).as_matrix()
        return compose(rotation, position)


@dataclass(frozen=True, eq=False)
class TrackerSamples:
    """What the tracker publishes over a recording.

    sample_ns: (N,) int64 true sample times since the start; stamp_ns:
    (N,) int64 message stamps (sample + latency); poses: (N, 4, 4) noisy
    T_tracker_marker in metres; true_poses: (N, 4, 4) noise-free; visible:
    (N,) bool (False: occluded, no message).
    """

    sample_ns: np.ndarray
    stamp_ns: np.ndarray
    poses: np.ndarray
    true_poses: np.ndarray
    visible: np.ndarray


def simulate_tracker(
    model: TrackerModel, trajectory: Trajectory, rng: np.random.Generator
) -> TrackerSamples:
    """Sample the marker along ``trajectory`` with noise, latency and dropouts."""
    sample_ns = model.sample_times_ns(trajectory.duration_ns)
    true = model.true_marker_poses(trajectory.poses_at(sample_ns))
    noisy = model.add_noise(true, rng)
    visible = model.visibility(sample_ns, rng)
    return TrackerSamples(sample_ns, sample_ns + model.latency_ns, noisy, true, visible)
