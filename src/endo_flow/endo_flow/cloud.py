"""The world clouds of one frame: metric depth → world points, grey levels, normals.

A frame gives two clouds: the live topic's, every ``cloud_decimation``-th
pixel along each axis, and the map's, every ``map_decimation``-th (1: full
resolution). Both come from the grid at the decimations' greatest common
divisor (:func:`world_clouds`) and the unit rays of the binned camera model
(:func:`binned_camera`: the same rays at those pixels, cached by the model);
each cloud takes every n-th node of that organised grid and back-projects
only its nodes, in the pass below, with the arithmetic of
:meth:`endo_io.camera.CameraModel.depth_to_points` (the same bits, without
its (h, w, 3) float64 grid). Each cloud's camera-facing normals come from central
differences of its own grid (neighbours ``decimation`` pixels apart, so the
live cloud's normals do not depend on whether the map took a cloud this
frame), and its points within the depth range are moved into ``world`` as
:func:`endo_io.pose.transform_points` moves them; normals are rotated alike.
The back-projection, the range test, the grid's normals and the transform are
one numba pass over the grid (:func:`_kept_normals`; the numpy version made
~10 full-grid temporaries, and at full resolution the transform's matrix
product alone cost ~10 ms per 640×480 frame).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence

import numba
import numpy as np

from endo_io.camera import CameraModel
from endo_io.image import irradiance_to_mono8

#: Binned models by (ray geometry, factor), newest last: their ray tables are
#: computed once per process (the warm-up's camera and the stream's are two
#: instances of one geometry; a 640×480 table took 340 ms at load 11).
_BINNED: OrderedDict[tuple[object, ...], CameraModel] = OrderedDict()
_BINNED_HELD = 8


def binned_camera(camera: CameraModel, factor: int) -> CameraModel:
    """The model of ``image[:H//f*f:f, :W//f*f:f]``: every f-th pixel of the camera's image.

    Pixel u' of the decimated image is pixel f·u' of the original, which is
    exactly image_geometry's binning mapping (``CameraModel`` binning
    without ROI), so its ray table is the original's at those pixels.

    The model is shared by every camera of the same size, K, D and
    distortion model (the last 8 asked for are held), so that its ray table
    (:meth:`CameraModel.unit_rays`, cached by the model) is computed once
    per process: the flow node's warm-up computes the tables its frames
    will use. Only the rays are the same: use it for back-projection, not
    for its frame_id.
    """
    key = (camera.width, camera.height, camera.distortion_model, camera.K.tobytes(),
           np.asarray(camera.D, np.float64).tobytes(), int(factor))
    model = _BINNED.get(key)
    if model is None:
        K = camera.K.copy()
        K[:2] /= factor
        model = CameraModel(
            width=camera.width // factor, height=camera.height // factor, K=K, D=camera.D,
            distortion_model=camera.distortion_model, binning_x=factor, binning_y=factor,
            frame_id=camera.frame_id, full_width=camera.width, full_height=camera.height,
        ) if factor != 1 else CameraModel(
            width=camera.width, height=camera.height, K=camera.K.copy(), D=camera.D,
            distortion_model=camera.distortion_model, frame_id=camera.frame_id,
        )
        _BINNED[key] = model
        while len(_BINNED) > _BINNED_HELD:
            _BINNED.popitem(last=False)
    else:
        _BINNED.move_to_end(key)
    return model


@numba.njit(cache=True, nogil=True)
def _normal_of(
    left: tuple[float, float, float], right: tuple[float, float, float],
    up: tuple[float, float, float], down: tuple[float, float, float],
    centre: tuple[float, float, float],
) -> tuple[np.float32, np.float32, np.float32]:
    """The unit normal of a node from its four neighbours' points and its own, facing the origin.

    The arithmetic is the numpy version's, operation for operation: float32
    differences and cross products, the length in float32 and the division
    by length × sign in float64, stored as float32. NaN where a neighbour is
    missing or the cross product vanishes. The one implementation
    :func:`_grid_normals` (through :func:`_grid_normal`) and
    :func:`_kept_normals` call.
    """
    dux = np.float32(right[0]) - np.float32(left[0])
    duy = np.float32(right[1]) - np.float32(left[1])
    duz = np.float32(right[2]) - np.float32(left[2])
    dvx = np.float32(down[0]) - np.float32(up[0])
    dvy = np.float32(down[1]) - np.float32(up[1])
    dvz = np.float32(down[2]) - np.float32(up[2])
    nx = duy * dvz - duz * dvy
    ny = duz * dvx - dux * dvz
    nz = dux * dvy - duy * dvx
    facing = (nx * np.float32(centre[0]) + ny * np.float32(centre[1])
              + nz * np.float32(centre[2]))
    length = np.sqrt(nx * nx + ny * ny + nz * nz)
    denom = np.float64(length) * (-1.0 if facing > 0.0 else 1.0)
    return (np.float32(np.float64(nx) / denom), np.float32(np.float64(ny) / denom),
            np.float32(np.float64(nz) / denom))


@numba.njit(cache=True, nogil=True)
def _grid_point(points: np.ndarray, r: int, c: int) -> tuple[float, float, float]:
    """Node (r, c) of an (h, w, 3) point grid."""
    return points[r, c, 0], points[r, c, 1], points[r, c, 2]


@numba.njit(cache=True, nogil=True)
def _grid_normal(points: np.ndarray, r: int, c: int) -> tuple[np.float32, np.float32, np.float32]:
    """The unit normal at interior node (r, c) of an (h, w, 3) point grid (:func:`_normal_of`)."""
    return _normal_of(_grid_point(points, r, c - 1), _grid_point(points, r, c + 1),
                      _grid_point(points, r - 1, c), _grid_point(points, r + 1, c),
                      _grid_point(points, r, c))


@numba.njit(cache=True, nogil=True)
def _ray_point(depth: np.ndarray, rays: np.ndarray, r: int, c: int) -> tuple[float, float, float]:
    """The camera-frame point of node (r, c): :meth:`CameraModel.depth_to_points`'s arithmetic.

    ``depth / ray_z · ray`` in float64 where the depth is > 0, NaN elsewhere
    (the same operations in the same order, so the same bits).
    """
    z = np.float64(depth[r, c])
    if z > 0.0:
        length = z / rays[r, c, 2]
        return length * rays[r, c, 0], length * rays[r, c, 1], length * rays[r, c, 2]
    return np.nan, np.nan, np.nan


@numba.njit(cache=True, nogil=True)
def _grid_normals(points: np.ndarray, normals: np.ndarray) -> None:
    """Fill ``normals`` (h, w, 3) float32 from the (h, w, 3) point grid (see surface_normals)."""
    h, w = points.shape[0], points.shape[1]
    normals[:] = np.nan
    for r in range(1, h - 1):
        for c in range(1, w - 1):
            normals[r, c, 0], normals[r, c, 1], normals[r, c, 2] = _grid_normal(points, r, c)


def surface_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals of an organised (h, w, 3) point grid, facing the camera at the origin.

    Central differences along both axes, crossed; NaN on the border and
    wherever a neighbour is missing (or the cross product vanishes).

    Args:
        points: (h, w, 3) float points in the camera frame, NaN invalid.

    Returns:
        (h, w, 3) float32 unit normals.
    """
    p = np.ascontiguousarray(points)
    if p.ndim != 3 or p.shape[2] != 3:
        raise ValueError(f"points must be (h, w, 3), got {p.shape}")
    normals = np.empty(p.shape, np.float32)
    _grid_normals(p, normals)
    return normals


