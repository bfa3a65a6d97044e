"""Smooth camera trajectories at surgical speeds, as 4x4 poses over time.

A trajectory is a closed-form function of time, so the camera (30 fps) and
the tracker (60 Hz, with latency) sample the *same* motion at any instant,
exactly and reproducibly. Poses are T_world_camera (4, 4) float64, metres,
camera = ``endoscope_optical_frame`` (REP 103: x right, y down, z forward).
Time is integer nanoseconds since the trajectory's start.

* :class:`ColonTrajectory`: slow advance along the colon's centreline
  (10 ± 5 mm/s), a lateral sweep of ±4 mm and look-around (yaw ±11°,
  pitch ±9°) with a slow roll — an endoscopist inspecting folds.
* :class:`AbdomenTrajectory`: a laparoscope sweeping over the abdominal wall,
  its distance from the wall breathing between 28 and 72 mm, tilting ±14°.
* :class:`StationTrajectory`: dwell at a list of poses, moving between them
  with minimum-jerk timing (the hand–eye calibration sequence).

All motions are sums of sinusoids with seeded phases: C∞ smooth, speeds 5–20
mm/s and angular rates below 25°/s, like careful manual endoscopy.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from endo_sim.colon import ColonScene
from endo_sim.errors import SimulationParameterError

NS_PER_S = 1_000_000_000


def _seconds(t_ns: np.ndarray | int) -> np.ndarray:
    """Integer nanoseconds -> float64 seconds (array)."""
    return np.asarray(t_ns, dtype=np.int64).astype(np.float64) / NS_PER_S


def compose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations and (N, 3) translations -> (N, 4, 4) transforms."""
    n = rotation.shape[0]
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = rotation
    out[:, :3, 3] = translation
    out[:, 3, 3] = 1.0
    return out


class Trajectory(ABC):
    """A camera motion: T_world_camera as a function of time."""

    def __init__(self, duration_ns: int) -> None:
        if duration_ns <= 0:
            raise SimulationParameterError(
                f"trajectory duration must be positive, got {duration_ns} ns"
            )
        self.duration_ns = int(duration_ns)

    @abstractmethod
    def poses_at(self, t_ns: np.ndarray) -> np.ndarray:
        """T_world_camera at times t_ns (N,) int64 ns since start -> (N, 4, 4) float64."""

    def pose_at(self, t_ns: int) -> np.ndarray:
        """T_world_camera (4, 4) at one time (int ns since start)."""
        return self.poses_at(np.array([t_ns], dtype=np.int64))[0]


class _Wobble:
    """Σ amplitude·sin(2π·f·t + phase) with seeded phases; value and derivative."""

    def __init__(self, rng: np.random.Generator, terms: list[tuple[float, float]]) -> None:
        self.amplitude = np.array([a for a, _ in terms])
        self.omega = 2.0 * math.pi * np.array([f for _, f in terms])
        self.phase = rng.uniform(0.0, 2.0 * math.pi, len(terms))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return np.sum(self.amplitude * np.sin(self.omega * t[:, None] + self.phase), axis=-1)


class ColonTrajectory(Trajectory):
    """Inspection inside :class:`~endo_sim.colon.ColonScene`.

    scene: the colon (its centreline guides the motion); seed: phases;
    duration_ns: length; start_z_m: axial start; advance_m_s: mean speed.
    """

    def __init__(
        self,
        scene: ColonScene,
        seed: int,
        duration_ns: int,
        start_z_m: float = 0.02,
        advance_m_s: float = 0.010,
    ) -> None:
        super().__init__(duration_ns)
        if not 0.0 < advance_m_s <= 0.02:
            raise SimulationParameterError("colon advance speed must be in (0, 20] mm/s")
        self.scene = scene
        rng = np.random.default_rng([int(seed), 0x7247])
        self.start_z_m = float(start_z_m)
        self.advance_m_s = float(advance_m_s)
        # Axial surge: ±2.7 mm at 0.3 Hz, i.e. ±5 mm/s around the mean advance.
        self._surge = _Wobble(rng, [(0.0027, 0.3)])
        self._lateral_x = _Wobble(rng, [(0.003, 0.17), (0.001, 0.41)])
        self._lateral_y = _Wobble(rng, [(0.003, 0.13), (0.001, 0.37)])
        self._yaw = _Wobble(rng, [(0.15, 0.11), (0.05, 0.29)])
        self._pitch = _Wobble(rng, [(0.12, 0.09), (0.04, 0.23)])
        self._roll = _Wobble(rng, [(0.35, 0.05)])

    def poses_at(self, t_ns: np.ndarray) -> np.ndarray:
        t = _seconds(t_ns)
        z = self.start_z_m + self.advance_m_s * t + self._surge(t) - self._surge(np.zeros(1))
        centre, tangent = self.scene.centreline(z)
        # A frame transported along the centreline: e1 ⟂ tangent, near world x.
        ref = np.array([1.0, 0.0, 0.0])
        e1 = ref - (tangent @ ref)[:, None] * tangent
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(tangent, e1)
        base = np.stack([e1, e2, tangent], axis=-1)  # columns: camera x, y, z
        position = centre + self._lateral_x(t)[:, None] * e1 + self._lateral_y(t)[:, None] * e2
        look = Rotation.from_euler(
            "YXZ", np.stack([self._yaw(t), self._pitch(t), self._roll(t)], axis=-1)
        ).as_matrix()
        return compose(base @ look, position)


