"""The previous solution moved by the known camera motion: a warm start for the next frame.

The near-light solver's first pass visits the nodes in the order of a
predicted solution (:mod:`endo_sfs.visit_order`). The previous frame's
solution as it stands is a poor predictor on moving video: the walls move
by 1–2 % of their distance per frame, more than the difference between
neighbouring nodes, so many neighbouring pairs come out in the wrong order.
With the camera's motion between the two frames (from the tracker), the
previous surface can be moved into the new view instead:

* every node of the solve grid is a viewing direction ω (the grid is a chart
  of the ray sphere, :mod:`endo_sfs.grid`), and the previous solution v = ln r
  puts a surface point at r·ω in the previous camera frame;
* ``T_current_previous`` (R, t) takes it to the current camera frame;
* the predicted v at a node of the current frame is the log-distance of the
  previous surface along that node's ray, found by inverse warping: start
  from the previous value at the same node, look the previous surface up
  where the current ray meets it, move that point, repeat (three fixed-point
  steps; the motion between frames is small against the distance).

Because the grid lives on the ray sphere, no lens model enters: the warp is
the same for any distortion.

**Units.** depth_relative is relative: metric depth = s × relative depth,
with s (metres per unit) unknown to the solver and estimated by ``endo_flow``
(the scale topic). A rotation needs no scale; a translation in metres must be
divided by s. :func:`predict_warm_start` takes ``metres_per_unit`` from the
caller (endo_flow's scale, or :func:`estimate_metres_per_unit` fitted on the
solved frames themselves) or ``None`` for a rotation-only prediction. The
solver's global shift (the median change of the data's singular value,
:func:`endo_sfs.near_light.global_shift`) is computed against the predicted
irradiance, so it corrects whatever distance change the prediction misses.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from endo_io.pose import invert_transform
from endo_sfs.errors import SfsInputError
from endo_sfs.grid import SolveGrid
from endo_sfs.relative_depth import PredictedStart, SfsSolution

#: Fixed-point steps of the inverse warp (each is one bilinear lookup per node).
WARP_STEPS = 3


def relative_motion(T_world_previous: np.ndarray, T_world_current: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_current_previous``: previous camera coordinates to current ones (metres)."""
    return invert_transform(np.asarray(T_world_current, dtype=np.float64)) @ np.asarray(
        T_world_previous, dtype=np.float64
    )