@numba.njit(cache=True, nogil=True)
def _kept_normals(
    depth: np.ndarray, rays: np.ndarray, lo: float, hi: float, R: np.ndarray,
    t: np.ndarray, index: np.ndarray, world: np.ndarray, normals: np.ndarray,
    row_start: int, row_stop: int,
) -> int:
    """The grid nodes kept, their world points and normals, in one pass; returns how many.

    Each node is back-projected in the pass (:func:`_ray_point`: ``depth`` by
    the unit ``rays`` of the same (h, w) grid, as
    :meth:`endo_io.camera.CameraModel.depth_to_points` does it, bit for bit),
    so no (h, w, 3) float64 point grid is made (at full resolution 7.4 MB
    written and read again per map frame). Only rows ``row_start`` to
    ``row_stop`` (excluded) of the grid are visited; a node's normal still
    reads its neighbours in the rows around (the grid's border is the whole
    grid's), so bands of rows give, end to end, what the whole grid gives. A
    node is kept when its depth is in [lo, hi] and its point is finite;
    ``index[:n]`` receives the kept nodes' flat indices (row-major),
    ``world[:n]`` their points moved by (R, t) as
    :func:`endo_io.pose.transform_points` moves them (R @ p + t in float64,
    stored as float32; the test holds the two together), and ``normals[:n]``
    their unit normals (:func:`surface_normals`'s arithmetic, NaN on the
    border and next to a missing neighbour) rotated by ``R`` in float64 and
    stored as float32. In the pass, not through ``transform_points``: at full
    resolution its (N, 3) @ (3, 3) product and the gather before it cost
    ~10 ms of 307 200 points on one thread, and OpenBLAS's threads spun on a
    loaded machine (160 ms wall per frame at load 10).
    """
    h, w = depth.shape
    n = 0
    for r in range(row_start, row_stop):
        for c in range(w):
            z = depth[r, c]
            if not (z >= lo and z <= hi):
                continue
            px, py, pz = _ray_point(depth, rays, r, c)
            if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
                continue
            index[n] = r * w + c
            world[n, 0] = np.float32(R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0])
            world[n, 1] = np.float32(R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1])
            world[n, 2] = np.float32(R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2])
            if r == 0 or c == 0 or r == h - 1 or c == w - 1:
                normals[n, 0] = np.nan
                normals[n, 1] = np.nan
                normals[n, 2] = np.nan
                n += 1
                continue
            gx, gy, gz = _normal_of(_ray_point(depth, rays, r, c - 1),
                                    _ray_point(depth, rays, r, c + 1),
                                    _ray_point(depth, rays, r - 1, c),
                                    _ray_point(depth, rays, r + 1, c), (px, py, pz))
            ax, ay, az = np.float64(gx), np.float64(gy), np.float64(gz)
            normals[n, 0] = np.float32(R[0, 0] * ax + R[0, 1] * ay + R[0, 2] * az)
            normals[n, 1] = np.float32(R[1, 0] * ax + R[1, 1] * ay + R[1, 2] * az)
            normals[n, 2] = np.float32(R[2, 0] * ax + R[2, 1] * ay + R[2, 2] * az)
            n += 1
    return n


