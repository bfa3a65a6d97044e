"""Abdominal wall: a gently curved, undulating surface seen from 20–80 mm.

Geometry (world frame, metres)
------------------------------
The insufflated abdomen seen from inside is a dome: the wall is concave
towards the laparoscope. It is the height field

    z = w(x, y) = −(x² + y²) / (2·Rc) + b(x, y)

with curvature radius ``Rc`` and a periodic bicubic B-spline ``b`` of random
undulations (bowel loops and fat under the peritoneum, a few millimetres high
over centimetres; seeded). The camera sits below (z < w) and looks up (+z).
The implicit function F = w(x, y) − z is positive on the camera side.

Ray casting
-----------
The ray's intersection with the bare paraboloid (b = 0) is a quadratic with a
closed-form root; Newton's method on F along the ray starts there and
converges in a few steps because the undulations are gentle (slopes < 0.5).
Newton stops once the error left, bounded by step²·max|F''|/(2|F'|), is below
1e-9 m. If Newton fails (never with the defaults), the ray is marched in
0.5 mm steps and the first sign change is bisected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from endo_sim.bands import run_in_bands
from endo_sim.bspline import random_control, surface_value, wrap_grid
from endo_sim.errors import SimulationParameterError
from endo_sim.surface import SurfaceHits
from endo_sim.surface import no_hit as _no_hit
from endo_sim.texture import Texture

#: Newton stops when the error left after its last step is below this (metres).
ACCURACY_M = 1e-9
#: Fallback march step (metres) and range.
MARCH_STEP_M = 5e-4
MAX_DISTANCE_M = 0.5


@dataclass(frozen=True)
class AbdomenGeometry:
    """Shape of the abdominal wall (metres).

    curvature_radius_m: 0.15 m, about the radius of an insufflated adult
    abdomen's dome; undulation_m: ±3 mm; knot spacing 18 mm.
    """

    curvature_radius_m: float = 0.15
    undulation_m: float = 0.003
    knot_spacing_m: float = 0.018
    knots: int = 24

    def __post_init__(self) -> None:
        if self.curvature_radius_m < 0.03:
            raise SimulationParameterError("abdomen curvature radius must be >= 30 mm")
        if not 0.0 <= self.undulation_m <= 0.25 * self.knot_spacing_m:
            raise SimulationParameterError(
                "undulation must be in [0, knot_spacing/4] (gentle slopes)"
            )
        if self.knots < 4 or self.knot_spacing_m <= 0.0:
            raise SimulationParameterError(
                "the undulation spline needs >= 4 knots and a spacing > 0"
            )


@nb.njit(cache=True, nogil=True, inline="always")
def abdomen_field(
    x: float, y: float, z: float, inv_two_rc: float, bumps: np.ndarray, inv_spacing: float
) -> tuple[float, float, float, float]:
    """F = w(x, y) − z (metres, > 0 on the camera side) and its gradient.

    bumps: wrapped control grid (:func:`~endo_sim.bspline.wrap_grid`);
    inv_spacing: 1 / knot spacing.
    """
    h, hx, hy = surface_value(bumps, inv_spacing, x, y)
    return (
        h - (x * x + y * y) * inv_two_rc - z,
        hx - 2.0 * x * inv_two_rc,
        hy - 2.0 * y * inv_two_rc,
        -1.0,
    )


#: The field compiled once without forced inlining, for the rare fallback.
_abdomen_field_outlined = nb.njit(cache=True, nogil=True)(abdomen_field.py_func)


@nb.njit(cache=True, nogil=True)
def _march(
    o: np.ndarray,
    d: tuple[float, float, float],
    inv_two_rc: float,
    bumps: np.ndarray,
    inv_spacing: float,
) -> tuple[float, float, float, float]:
    """Fallback: fixed steps to the first sign change of F, then bisection."""
    dx, dy, dz = d
    lo = 0.0
    if _abdomen_field_outlined(o[0], o[1], o[2], inv_two_rc, bumps, inv_spacing)[0] <= 0.0:
        return math.nan, 0.0, 0.0, 0.0
    hi = MARCH_STEP_M
    while hi < MAX_DISTANCE_M:
        x, y, z = o[0] + hi * dx, o[1] + hi * dy, o[2] + hi * dz
        if _abdomen_field_outlined(x, y, z, inv_two_rc, bumps, inv_spacing)[0] <= 0.0:
            for _ in range(80):
                mid = 0.5 * (lo + hi)
                x, y, z = o[0] + mid * dx, o[1] + mid * dy, o[2] + mid * dz
                if _abdomen_field_outlined(x, y, z, inv_two_rc, bumps, inv_spacing)[0] > 0.0:
                    lo = mid
                else:
                    hi = mid
            t = 0.5 * (lo + hi)
            x, y, z = o[0] + t * dx, o[1] + t * dy, o[2] + t * dz
            _f, gx, gy, gz = _abdomen_field_outlined(x, y, z, inv_two_rc, bumps, inv_spacing)
            return t, gx, gy, gz
        lo = hi
        hi += MARCH_STEP_M
    return math.nan, 0.0, 0.0, 0.0


@nb.njit(cache=True, nogil=True)
def abdomen_trace(
    origin: np.ndarray,
    rotation: np.ndarray,
    rays: np.ndarray,
    mask: np.ndarray,
    inv_two_rc: float,
    bumps: np.ndarray,
    inv_spacing: float,
    half_curvature: float,
    out_distance: np.ndarray,
    out_normal: np.ndarray,
    out_uv: np.ndarray,
    row_start: int,
    row_stop: int,
) -> None:
    """Ray cast the wall for every pixel of ``mask`` in rows [row_start, row_stop).

    origin (3,), rotation (3, 3) camera-to-world; rays (H, W, 3) camera frame;
    mask (H, W). half_curvature: bound of |F''|/2 along a ray (m⁻¹) for the
    Newton stopping rule. Writes distance (H, W) metres (NaN: masked/no hit),
    the camera-frame unit normal facing the camera (H, W, 3) and
    uv = (y, x) world metres (H, W, 2).
    """
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(row_start, row_stop):
        for j in range(mask.shape[1]):
            if not mask[i, j]:
                _no_hit(out_distance, out_normal, out_uv, i, j)
                continue
            r = rays[i, j]
            dx = rotation[0, 0] * r[0] + rotation[0, 1] * r[1] + rotation[0, 2] * r[2]
            dy = rotation[1, 0] * r[0] + rotation[1, 1] * r[1] + rotation[1, 2] * r[2]
            dz = rotation[2, 0] * r[0] + rotation[2, 1] * r[1] + rotation[2, 2] * r[2]
            # Paraboloid: A t² + B t + C = 0 with C < 0 (camera below the wall).
            qa = (dx * dx + dy * dy) * inv_two_rc
            qb = 2.0 * (ox * dx + oy * dy) * inv_two_rc + dz
            qc = (ox * ox + oy * oy) * inv_two_rc + oz
            t = math.nan
            if qc < 0.0:
                t = -2.0 * qc / (qb + math.sqrt(qb * qb - 4.0 * qa * qc))
            gx = gy = gz = 0.0
            converged = False
            if t == t:
                for _ in range(20):
                    x, y, z = ox + t * dx, oy + t * dy, oz + t * dz
                    f, gx, gy, gz = abdomen_field(x, y, z, inv_two_rc, bumps, inv_spacing)
                    slope = gx * dx + gy * dy + gz * dz
                    if slope >= -1e-3 or t < 0.0:
                        break
                    step = -f / slope
                    t += step
                    # Quadratic convergence: the error left is below
                    # step²·|F''|/(2|F'|); stop once that is under the accuracy.
                    if step * step * half_curvature < -ACCURACY_M * slope:
                        converged = t > 0.0
                        break
            if not converged:
                t, gx, gy, gz = _march(origin, (dx, dy, dz), inv_two_rc, bumps, inv_spacing)
            if t != t:
                _no_hit(out_distance, out_normal, out_uv, i, j)
                continue
            out_distance[i, j] = t
            norm = math.sqrt(gx * gx + gy * gy + gz * gz)
            gx /= norm
            gy /= norm
            gz /= norm
            out_normal[i, j, 0] = rotation[0, 0] * gx + rotation[1, 0] * gy + rotation[2, 0] * gz
            out_normal[i, j, 1] = rotation[0, 1] * gx + rotation[1, 1] * gy + rotation[2, 1] * gz
            out_normal[i, j, 2] = rotation[0, 2] * gx + rotation[1, 2] * gy + rotation[2, 2] * gz
            out_uv[i, j, 0] = oy + t * dy
            out_uv[i, j, 1] = ox + t * dx


class AbdomenScene:
    """The abdominal wall (:class:`AbdomenGeometry`) with a tissue texture over (y, x)."""

    name = "abdomen"
    #: Moist peritoneum: a little less glossy than colon mucosa.
    specular_weight = 0.7

    def __init__(self, geometry: AbdomenGeometry, texture: Texture, seed: int) -> None:
        self.geometry = geometry
        self.texture = texture
        rng = np.random.default_rng([int(seed), 0xAB0])
        control = random_control(rng, (geometry.knots, geometry.knots), geometry.undulation_m)
        self.bumps = wrap_grid(control)
        # |F''| along a unit ray <= |∇²w| <= 1/Rc + (second differences of the
        # control heights) / spacing²; twice that for margin, halved for the rule.
        second = max(
            float(np.max(np.abs(np.diff(control, 2, axis=0)))),
            float(np.max(np.abs(np.diff(control, 2, axis=1)))),
        )
        bound = 1.0 / geometry.curvature_radius_m + 2.0 * second / geometry.knot_spacing_m**2
        self.half_curvature = float(bound)

    def wall_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """w(x, y) (metres) at world positions x, y (same shape)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        flat = [
            surface_value(self.bumps, 1.0 / self.geometry.knot_spacing_m, float(a), float(b))[0]
            for a, b in zip(x.ravel(), y.ravel(), strict=True)
        ]
        bumps = np.array(flat).reshape(x.shape)
        return bumps - (x * x + y * y) / (2.0 * self.geometry.curvature_radius_m)

    def trace_geometry(
        self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance (H, W) metres, camera-frame normal (H, W, 3), texture uv (H, W, 2)."""
        height, width = mask.shape
        distance = np.empty((height, width))
        normal = np.empty((height, width, 3))
        uv = np.empty((height, width, 2))
        run_in_bands(
            abdomen_trace,
            height,
            np.ascontiguousarray(pose[:3, 3], dtype=np.float64),
            np.ascontiguousarray(pose[:3, :3], dtype=np.float64),
            rays,
            mask,
            0.5 / self.geometry.curvature_radius_m,
            self.bumps,
            1.0 / self.geometry.knot_spacing_m,
            self.half_curvature,
            distance,
            normal,
            uv,
        )
        return distance, normal, uv

    def trace(self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray) -> SurfaceHits:
        """First hits of the unit rays (H, W, 3, camera frame) from the camera at pose (4, 4)."""
        distance, normal, uv = self.trace_geometry(pose, rays, mask)
        albedo = self.texture.sample(uv, np.isfinite(distance))
        return SurfaceHits(distance, normal, albedo, self.specular_weight)