def chart_origin(grid: SolveGrid) -> tuple[float, float]:
    """Stereographic chart coordinates of node (0, 0) of ``grid``."""
    ray = grid.node_rays[0, 0]
    return float(ray[0] / (1.0 + ray[2])), float(ray[1] / (1.0 + ray[2]))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bilinear(grid: np.ndarray, gx: float, gy: float) -> float:
    """Bilinear value of ``grid`` at node coordinates (gx, gy); NaN unless all four are finite."""
    ny, nx = grid.shape
    if not (gx >= 0.0 and gy >= 0.0 and gx <= nx - 1 and gy <= ny - 1):
        return np.nan
    x0 = min(int(gx), nx - 2)
    y0 = min(int(gy), ny - 2)
    fx = gx - x0
    fy = gy - y0
    top = grid[y0, x0] * (1.0 - fx) + grid[y0, x0 + 1] * fx
    bottom = grid[y0 + 1, x0] * (1.0 - fx) + grid[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def warp_log_distance(
    previous: np.ndarray,
    previous_extra: np.ndarray,
    node_rays: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    origin_x: float,
    origin_y: float,
    hx: float,
    hy: float,
    stride: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The previous surface (ln r per node) seen from the moved camera, per node.

    previous: (ny, nx) float64 ln r of the previous frame, NaN unknown.
    previous_extra: (k, ny, nx) float64 per-node values carried along with
    the surface (irradiance, slope), NaN unknown. node_rays: (ny, nx, 3)
    unit rays of the stereographic grid; rotation (3, 3), translation (3,):
    previous camera coordinates to current (p' = R·p + t, in the unit of
    e^v). origin_x, origin_y, hx, hy: the chart's node (0, 0) and spacing.
    stride: every stride-th node in each direction is computed (1: all).
    Returns ((my, mx) predicted ln r, NaN where the lookup leaves the
    previous solution; (k, my, mx) the carried values there; (my, mx) the
    previous ln r of the looked-up point, i.e. before the move).
    """
    ny, nx = previous.shape
    my = (ny + stride - 1) // stride
    mx = (nx + stride - 1) // stride
    extras = previous_extra.shape[0]
    out = np.full((my, mx), np.nan)
    before = np.full((my, mx), np.nan)
    carried = np.full((extras, my, mx), np.nan)
    for a in prange(my):
        i = a * stride
        for b in range(mx):
            j = b * stride
            guess = previous[i, j]
            if not np.isfinite(guess):
                continue
            wx = node_rays[i, j, 0]
            wy = node_rays[i, j, 1]
            wz = node_rays[i, j, 2]
            r_new = np.exp(guess)
            v_prev = np.nan
            gx = 0.0
            gy = 0.0
            for _ in range(WARP_STEPS):
                # The current ray's point at the guessed distance, in the
                # previous camera: p = Rᵀ(p' − t).
                qx = r_new * wx - translation[0]
                qy = r_new * wy - translation[1]
                qz = r_new * wz - translation[2]
                px = rotation[0, 0] * qx + rotation[1, 0] * qy + rotation[2, 0] * qz
                py = rotation[0, 1] * qx + rotation[1, 1] * qy + rotation[2, 1] * qz
                pz = rotation[0, 2] * qx + rotation[1, 2] * qy + rotation[2, 2] * qz
                norm = np.sqrt(px * px + py * py + pz * pz)
                ux = px / norm
                uy = py / norm
                uz = pz / norm
                if not uz > -0.9:
                    v_prev = np.nan
                    break
                gx = (ux / (1.0 + uz) - origin_x) / hx
                gy = (uy / (1.0 + uz) - origin_y) / hy
                v_prev = _bilinear(previous, gx, gy)
                if not np.isfinite(v_prev):
                    break
                # The previous surface's point along that direction, moved.
                r_prev = np.exp(v_prev)
                sx = r_prev * ux
                sy = r_prev * uy
                sz = r_prev * uz
                mx_ = rotation[0, 0] * sx + rotation[0, 1] * sy + rotation[0, 2] * sz \
                    + translation[0]
                my_ = rotation[1, 0] * sx + rotation[1, 1] * sy + rotation[1, 2] * sz \
                    + translation[1]
                mz_ = rotation[2, 0] * sx + rotation[2, 1] * sy + rotation[2, 2] * sz \
                    + translation[2]
                r_new = np.sqrt(mx_ * mx_ + my_ * my_ + mz_ * mz_)
            if not np.isfinite(v_prev):
                continue
            out[a, b] = np.log(r_new)
            before[a, b] = v_prev
            for k in range(extras):
                carried[k, a, b] = _bilinear(previous_extra[k], gx, gy)
    return out, carried, before


def _motion_in_units(
    T_current_previous: np.ndarray, metres_per_unit: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with t in depth_relative units (zero without a scale)."""
    T = np.asarray(T_current_previous, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise SfsInputError(f"camera motion must be a finite (4, 4) transform, got {T.shape}")
    rotation = np.ascontiguousarray(T[:3, :3])
    if metres_per_unit is None:
        return rotation, np.zeros(3)
    if not (np.isfinite(metres_per_unit) and metres_per_unit > 0.0):
        raise SfsInputError(f"metres_per_unit must be finite and > 0, got {metres_per_unit}")
    return rotation, np.ascontiguousarray(T[:3, 3] / metres_per_unit)


def _warp(
    grid: SolveGrid,
    previous: np.ndarray,
    extra: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    stride: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    origin_x, origin_y = chart_origin(grid)
    hx, hy = grid.spacing
    return warp_log_distance(
        np.ascontiguousarray(previous, dtype=np.float64), extra,
        np.ascontiguousarray(grid.node_rays), rotation, translation, origin_x, origin_y,
        hx, hy, stride,
    )


def predict_warm_start(
    previous: SfsSolution,
    T_current_previous: np.ndarray,
    *,
    metres_per_unit: float | None,
) -> PredictedStart:
    """The previous near-light solution moved into the current view.

    previous: the previous frame's :class:`endo_sfs.relative_depth.SfsSolution`
    (near-light). T_current_previous: (4, 4) rigid transform from the
    previous camera frame to the current one, metres
    (:func:`relative_motion` of the two ``T_world_camera``).
    metres_per_unit: metres per unit of depth_relative (endo_flow's scale, or
    :func:`estimate_metres_per_unit`); None moves by the rotation only.
    Returns a :class:`PredictedStart` for :func:`endo_sfs.solve`'s
    ``warm_start``.

    Raises:
        SfsInputError: not a near-light solution, or a bad transform or scale.
    """
    if not isinstance(previous, SfsSolution) or previous.model != "near_light":
        raise SfsInputError("a pose-predicted warm start needs a near-light SfsSolution")
    rotation, translation = _motion_in_units(T_current_previous, metres_per_unit)
    irradiance = previous.node_irradiance
    slope = previous.node_slope if previous.node_slope is not None else np.full_like(
        irradiance, np.nan
    )
    extra = np.ascontiguousarray(np.stack([irradiance, slope]), dtype=np.float64)
    predicted, carried, before = _warp(
        previous.grid, previous.node_solution, extra, rotation, translation, 1
    )
    # The same patch at the new distance reads I·(r/r')² (the angle to the
    # ray changes little between frames).
    with np.errstate(invalid="ignore", over="ignore"):
        moved_irradiance = carried[0] * np.exp(2.0 * (before - predicted))
    return PredictedStart(
        node_solution=predicted,
        node_irradiance=moved_irradiance,
        node_slope=carried[1] if previous.node_slope is not None else None,
        grid=previous.grid,
        ordered_work=previous.ordered_work,
        frames_since_ordered=previous.frames_since_ordered,
        ordered_retries=previous.ordered_retries,
    )


#: Node stride of the scale fit (every 4th node in each direction).
_FIT_STRIDE = 4
#: Scale fits: Gauss–Newton steps on 1/s.
_FIT_STEPS = 3


def estimate_metres_per_unit(
    previous: SfsSolution,
    current: SfsSolution,
    T_current_previous: np.ndarray,
    *,
    initial: float | None = None,
) -> float | None:
    """The metres per depth_relative unit that best moves one solution onto the next.

    previous, current: two near-light :class:`SfsSolution` of the same grid;
    T_current_previous: (4, 4) their relative camera motion in metres.
    Fits u = 1/s (units per metre) so that the previous solution moved by
    (R, u·t) matches the current one (least squares in ln r over every 4th
    node, Gauss–Newton from ``initial`` or 0). Returns s, or None when
    the motion has no translation to measure it by (or the fit fails).
    """
    if not (isinstance(previous, SfsSolution) and isinstance(current, SfsSolution)):
        return None
    if previous.grid is not current.grid:
        return None
    T = np.asarray(T_current_previous, dtype=np.float64)
    rotation = np.ascontiguousarray(T[:3, :3])
    direction = T[:3, 3]
    if not np.all(np.isfinite(T)) or np.linalg.norm(direction) <= 0.0:
        return None
    target = current.node_solution[::_FIT_STRIDE, ::_FIT_STRIDE]
    none = np.empty((0, *previous.node_solution.shape))
    units = 1.0 / initial if initial else 0.0
    step = 1e-3 / np.linalg.norm(direction)  # a motion of 1e-3 units, for the derivative
    for _ in range(_FIT_STEPS):
        base, _, _ = _warp(previous.grid, previous.node_solution, none, rotation,
                           np.ascontiguousarray(direction * units), _FIT_STRIDE)
        moved, _, _ = _warp(previous.grid, previous.node_solution, none, rotation,
                            np.ascontiguousarray(direction * (units + step)), _FIT_STRIDE)
        derivative = (moved - base) / step
        residual = target - base
        ok = np.isfinite(derivative) & np.isfinite(residual)
        if ok.sum() < 100:
            return None
        g = derivative[ok]
        r = residual[ok]
        denominator = float(g @ g)
        if denominator <= 0.0:
            return None
        units += float(g @ r) / denominator
    if not units > 0.0:
        return None
    return 1.0 / units
