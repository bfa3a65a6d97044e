"""Hand–eye calibration sequence: a checkerboard seen from ~15 tracked poses.

The board lies in the world's z = 0 plane, centred on the origin; the camera
looks at it from below (z < 0) from 40–60 mm, tilted up to 30° in varied
directions and rolled, so that the relative rotations between stations span
all three axes (what AX = XB solvers need). Every station keeps the whole
board inside the circular field of view. The camera dwells at each station
and moves between stations with minimum-jerk timing, so the sequence also
contains motion for estimating the tracker's latency.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from endo_io.camera import CameraModel
from endo_sim.errors import SimulationParameterError
from endo_sim.planar import CheckerboardScene
from endo_sim.trajectory import StationTrajectory

#: Default board: 8×5 inner corners (OpenCV pattern size), 4 mm squares.
DEFAULT_INNER_CORNERS = (8, 5)
DEFAULT_SQUARE_M = 0.004


def centred_board(
    inner_corners: tuple[int, int] = DEFAULT_INNER_CORNERS,
    square_m: float = DEFAULT_SQUARE_M,
    channels: int = 1,
) -> CheckerboardScene:
    """A checkerboard in the world z = 0 plane, centred on the world origin (1 or 3 channels)."""
    cols, rows = inner_corners
    pose = np.eye(4)
    pose[:3, 3] = (-0.5 * (cols + 1) * square_m, -0.5 * (rows + 1) * square_m, 0.0)
    corners = (int(inner_corners[0]), int(inner_corners[1]))
    return CheckerboardScene(pose, corners, square_m, channels=channels)


def _look_at(position: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """T_world_camera with the optical axis from ``position`` to ``target``, rolled."""
    forward = target - position
    forward /= np.linalg.norm(forward)
    ref = np.array([1.0, 0.0, 0.0]) if abs(forward[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    right = ref - (ref @ forward) * forward
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    base = np.stack([right, down, forward], axis=-1)
    pose = np.eye(4)
    pose[:3, :3] = base @ Rotation.from_rotvec([0.0, 0.0, roll]).as_matrix()
    pose[:3, 3] = position
    return pose


def board_in_view(
    board: CheckerboardScene,
    camera: CameraModel,
    pose: np.ndarray,
    fov_radius_px: float | None,
    margin: float = 0.85,
) -> bool:
    """True when the board's outer corners project inside ``margin``·(FOV radius)."""
    cols, rows = board.inner_corners
    s = board.square_m
    outer = np.array(
        [
            [0, 0, 0],
            [(cols + 1) * s, 0, 0],
            [0, (rows + 1) * s, 0],
            [(cols + 1) * s, (rows + 1) * s, 0],
        ]
    )
    world = outer @ board.pose_world_board[:3, :3].T + board.pose_world_board[:3, 3]
    camera_points = (world - pose[:3, 3]) @ pose[:3, :3]
    pixels = camera.project(camera_points)
    if not np.all(np.isfinite(pixels)):
        return False
    radius = fov_radius_px if fov_radius_px is not None else 0.5 * min(camera.width, camera.height)
    distance = np.hypot(pixels[:, 0] - camera.cx, pixels[:, 1] - camera.cy)
    inside_image = (
        (pixels[:, 0] >= 0)
        & (pixels[:, 0] <= camera.width - 1)
        & (pixels[:, 1] >= 0)
        & (pixels[:, 1] <= camera.height - 1)
    )
    return bool(np.all(distance <= margin * radius) and np.all(inside_image))


def handeye_stations(
    board: CheckerboardScene,
    camera: CameraModel,
    seed: int,
    count: int = 15,
    fov_radius_px: float | None = None,
    distance_range_m: tuple[float, float] = (0.040, 0.060),
    max_tilt_rad: float = math.radians(30.0),
) -> np.ndarray:
    """``count`` station poses T_world_camera (count, 4, 4) looking at the board.

    Tilts (angle between the optical axis and the board normal) are spread
    up to ``max_tilt_rad`` around the full circle, rolls over ±90°; every
    station sees the whole board. Deterministic from ``seed``.
    """
    rng = np.random.default_rng([int(seed), 0x4E7E])
    stations: list[np.ndarray] = []
    attempts = 0
    while len(stations) < count:
        attempts += 1
        if attempts > 20000:
            raise SimulationParameterError(
                "cannot place the board in view at the requested distances; enlarge the FOV or "
                "the distance range"
            )
        k = len(stations)
        # Stratify the tilt direction so that rotation axes are diverse.
        azimuth = 2.0 * math.pi * (k + rng.uniform(0.0, 1.0)) / count
        tilt = max_tilt_rad * math.sqrt(rng.uniform(0.15, 1.0))
        distance = rng.uniform(*distance_range_m)
        direction = np.array(
            [
                math.sin(tilt) * math.cos(azimuth),
                math.sin(tilt) * math.sin(azimuth),
                -math.cos(tilt),
            ]
        )
        target = np.array([rng.uniform(-0.003, 0.003), rng.uniform(-0.003, 0.003), 0.0])
        pose = _look_at(
            target + distance * direction, target, rng.uniform(-0.5 * math.pi, 0.5 * math.pi)
        )
        if board_in_view(board, camera, pose, fov_radius_px):
            stations.append(pose)
    return np.array(stations)


def handeye_trajectory(
    stations: np.ndarray, dwell_s: float = 0.8, move_s: float = 1.6
) -> StationTrajectory:
    """Dwell ``dwell_s`` at each station, ``move_s`` minimum-jerk moves between them."""
    return StationTrajectory(stations, round(dwell_s * 1e9), round(move_s * 1e9))
