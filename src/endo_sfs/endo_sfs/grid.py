"""The solve grid: where on the sphere of viewing directions the PDE is solved.

The shading equations are posed over viewing directions, not over pixels. A
lens with distortion (or a ``solve_scale`` below one) makes the pixel grid a
non-uniform sampling of those directions, so each model is solved on a
uniform grid of its own chart of the ray sphere and the result is resampled
back to the pixels through the camera's per-pixel ray table:

* ``gnomonic`` (orthographic model): the normalised image plane
  (x, y) = (ω_x/ω_z, ω_y/ω_z), spacing 1/(f·scale). For an undistorted camera
  at scale 1 its nodes are exactly the pixel centres and no resampling
  happens.
* ``stereographic`` (near-light model): s = (ω_x, ω_y)/(1 + ω_z), spacing
  1/(2f·scale) (equal to the pixel pitch at the image centre). The chart is
  conformal, so the sphere's gradient norm is |∇_s v|/λ with the scalar
  factor λ(s) = 2/(1 + |s|²): the perspective Hamiltonian becomes an isotropic
  Eikonal-type equation and the simple Godunov update applies.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.ndimage import map_coordinates

from endo_io.camera import CameraModel
from endo_sfs import resampling

Projection = Literal["gnomonic", "stereographic"]

#: Rays this close to perpendicular to the optical axis have no gnomonic chart.
_MIN_RAY_Z = 1e-3
#: A node whose pixel maps back farther than this (in nodes) is not one-to-one.
_ROUND_TRIP_TOL = 0.5
_CACHE_SIZE = 8


@dataclass(frozen=True, eq=False)
class SolveGrid:
    """A uniform grid over one chart of the ray sphere, tied to one camera.

    Attributes:
        projection: "gnomonic" or "stereographic".
        shape: (ny, nx) nodes.
        spacing: (hx, hy) chart units per node.
        node_pixel_x, node_pixel_y: (ny, nx) float64 pixel coordinates (u, v)
            of every node; NaN where the node is not seen by the camera.
        node_rays: (ny, nx, 3) float64 unit rays of the nodes.
        conformal_factor_sq: (ny, nx) float64 λ² (ones for gnomonic).
        pixel_node_x, pixel_node_y: (H, W) float64 node coordinates of every
            pixel (NaN for pixels without a chart position).
        pixel_rays: (H, W, 3) float64 unit ray of every pixel.
        pixel_ray_z: (H, W) float64 its z component, contiguous (depth = r·ω_z).
        pixel_has_ray: (H, W) bool pixels whose ray is finite.
        identity: True when nodes and pixels coincide (no resampling).
    """

    projection: Projection
    shape: tuple[int, int]
    spacing: tuple[float, float]
    node_pixel_x: np.ndarray
    node_pixel_y: np.ndarray
    node_rays: np.ndarray
    conformal_factor_sq: np.ndarray
    pixel_node_x: np.ndarray
    pixel_node_y: np.ndarray
    pixel_rays: np.ndarray
    pixel_ray_z: np.ndarray
    pixel_has_ray: np.ndarray
    identity: bool

    def to_nodes(
        self, image: np.ndarray, valid: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Resample a pixel image to the nodes (bilinear, all four pixels valid).

        image: (H, W) float; valid: (H, W) bool. Returns ((ny, nx) float64
        with NaN at invalid nodes, (ny, nx) bool validity).
        """
        if self.identity:
            values = np.where(valid, image, np.nan).astype(np.float64)
            return values, valid.copy()
        # float32 (the corrected image) is read as it is: no float64 copy.
        dtype = np.float32 if np.asarray(image).dtype == np.float32 else np.float64
        return resampling.sample_strict(
            np.ascontiguousarray(image, dtype=dtype),
            np.ascontiguousarray(valid),
            self.node_pixel_x,
            self.node_pixel_y,
        )

    def to_pixels(self, values: np.ndarray, wanted: np.ndarray) -> np.ndarray:
        """Resample node values back to the pixels (bilinear over finite nodes).

        values: (ny, nx) float64, non-finite where unknown; wanted: (H, W)
        bool. Returns (H, W) float64, NaN where not wanted or unknown.
        """
        if self.identity:
            return np.where(wanted & np.isfinite(values), values, np.nan)
        return resampling.sample_weighted(
            np.ascontiguousarray(values, dtype=np.float64),
            self.pixel_node_x,
            self.pixel_node_y,
            np.ascontiguousarray(wanted),
        )


