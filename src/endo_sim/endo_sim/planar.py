"""Planar scenes: a uniform gray card and a printed checkerboard target.

Both are a plane with a closed-form ray intersection, t = ((p0 − o)·n)/(d·n),
exact to rounding. The gray card is matte and uniform (the photometric
calibration target); the checkerboard (the hand–eye target) is matte, its
squares box-filtered over each pixel's footprint in closed form, so that
corner positions are free of aliasing, as with a real lens's blur.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from endo_sim.errors import SimulationParameterError
from endo_sim.surface import SurfaceHits


def _plane_hits(
    pose: np.ndarray,
    rays: np.ndarray,
    mask: np.ndarray,
    point_world: np.ndarray,
    normal_world: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance (H, W), camera-frame normal (H, W, 3) facing the camera, hits (H, W, 3) world."""
    rotation = pose[:3, :3]
    origin = pose[:3, 3]
    normal_cam = rotation.T @ normal_world
    denom = rays @ normal_cam
    height = float((point_world - origin) @ normal_world)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = height / denom
    valid = mask & np.isfinite(distance) & (distance > 0.0)
    distance = np.where(valid, distance, np.nan)
    # Face the camera: n·ray < 0.
    facing = np.where(denom > 0.0, -1.0, 1.0)[..., None] * normal_cam
    normal = np.where(valid[..., None], facing, 0.0)
    points = origin + (distance[..., None] * rays) @ rotation.T
    return distance, normal, points


@dataclass(frozen=True, eq=False)
class PlaneScene:
    """An infinite matte plane of uniform albedo (the gray card).

    point_world (3,) and normal_world (3,) (normalised here) in metres;
    albedo: reflectance per channel, (C,) or a float.
    """

    point_world: np.ndarray
    normal_world: np.ndarray
    albedo: np.ndarray | float
    name: str = "plane"
    #: A gray card is matte: no specular lobe.
    specular_weight: float = 0.0

    def __post_init__(self) -> None:
        n = np.asarray(self.normal_world, dtype=np.float64)
        if n.shape != (3,) or not np.linalg.norm(n) > 0.0:
            raise SimulationParameterError("plane normal must be a non-zero 3-vector")
        albedo = np.atleast_1d(np.asarray(self.albedo, dtype=np.float64))
        if albedo.ndim != 1 or albedo.size not in (1, 3) or np.any((albedo < 0) | (albedo > 1)):
            raise SimulationParameterError("plane albedo must be 1 or 3 values in [0, 1]")
        object.__setattr__(self, "normal_world", n / np.linalg.norm(n))
        object.__setattr__(self, "point_world", np.asarray(self.point_world, dtype=np.float64))
        object.__setattr__(self, "albedo", albedo)

    def trace(self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray) -> SurfaceHits:
        """Hits of the unit rays (H, W, 3, camera frame) from the camera at pose (4, 4)."""
        distance, normal, _points = _plane_hits(
            pose, rays, mask, self.point_world, self.normal_world
        )
        albedo_values = np.asarray(self.albedo, dtype=np.float64)
        albedo = np.where(np.isfinite(distance)[..., None], albedo_values[None, None, :], 0.0)
        return SurfaceHits(distance, normal, albedo, self.specular_weight)


def _filtered_square_wave(u: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Square wave (+1 on [0, 1), −1 on [1, 2), period 2) box-filtered over ``width``.

    u, width: (...) in square units. The running integral of the square wave
    is a triangle wave T, so the box average is (T(u + w/2) − T(u − w/2)) / w.
    """

    def triangle(x: np.ndarray) -> np.ndarray:
        m = np.mod(x, 2.0)
        return np.where(m < 1.0, m, 2.0 - m)

    sharp = np.where(np.mod(u, 2.0) < 1.0, 1.0, -1.0)
    w = np.maximum(width, 1e-9)
    smooth = (triangle(u + 0.5 * w) - triangle(u - 0.5 * w)) / w
    return np.where(width > 1e-6, smooth, sharp)


@dataclass(frozen=True, eq=False)
class CheckerboardScene:
    """A printed checkerboard on a plane, with a white margin, on a gray background.

    pose_world_board (4, 4): board frame (x along the columns, y along the
    rows, z the board normal, origin at the outer corner of the first square)
    in the world. inner_corners: (columns, rows) of inner corners as OpenCV's
    ``findChessboardCorners`` counts them. square_m: square size in metres.
    The first square (at the origin) is dark. margin_squares: white margin
    around the pattern, in squares; beyond it the background albedo.
    channels: 1 or 3 (a neutral print: equal in all channels).
    """

    pose_world_board: np.ndarray
    inner_corners: tuple[int, int] = (8, 5)
    square_m: float = 0.004
    dark: float = 0.06
    light: float = 0.80
    margin_squares: float = 1.0
    background: float = 0.25
    channels: int = 1
    name: str = "checkerboard"
    specular_weight: float = 0.0

    def __post_init__(self) -> None:
        if min(self.inner_corners) < 2 or self.square_m <= 0.0:
            raise SimulationParameterError("checkerboard needs >= 2x2 inner corners and square > 0")
        if not 0.0 <= self.dark < self.light <= 1.0:
            raise SimulationParameterError(
                "checkerboard albedo must satisfy 0 <= dark < light <= 1"
            )

    def corners_board(self) -> np.ndarray:
        """Inner corners (N, 3) metres in the board frame, x fastest (OpenCV order)."""
        cols, rows = self.inner_corners
        grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float64) + 1.0
        return np.column_stack([grid * self.square_m, np.zeros(len(grid))])

    def corners_world(self) -> np.ndarray:
        """Inner corners (N, 3) metres in the world frame, OpenCV order."""
        c = self.corners_board()
        return c @ self.pose_world_board[:3, :3].T + self.pose_world_board[:3, 3]

    def trace(self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray) -> SurfaceHits:
        """Hits of the unit rays (H, W, 3, camera frame) from the camera at pose (4, 4)."""
        rotation = self.pose_world_board[:3, :3]
        origin = self.pose_world_board[:3, 3]
        distance, normal, points = _plane_hits(pose, rays, mask, origin, rotation[:, 2])
        valid = np.isfinite(distance)
        local = (np.where(valid[..., None], points, 0.0) - origin) @ rotation
        u = local[..., 0] / self.square_m
        v = local[..., 1] / self.square_m
        # Pixel footprint in square units, from the neighbours' coordinates
        # (a pixel's box filter, as a real lens and sensor pixel integrate).
        du_y, du_x = np.gradient(u)
        dv_y, dv_x = np.gradient(v)
        width_u = np.nan_to_num(np.abs(du_x) + np.abs(du_y), nan=0.0)
        width_v = np.nan_to_num(np.abs(dv_x) + np.abs(dv_y), nan=0.0)
        cols, rows = self.inner_corners
        # Pattern squares: first square dark ⇒ value (1 + s_u·s_v)/2 is "dark-ness".
        product = _filtered_square_wave(u, width_u) * _filtered_square_wave(v, width_v)
        pattern = self.light + (self.dark - self.light) * 0.5 * (1.0 + product)
        inside = (u >= 0) & (u <= cols + 1) & (v >= 0) & (v <= rows + 1)
        m = self.margin_squares
        on_board = (u >= -m) & (u <= cols + 1 + m) & (v >= -m) & (v <= rows + 1 + m)
        albedo = np.where(inside, pattern, np.where(on_board, self.light, self.background))
        albedo = np.repeat(np.where(valid, albedo, 0.0)[..., None], self.channels, axis=-1)
        return SurfaceHits(distance, normal, albedo, self.specular_weight)
