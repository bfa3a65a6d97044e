"""Ground-truth scenes for testing and benchmarking shape from shading.

Each scene renders the linear irradiance image the SFS models assume and
returns the exact depth, computed analytically (or, for the bumpy surface, to
round-off by ray geometry), independently of the solvers' own formulas:

* near-light scenes: a point light at the optical centre, I = R(cos θ)/r²
  with R from :mod:`endo_sfs.reflectance` and θ between the surface normal
  and the ray, for every pixel ray of a :class:`~endo_io.camera.CameraModel`;
* orthographic scenes: a height field z(x, y) over normalised image
  coordinates with the light along the view direction, I = R(1/√(1+|∇z|²)).

Distances are in the scene's own unit; with albedo × light = 1 the near-light
solution reproduces them exactly (no scale ambiguity).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from endo_io.camera import CameraModel
from endo_sfs.reflectance import colocated_radiance


@dataclass(frozen=True)
class Rendering:
    """A rendered frame.

    irradiance (H, W) float64 (NaN where the ray misses), depth (H, W)
    float64 along the optical axis (NaN where it misses).
    """

    irradiance: np.ndarray
    depth: np.ndarray


# ---------------------------------------------------------------- near-light


@dataclass(frozen=True)
class Sphere:
    """Outside of a sphere: centre (3,) and radius, in scene units."""

    centre: tuple[float, float, float]
    radius: float

    def hit(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance r (...) and unit normal (..., 3) facing the camera; NaN on a miss."""
        c = np.asarray(self.centre, dtype=np.float64)
        b = rays @ c
        disc = b * b - (c @ c - self.radius**2)
        with np.errstate(invalid="ignore"):
            r = np.where(disc >= 0.0, b - np.sqrt(disc), np.nan)
        r = np.where(r > 0.0, r, np.nan)
        normals = (r[..., None] * rays - c) / self.radius
        return r, normals