Cloud = tuple[np.ndarray, np.ndarray, np.ndarray]
"""(M, 3) float32 world points, metres; (M,) uint8 grey; (M, 3) float32 unit world normals."""


def world_clouds(
    depth: np.ndarray,
    image: np.ndarray,
    camera: CameraModel,
    T_world_camera: np.ndarray,
    *,
    decimations: Sequence[int],
    min_depth_m: float,
    max_depth_m: float,
    white: float,
    gamma: float,
) -> list[Cloud]:
    """World clouds of one metric depth image at several decimations, from one back-projection.

    Args:
        depth: (H, W) float32 metric depth along z, metres, NaN invalid.
        image: (H, W) float linear irradiance of the same frame.
        camera: the binned model of the grid at the greatest common divisor
            g of ``decimations`` (``binned_camera(full_camera, g)``).
        T_world_camera: (4, 4) camera pose, metres.
        decimations: each cloud takes every this-th pixel along each axis;
            each must be a multiple of g (true of any set: g divides them).
        min_depth_m, max_depth_m: depth range of the points kept.
        white, gamma: the 8-bit mapping of the grey level
            (:func:`endo_io.image.irradiance_to_mono8`).

    Returns:
        One cloud per decimation, in their order (equal decimations share
        one): ((M, 3) float32 world points, metres; (M,) uint8 grey; (M, 3)
        float32 unit world normals facing the camera, NaN where a neighbour
        was missing), in row-major order of that decimation's grid, which is
        ``binned_camera(full_camera, decimation)``'s.

    Raises:
        ValueError: no decimation or one below 1, or ``depth`` too small
            for ``camera`` at step g.
    """
    if not decimations or min(decimations) < 1:
        raise ValueError(f"decimations must be >= 1, got {list(decimations)}")
    step = math.gcd(*(int(k) for k in decimations))
    sub, grey_grid = _grid(depth, image, camera, step)
    rays = camera.unit_rays()
    clouds: dict[int, Cloud] = {}
    for k in decimations:
        if int(k) in clouds:
            continue
        s = int(k) // step
        if s == 1:
            clouds[int(k)] = _grid_cloud(rays, sub, grey_grid, T_world_camera, min_depth_m,
                                         max_depth_m, white, gamma)
            continue
        h, w = camera.height // s * s, camera.width // s * s
        every = np.ascontiguousarray(rays[:h:s, :w:s])
        every.setflags(write=False)  # as the table itself: one numba signature for both
        clouds[int(k)] = _grid_cloud(
            every, sub[:h:s, :w:s], grey_grid[:h:s, :w:s],
            T_world_camera, min_depth_m, max_depth_m, white, gamma)
    return [clouds[int(k)] for k in decimations]


def _grid(
    depth: np.ndarray, image: np.ndarray, camera: CameraModel, step: int
) -> tuple[np.ndarray, np.ndarray]:
    """The depth and image nodes of the ``camera`` grid: every ``step``-th pixel (views)."""
    rows, cols = slice(0, camera.height * step, step), slice(0, camera.width * step, step)
    sub = np.asarray(depth)[rows, cols]
    if sub.shape != (camera.height, camera.width):
        raise ValueError(f"depth {np.shape(depth)} has no {camera.width}x{camera.height} grid "
                         f"at step {step}")
    return sub, np.asarray(image)[rows, cols]