def _chart(rays: np.ndarray, projection: Projection) -> np.ndarray:
    """Chart coordinates (..., 2) of unit rays (..., 3); NaN where undefined."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if projection == "gnomonic":
            z = rays[..., 2]
            xy = rays[..., :2] / z[..., None]
            xy[~(z > _MIN_RAY_Z)] = np.nan
        else:
            xy = rays[..., :2] / (1.0 + rays[..., 2])[..., None]
    return xy


def _chart_rays(xy: np.ndarray, projection: Projection) -> np.ndarray:
    """Unit rays (..., 3) of chart coordinates (..., 2)."""
    x, y = xy[..., 0], xy[..., 1]
    if projection == "gnomonic":
        rays = np.stack([x, y, np.ones_like(x)], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    s2 = x * x + y * y
    return np.stack([2.0 * x, 2.0 * y, 1.0 - s2], axis=-1) / (1.0 + s2)[..., None]


def build_solve_grid(camera: CameraModel, projection: Projection, solve_scale: float) -> SolveGrid:
    """Build the solve grid of ``camera`` for one chart and scale.

    solve_scale: node density relative to the pixel density at the principal
    point, in (0, 1]. Returns a :class:`SolveGrid`.
    """
    rays = np.asarray(camera.unit_rays(), dtype=np.float64)
    pixel_xy = _chart(rays, projection)
    factor = 1.0 if projection == "gnomonic" else 0.5
    hx = factor / (camera.fx * solve_scale)
    hy = factor / (camera.fy * solve_scale)
    finite = np.all(np.isfinite(pixel_xy), axis=-1)
    if not finite.any():
        raise ValueError("the camera model maps no pixel to a viewing direction")
    x_min, y_min = np.min(pixel_xy[finite], axis=0)
    x_max, y_max = np.max(pixel_xy[finite], axis=0)
    nx = int(np.floor((x_max - x_min) / hx + 1e-6)) + 1
    ny = int(np.floor((y_max - y_min) / hy + 1e-6)) + 1
    pixel_node_x = (pixel_xy[..., 0] - x_min) / hx
    pixel_node_y = (pixel_xy[..., 1] - y_min) / hy

    identity = (
        projection == "gnomonic"
        and solve_scale == 1.0
        and not np.any(camera.D)
        and camera.K[0, 1] == 0.0
        and (ny, nx) == (camera.height, camera.width)
    )
    grid_y, grid_x = np.mgrid[0:ny, 0:nx].astype(np.float64)
    node_xy = np.stack([x_min + grid_x * hx, y_min + grid_y * hy], axis=-1)
    node_rays = _chart_rays(node_xy, projection)
    if identity:
        node_px, node_py = grid_x, grid_y
    else:
        uv = camera.project(node_rays)
        node_px = np.ascontiguousarray(uv[..., 0])
        node_py = np.ascontiguousarray(uv[..., 1])
        # A distortion polynomial folds back beyond its valid radius: keep
        # only nodes whose pixel maps back onto the node.
        inside = (
            np.isfinite(node_px)
            & (node_px >= 0) & (node_px <= camera.width - 1)
            & (node_py >= 0) & (node_py <= camera.height - 1)
        )
        coords = np.stack([np.where(inside, node_py, 0.0), np.where(inside, node_px, 0.0)])
        back_x = map_coordinates(np.nan_to_num(pixel_node_x, nan=-1e6), coords, order=1)
        back_y = map_coordinates(np.nan_to_num(pixel_node_y, nan=-1e6), coords, order=1)
        one_to_one = inside & (np.hypot(back_x - grid_x, back_y - grid_y) <= _ROUND_TRIP_TOL)
        node_px[~one_to_one] = np.nan
        node_py[~one_to_one] = np.nan
    if projection == "stereographic":
        s2 = np.sum(node_xy * node_xy, axis=-1)
        lam2 = (2.0 / (1.0 + s2)) ** 2
    else:
        lam2 = np.ones((ny, nx))
    return SolveGrid(
        projection=projection,
        shape=(ny, nx),
        spacing=(hx, hy),
        node_pixel_x=node_px,
        node_pixel_y=node_py,
        node_rays=node_rays,
        conformal_factor_sq=lam2,
        pixel_node_x=np.ascontiguousarray(pixel_node_x),
        pixel_node_y=np.ascontiguousarray(pixel_node_y),
        pixel_rays=rays,
        pixel_ray_z=np.ascontiguousarray(rays[..., 2]),
        pixel_has_ray=np.all(np.isfinite(rays), axis=-1),
        identity=identity,
    )


_GRID_CACHE: OrderedDict[tuple[object, ...], SolveGrid] = OrderedDict()


def solve_grid(camera: CameraModel, projection: Projection, solve_scale: float) -> SolveGrid:
    """:func:`build_solve_grid`, cached for the last few camera models."""
    key = (
        projection, float(solve_scale), camera.width, camera.height, camera.K.tobytes(),
        camera.D.tobytes(), camera.distortion_model, camera.binning_x, camera.binning_y,
        camera.roi,
    )
    grid = _GRID_CACHE.get(key)
    if grid is None:
        grid = build_solve_grid(camera, projection, solve_scale)
        _GRID_CACHE[key] = grid
        while len(_GRID_CACHE) > _CACHE_SIZE:
            _GRID_CACHE.popitem(last=False)
    else:
        _GRID_CACHE.move_to_end(key)
    return grid