@dataclass(frozen=True)
class Plane:
    """A plane through ``point`` with unit ``normal`` (any orientation)."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]

    def hit(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance r (...) and unit normal (..., 3) facing the camera; NaN on a miss."""
        n = np.asarray(self.normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        p = np.asarray(self.point, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (p @ n) / (rays @ n)
        r = np.where(r > 0.0, r, np.nan)
        facing = np.where((rays @ n)[..., None] < 0.0, n, -n)
        return r, facing


@dataclass(frozen=True)
class TubeInterior:
    """The inside wall of an infinite cylinder seen from a camera inside it."""

    point: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float

    def hit(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance r (...) and unit normal (..., 3) facing the camera; NaN on a miss."""
        a = np.asarray(self.axis, dtype=np.float64)
        a = a / np.linalg.norm(a)
        p = np.asarray(self.point, dtype=np.float64)
        # Components perpendicular to the axis of the ray and of the camera
        # centre (the origin) relative to the axis point.
        d_perp = rays - (rays @ a)[..., None] * a
        o_perp = -p - (-p @ a) * a
        qa = np.sum(d_perp * d_perp, axis=-1)
        qb = 2.0 * (d_perp @ o_perp)
        qc = o_perp @ o_perp - self.radius**2
        with np.errstate(invalid="ignore", divide="ignore"):
            r = (-qb + np.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)
        r = np.where(r > 0.0, r, np.nan)
        wall = r[..., None] * rays - p
        radial = wall - (wall @ a)[..., None] * a
        normals = -radial / self.radius
        return r, normals


@dataclass(frozen=True)
class BumpyRadialSurface:
    """A base surface whose distance along each ray is modulated by bumps.

    r(ω) = r_base(ω)·(1 + Σ_k a_k·exp(−|s − s_k|²/(2 w_k²))), with s the
    stereographic coordinates of the ray ω: a smooth tissue-like surface
    with pits, mounds and saddles. Normals come from central differences of
    the exact point map S(s) = r·ω (step 1e-6, error ~1e-10).
    """

    base: Sphere | Plane | TubeInterior
    centres: tuple[tuple[float, float], ...]
    amplitudes: tuple[float, ...]
    widths: tuple[float, ...]
    step: float = field(default=1e-6)

    def _distance(self, s: np.ndarray) -> np.ndarray:
        rays = _stereographic_rays(s)
        r, _ = self.base.hit(rays)
        modulation = np.ones(s.shape[:-1])
        for centre, amplitude, width in zip(
            self.centres, self.amplitudes, self.widths, strict=True
        ):
            d2 = np.sum((s - np.asarray(centre)) ** 2, axis=-1)
            modulation += amplitude * np.exp(-0.5 * d2 / width**2)
        return r * modulation

    def _point(self, s: np.ndarray) -> np.ndarray:
        return self._distance(s)[..., None] * _stereographic_rays(s)

    def hit(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance r (...) and unit normal (..., 3) facing the camera; NaN on a miss."""
        s = rays[..., :2] / (1.0 + rays[..., 2])[..., None]
        h = self.step
        ex = np.array([h, 0.0])
        ey = np.array([0.0, h])
        tangent_x = self._point(s + ex) - self._point(s - ex)
        tangent_y = self._point(s + ey) - self._point(s - ey)
        normals = np.cross(tangent_x, tangent_y)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        normals = np.where(np.sum(normals * rays, axis=-1, keepdims=True) > 0, -normals, normals)
        return self._distance(s), normals


def _stereographic_rays(s: np.ndarray) -> np.ndarray:
    s2 = np.sum(s * s, axis=-1)
    return np.stack([2.0 * s[..., 0], 2.0 * s[..., 1], 1.0 - s2], axis=-1) / (1.0 + s2)[..., None]


def render_near_light(
    camera: CameraModel,
    surface: Sphere | Plane | TubeInterior | BumpyRadialSurface,
    roughness: float = 0.0,
    specular: float = 0.0,
    shininess: float = 60.0,
) -> Rendering:
    """Render I = R(cos θ)/r² with the light at the optical centre.

    R is Oren–Nayar (:func:`endo_sfs.reflectance.colocated_radiance`, albedo
    1) plus an optional white specular lobe k·cos^m θ (``specular`` k,
    ``shininess`` m), the highlights of wet tissue, which the SFS models do
    not contain (see :mod:`endo_sfs.highlights`).
    Returns a :class:`Rendering` of the camera's size; pixels whose ray
    misses the surface or sees it from behind are NaN in both images.
    """
    rays = np.asarray(camera.unit_rays(), dtype=np.float64)
    r, normals = surface.hit(rays)
    cos_theta = -np.sum(normals * rays, axis=-1)
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(r) & (cos_theta > 0.0)
        radiance = colocated_radiance(cos_theta, roughness)
        if specular > 0.0:
            radiance = radiance + specular * np.clip(cos_theta, 0.0, 1.0) ** shininess
        irradiance = np.where(seen, radiance / (r * r), np.nan)
    depth = np.where(seen, r * rays[..., 2], np.nan)
    return Rendering(irradiance=irradiance, depth=depth)


# ---------------------------------------------------------------- orthographic


def posed_tube_sequence(
    camera: CameraModel,
    frames: int,
    roughness: float = 0.3,
    *,
    turn_deg: float = 1.0,
    approach: float = 0.05,
    advance: float = 0.03,
) -> list[tuple[Rendering, np.ndarray]]:
    """A camera moving inside a world-fixed tube (axis z, radius 1), with its poses.

    The camera starts 0.6 off the axis looking 63° off it; per frame it
    advances ``advance`` along the axis, moves ``approach`` towards the wall
    and turns ``turn_deg`` (along the axis alone the view would not change).
    Returns (rendering, (4, 4) T_world_camera in the rendering's unit) per
    frame.
    """
    from endo_io.pose import rigid_transform

    out = []
    for k in range(frames):
        beta = 1.1 + np.radians(turn_deg) * k
        pose = rigid_transform((-beta, 0.0, 0.0), (0.0, 0.6 - approach * k, advance * k))
        rotation, centre = pose[:3, :3], pose[:3, 3]
        tube = TubeInterior(tuple(rotation.T @ -centre), tuple(rotation.T[:, 2]), 1.0)
        out.append((render_near_light(camera, tube, roughness), pose))
    return out


def normalised_coordinates(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) normalised image coordinates (H, W) of an undistorted camera's pixels."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    return (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy


def render_orthographic(
    height: np.ndarray, gradient_x: np.ndarray, gradient_y: np.ndarray, roughness: float = 0.0
) -> Rendering:
    """Render the seed paper's orthographic image of a height field.

    height, gradient_x, gradient_y: (H, W) depth z (NaN where undefined) and
    its exact partial derivatives in normalised coordinates.
    Returns I = A·c + B·(1 − c²), c = 1/√(1 + |∇z|²), and depth = height.
    """
    cos_theta = 1.0 / np.sqrt(1.0 + gradient_x**2 + gradient_y**2)
    irradiance = np.where(np.isfinite(height), colocated_radiance(cos_theta, roughness), np.nan)
    return Rendering(irradiance=irradiance, depth=np.asarray(height, dtype=np.float64))


def quantise_8bit(
    irradiance: np.ndarray, rng: np.random.Generator, noise_dn: float = 1.0, peak: float = 0.95
) -> np.ndarray:
    """An 8-bit camera's view of ``irradiance``, back in irradiance units.

    The image is exposed so that its maximum lands at ``peak`` of full scale,
    Gaussian read noise of ``noise_dn`` grey levels is added, the result is
    rounded to 0…255 and divided by the exposure again (what a calibrated
    pipeline hands to SFS). NaN stays NaN. Returns (H, W) float64.
    """
    exposure = peak / np.nanmax(irradiance)
    levels = irradiance * exposure * 255.0 + rng.normal(0.0, noise_dn, irradiance.shape)
    quantised = np.clip(np.round(levels), 0.0, 255.0) / 255.0
    return np.where(np.isfinite(irradiance), quantised / exposure, np.nan)


# ---------------------------------------------------------------- standard scenes

#: Names of the standard scenes used by the tests, the benchmark and docs/sfs.md.
SCENE_NAMES: tuple[str, ...] = ("sphere", "tilted_plane", "tube", "bumpy")


def scene_camera(size: int, fov_deg: float = 70.0, distortion: float = 0.0) -> CameraModel:
    """A square camera of ``size`` pixels and horizontal field of view ``fov_deg``.

    The principal point is off the pixel grid on purpose (no symmetry helps
    the solver); ``distortion`` is the plumb_bob k1 coefficient.
    """
    focal = (size / 2.0) / np.tan(np.radians(fov_deg / 2.0))
    centre = (size - 1) / 2.0
    return CameraModel.pinhole(
        size, size, focal, focal, centre + 0.17 * size / 256, centre - 0.23 * size / 256,
        D=np.array([distortion, 0.0, 0.0, 0.0, 0.0]), distortion_model="plumb_bob",
    )


def near_light_surface(name: str) -> Sphere | Plane | TubeInterior | BumpyRadialSurface:
    """One of :data:`SCENE_NAMES` for the near-light model (scene units ≈ cm).

    Each has its nearest point in a 70° view, so the whole view is the
    domain of dependence of its singular points (see :mod:`endo_sfs.near_light`).
    """
    if name == "sphere":
        return Sphere((0.1, -0.05, 3.0), 1.2)
    if name == "tilted_plane":
        return Plane((0.0, 0.0, 2.0), (np.sin(0.35), 0.1, -np.cos(0.35)))
    if name == "tube":
        # Camera 0.6 off the axis of a radius-1 tube, looking 63° off the axis
        # towards the near wall.
        return TubeInterior((0.0, -0.6, 0.0), (0.0, -np.sin(1.1), np.cos(1.1)), 1.0)
    if name == "bumpy":
        return BumpyRadialSurface(
            Sphere((0.05, 0.03, 4.0), 2.5),
            centres=((0.1, 0.05), (-0.12, 0.08), (0.02, -0.15), (-0.05, -0.02)),
            amplitudes=(0.04, -0.03, 0.03, 0.02),
            widths=(0.06, 0.05, 0.07, 0.04),
        )
    raise ValueError(f"unknown scene {name!r}; expected one of {SCENE_NAMES}")


@dataclass(frozen=True)
class OrthographicScene:
    """An orthographic height field and the sources the Eikonal needs.

    height, gradient_x, gradient_y: (H, W) float64 (NaN outside the surface).
    boundary_depth: (H, W) true depth on the region's border (NaN elsewhere)
    for scenes without a singular point, else None. concave: the singular
    points are depth maxima.
    """

    height: np.ndarray
    gradient_x: np.ndarray
    gradient_y: np.ndarray
    boundary_depth: np.ndarray | None
    concave: bool


def orthographic_scene(name: str, camera: CameraModel) -> OrthographicScene:
    """One of :data:`SCENE_NAMES` as a height field over ``camera``'s pixels.

    Depth is 1 at the singular points. sphere: a dome; tilted_plane: a plane
    (no singular point: border data); tube: a trough, the inside of a tube
    (concave, singular line); bumpy: a dome with mounds and dimples gentler
    than its own slope (so the apex stays the only depth extremum).
    """
    x, y = normalised_coordinates(camera)
    inside_view = x * x + y * y < 0.6**2
    if name in ("sphere", "bumpy"):
        radius, cx, cy = 0.5, 0.03, -0.02
        dx, dy = x - cx, y - cy
        p2 = dx * dx + dy * dy
        inside = (p2 < (0.85 * radius) ** 2) & inside_view
        root = np.sqrt(np.maximum(radius * radius - p2, 1e-12))
        height, gx, gy = 1.0 + radius - root, dx / root, dy / root
        if name == "bumpy":
            for bx, by, amplitude, width in (
                (0.25, 0.08, 0.02, 0.045),
                (-0.2, 0.2, -0.015, 0.04),
                (0.02, -0.3, 0.02, 0.05),
                (-0.28, -0.12, 0.012, 0.04),
            ):
                bump = amplitude * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * width**2))
                height = height + bump
                gx = gx - bump * (x - bx) / width**2
                gy = gy - bump * (y - by) / width**2
        return OrthographicScene(np.where(inside, height, np.nan), gx, gy, None, False)
    if name == "tilted_plane":
        a, b = 0.35, -0.2
        height = np.where(inside_view, 1.0 + a * x + b * y, np.nan)
        inner = np.zeros_like(inside_view)
        inner[1:-1, 1:-1] = (
            inside_view[1:-1, 1:-1] & inside_view[:-2, 1:-1] & inside_view[2:, 1:-1]
            & inside_view[1:-1, :-2] & inside_view[1:-1, 2:]
        )
        border = inside_view & ~inner
        return OrthographicScene(
            height, np.full_like(x, a), np.full_like(x, b), np.where(border, height, np.nan), False
        )
    if name == "tube":
        radius, angle = 0.6, 0.3
        u = x * np.cos(angle) + y * np.sin(angle) - 0.05
        inside = (np.abs(u) < 0.8 * radius) & inside_view
        root = np.sqrt(np.maximum(radius * radius - u * u, 1e-12))
        slope = -u / root
        return OrthographicScene(
            np.where(inside, 1.0 - radius + root, np.nan),
            slope * np.cos(angle), slope * np.sin(angle), None, True,
        )
    raise ValueError(f"unknown scene {name!r}; expected one of {SCENE_NAMES}")