def _grid_cloud(
    rays: np.ndarray, depth: np.ndarray, image: np.ndarray, T_world_camera: np.ndarray,
    min_depth_m: float, max_depth_m: float, white: float, gamma: float,
    rows: tuple[int, int] | None = None,
) -> Cloud:
    """The world cloud of an organised (h, w) depth grid and its (h, w, 3) unit rays.

    See :func:`world_clouds`. ``rows``: only the grid rows from the first to
    the second (excluded); None: all.
    """
    h, w = depth.shape
    T = np.asarray(T_world_camera, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_camera must be (4, 4), got {T.shape}")
    start, stop = (0, h) if rows is None else rows
    size = max(stop - start, 0) * w
    index = np.empty(size, np.int64)
    world = np.empty((size, 3), np.float32)
    normals = np.empty((size, 3), np.float32)
    n = _kept_normals(np.ascontiguousarray(depth), np.ascontiguousarray(rays),
                      float(min_depth_m), float(max_depth_m), np.ascontiguousarray(T[:3, :3]),
                      np.ascontiguousarray(T[:3, 3]), index, world, normals, start, stop)
    index, world, normals = index[:n], world[:n], normals[:n]
    grey = irradiance_to_mono8(np.asarray(image).reshape(1, -1).take(index, axis=1),
                               white=white, gamma=gamma)[0]
    return world, grey, normals


class BandedCloud:
    """One frame's world cloud at one decimation, built a band of grid rows at a time.

    The bands, concatenated in the order taken, are :func:`world_cloud`'s
    cloud (same points, grey levels and normals, same order; tested): a
    node's normal reads the rows around its band. The live flow node fuses
    a frame's full-resolution map cloud this way over the frames that
    follow, so that no one frame carries the whole cloud and its insert.
    Each band's nodes are back-projected as it is taken (in the pass).

    Args:
        depth, image, camera, T_world_camera, decimation, min_depth_m,
        max_depth_m, white, gamma: as :func:`world_cloud`'s. The arrays
        are held (not copied) until the last band is taken.
    """

    def __init__(
        self,
        depth: np.ndarray,
        image: np.ndarray,
        camera: CameraModel,
        T_world_camera: np.ndarray,
        *,
        decimation: int,
        min_depth_m: float,
        max_depth_m: float,
        white: float,
        gamma: float,
    ) -> None:
        if decimation < 1:
            raise ValueError(f"decimation must be >= 1, got {decimation}")
        self._depth, self._image = _grid(depth, image, camera, int(decimation))
        self._camera = camera
        self._T = np.asarray(T_world_camera, np.float64)
        self._range = (float(min_depth_m), float(max_depth_m))
        self._grey = (float(white), float(gamma))
        #: grid rows of the decimated grid, and the first not yet taken
        self.rows = camera.height
        self.next_row = 0

    @property
    def done(self) -> bool:
        """Whether every row has been taken."""
        return self.next_row >= self.rows

    def take(self, rows: int) -> Cloud:
        """The cloud of the next ``rows`` grid rows (fewer at the end; empty when done)."""
        if rows < 1:
            raise ValueError(f"rows must be >= 1, got {rows}")
        start = self.next_row
        self.next_row = min(start + int(rows), self.rows)
        return _grid_cloud(self._camera.unit_rays(), self._depth, self._image, self._T,
                           *self._range, *self._grey, rows=(start, self.next_row))


def world_cloud(
    depth: np.ndarray,
    image: np.ndarray,
    camera: CameraModel,
    T_world_camera: np.ndarray,
    *,
    decimation: int,
    min_depth_m: float,
    max_depth_m: float,
    white: float,
    gamma: float,
) -> Cloud:
    """The world cloud of one decimation (:func:`world_clouds` with one).

    Args:
        depth: (H, W) float32 metric depth along z, metres, NaN invalid.
        image: (H, W) float linear irradiance of the same frame.
        camera: the binned model of the decimated grid
            (``binned_camera(full_camera, decimation)``).
        T_world_camera: (4, 4) camera pose, metres.
        decimation: every this-th pixel along each axis.
        min_depth_m, max_depth_m: depth range of the points kept.
        white, gamma: the 8-bit mapping of the grey level.

    Returns:
        ((M, 3) float32 world points, metres; (M,) uint8 grey; (M, 3)
        float32 unit world normals facing the camera, NaN where a neighbour
        was missing), in row-major order of the decimated grid.
    """
    return world_clouds(depth, image, camera, T_world_camera, decimations=(decimation,),
                        min_depth_m=min_depth_m, max_depth_m=max_depth_m, white=white,
                        gamma=gamma)[0]