class AbdomenTrajectory(Trajectory):
    """Sweep over :class:`~endo_sim.abdomen.AbdomenScene`'s wall, looking up (+z).

    The distance to the dome along z breathes between 28 and 72 mm (period 12 s).
    """

    def __init__(self, curvature_radius_m: float, seed: int, duration_ns: int) -> None:
        super().__init__(duration_ns)
        rng = np.random.default_rng([int(seed), 0xAB7])
        self.curvature_radius_m = float(curvature_radius_m)
        self._x = _Wobble(rng, [(0.018, 0.05), (0.004, 0.19)])
        self._y = _Wobble(rng, [(0.015, 0.07), (0.004, 0.23)])
        self._distance = _Wobble(rng, [(0.020, 1.0 / 12.0), (0.002, 0.31)])
        self._tilt_x = _Wobble(rng, [(0.18, 0.08), (0.05, 0.21)])
        self._tilt_y = _Wobble(rng, [(0.18, 0.06), (0.05, 0.17)])
        self._roll = _Wobble(rng, [(0.4, 0.04)])

    def poses_at(self, t_ns: np.ndarray) -> np.ndarray:
        t = _seconds(t_ns)
        x = self._x(t)
        y = self._y(t)
        distance = 0.050 + self._distance(t)
        z = -(x * x + y * y) / (2.0 * self.curvature_radius_m) - distance
        rotation = Rotation.from_euler(
            "XYZ", np.stack([self._tilt_x(t), self._tilt_y(t), self._roll(t)], axis=-1)
        ).as_matrix()
        return compose(rotation, np.stack([x, y, z], axis=-1))


class StationTrajectory(Trajectory):
    """Dwell at each of ``stations`` (K, 4, 4) for dwell_ns, moving between them in move_ns.

    Moves use minimum-jerk timing s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ (zero velocity and
    acceleration at both ends): linear in translation, SLERP in rotation.
    """

    def __init__(self, stations: np.ndarray, dwell_ns: int, move_ns: int) -> None:
        stations = np.asarray(stations, dtype=np.float64)
        if stations.ndim != 3 or stations.shape[1:] != (4, 4) or len(stations) < 1:
            raise SimulationParameterError("stations must be (K, 4, 4) poses, K >= 1")
        if dwell_ns <= 0 or move_ns <= 0:
            raise SimulationParameterError("dwell and move durations must be positive")
        self.stations = stations
        self.dwell_ns = int(dwell_ns)
        self.move_ns = int(move_ns)
        super().__init__(len(stations) * self.dwell_ns + (len(stations) - 1) * self.move_ns)
        self._rotations = Rotation.from_matrix(stations[:, :3, :3])

    def station_times_ns(self) -> np.ndarray:
        """(K, 2) int64 start and end of each dwell, ns since the start."""
        starts = np.arange(len(self.stations), dtype=np.int64) * (self.dwell_ns + self.move_ns)
        return np.stack([starts, starts + self.dwell_ns], axis=-1)

    def poses_at(self, t_ns: np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(t_ns, dtype=np.int64), 0, self.duration_ns)
        period = self.dwell_ns + self.move_ns
        index = np.minimum(t // period, len(self.stations) - 1)
        into = t - index * period
        tau = np.clip((into - self.dwell_ns) / self.move_ns, 0.0, 1.0)
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)
        nxt = np.minimum(index + 1, len(self.stations) - 1)
        a = self.stations[index]
        b = self.stations[nxt]
        translation = a[:, :3, 3] + s[:, None] * (b[:, :3, 3] - a[:, :3, 3])
        rotation = np.empty((len(t), 3, 3))
        for k in range(len(t)):
            if s[k] == 0.0 or index[k] == nxt[k]:
                rotation[k] = a[k, :3, :3]
            else:
                pair = Rotation.concatenate(
                    [self._rotations[int(index[k])], self._rotations[int(nxt[k])]]
                )
                rotation[k] = Slerp([0.0, 1.0], pair)(s[k]).as_matrix()
        return compose(rotation, translation)
