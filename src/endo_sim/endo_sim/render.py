"""The one renderer: scene + pose + photometry + camera -> raw image, depth, irradiance.

Every image the simulator produces (colon, abdomen, gray card, checkerboard,
offline bags and the live stand-in driver) comes from :meth:`Renderer.render`:

1. the scene ray casts the camera's unit-ray table (:meth:`CameraModel.unit_rays`,
   so lens distortion is rendered exactly as the camera model describes it)
   inside the circular field-of-view mask;
2. :class:`~endo_sim.photometry.Photometry` turns distance, normal and albedo
   into linear irradiance (see its module docstring for the formula);
3. the sensor adds shot and read noise, clips at the full well, applies the
   camera response and quantises.

Outside the field of view the image is 0 and depth is NaN (REP 118).

Speed: the ray table, mask, light map, Oren–Nayar table and quantisation
thresholds are computed once per renderer. For the light at the optical
centre (the default) shading is one fused numba kernel reading an Oren–Nayar
table tabulated from :func:`endo_sfs.reflectance.oren_nayar_radiance` at
co-located geometry (where it is A·c + B·(1 − c²), a quadratic in c = cos θ, so
linear interpolation over 4097 entries is exact to 4e-9); with an offset light
:func:`~endo_sfs.reflectance.oren_nayar_radiance` is called per pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.special import ndtri

from endo_io.camera import CameraModel
from endo_sfs.reflectance import oren_nayar_radiance
from endo_sim.bands import run_in_bands
from endo_sim.errors import SimulationParameterError
from endo_sim.photometry import Photometry
from endo_sim.surface import Scene, SurfaceHits

#: Entries of the co-located Oren–Nayar table over cos θ ∈ [0, 1].
REFLECTANCE_TABLE_SIZE = 4097


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One rendered frame.

    image: (H, W) (mono) or (H, W, 3) (rgb) uint8 for 8 bits, uint16 holding
        0..4095 for 12 bits; 0 outside the field of view.
    depth: (H, W) float32 metres along the optical axis (z), NaN outside the
        field of view or where no surface was hit (REP 118).
    irradiance: (H, W, C) float64 noise-free linear irradiance before the
        sensor clips (1 = full well); 0 where no hit.
    encoding: the sensor_msgs/Image encoding of ``image``.
    """

    image: np.ndarray
    depth: np.ndarray
    irradiance: np.ndarray
    encoding: str


@nb.njit(cache=True, nogil=True)
def _shade_colocated(
    distance: np.ndarray,
    normal: np.ndarray,
    rays: np.ndarray,
    albedo: np.ndarray,
    light_map: np.ndarray,
    table: np.ndarray,
    specular: float,
    shininess: float,
    exposure: float,
    out: np.ndarray,
    row_start: int,
    row_stop: int,
) -> None:
    """E = exposure·L·(ρ·R_ON(c) + specular·c^m)/t² with c = −n·ray, into out (H, W, C).

    c^m is skipped where it is below e^-36 (1e-16), i.e. for c < e^(-36/m):
    the lobe is then zero to double precision and the power is the costliest
    operation of the kernel.
    """
    lobe_floor = math.exp(-36.0 / shininess)
    last = table.shape[0] - 1
    for i in range(row_start, row_stop):
        for j in range(distance.shape[1]):
            t = distance[i, j]
            if t != t:
                for c in range(out.shape[2]):
                    out[i, j, c] = 0.0
                continue
            cos = -(
                normal[i, j, 0] * rays[i, j, 0]
                + normal[i, j, 1] * rays[i, j, 1]
                + normal[i, j, 2] * rays[i, j, 2]
            )
            cos = min(max(cos, 0.0), 1.0)
            x = cos * last
            k = min(int(x), last - 1)
            f = x - k
            diffuse = table[k] * (1.0 - f) + table[k + 1] * f
            gloss = specular * cos**shininess if specular > 0.0 and cos > lobe_floor else 0.0
            scale = exposure * light_map[i, j] / (t * t)
            for c in range(out.shape[2]):
                out[i, j, c] = scale * (albedo[i, j, c] * diffuse + gloss)


#: Bins of the inverse normal CDF used by the noise generator.
_NORMAL_TABLE_BITS = 12
#: Bins of the coarse irradiance -> code table (the exact code is then found
#: by comparing with the thresholds next to the table's guess).
_CODE_TABLE_SIZE = 1 << 16


def _normal_table() -> np.ndarray:
    """Inverse standard normal CDF at the edges of 2^12 equal-probability bins.

    The end points (probability 0 and 1) are clamped to the half-bin
    quantiles, so draws are limited to ±3.7σ, irrelevant for sensor noise.
    """
    n = 1 << _NORMAL_TABLE_BITS
    p = np.arange(n + 1, dtype=np.float64) / n
    p[0] = 0.5 / n
    p[-1] = 1.0 - 0.5 / n
    return ndtri(p)


@nb.njit(cache=True, nogil=True)
def _mix64(x: np.uint64) -> np.uint64:
    """SplitMix64 finaliser: a bijective 64-bit hash with full avalanche."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@nb.njit(cache=True, nogil=True)
def _standard_normal(key: np.uint64, index: int, table: np.ndarray) -> float:
    """A standard normal draw for counter ``index`` of stream ``key``.

    Counter-based (hash of key and index), so the draws do not depend on
    which thread computes which pixel: frames are bit-identical for any
    thread count. Inverse-CDF sampling, linear inside 4096 bins.
    """
    bits = _mix64(key + np.uint64(index) * np.uint64(0x9E3779B97F4A7C15))
    k = np.int64(bits >> np.uint64(64 - _NORMAL_TABLE_BITS))
    frac = np.float64((bits >> np.uint64(11)) & np.uint64((1 << 40) - 1)) * (1.0 / (1 << 40))
    return table[k] + (table[k + 1] - table[k]) * frac


@nb.njit(cache=True, nogil=True)
def _expose(
    irradiance: np.ndarray,
    valid: np.ndarray,
    noise_key: np.uint64,
    noisy: bool,
    normal_table: np.ndarray,
    full_well: float,
    read_noise: float,
    thresholds: np.ndarray,
    code_table: np.ndarray,
    out: np.ndarray,
    row_start: int,
    row_stop: int,
) -> None:
    """Sensor: noise, full-well clip, response, quantisation, into out (H, W, C).

    irradiance (H, W, C) linear; valid (H, W) pixels in the field of view.
    Shot noise (variance = electrons) and read noise are one Gaussian of
    variance electrons + read², drawn from the counter-based stream
    ``noise_key`` when ``noisy``. thresholds: (2^bits − 1,) ascending
    irradiances where the code steps up; code_table: code at each of its bins'
    lower edge, refined exactly against ``thresholds``.
    """
    n_thr = thresholds.shape[0]
    bins = code_table.shape[0]
    channels = out.shape[2]
    width = out.shape[1]
    for i in range(row_start, row_stop):
        for j in range(width):
            if not valid[i, j]:
                for c in range(channels):
                    out[i, j, c] = 0
                continue
            for c in range(channels):
                e = irradiance[i, j, c]
                if noisy:
                    electrons = e * full_well
                    sigma = math.sqrt(min(electrons, full_well) + read_noise * read_noise)
                    draw = _standard_normal(noise_key, (i * width + j) * channels + c, normal_table)
                    e = (electrons + sigma * draw) / full_well
                e = min(max(e, 0.0), 1.0)
                code = code_table[min(int(e * bins), bins - 1)]
                while code < n_thr and thresholds[code] <= e:
                    code += 1
                out[i, j, c] = code


def _code_table(thresholds: np.ndarray) -> np.ndarray:
    """Code (number of thresholds <= E) at E = k / size for each bin k, (size,) int64."""
    edges = np.arange(_CODE_TABLE_SIZE, dtype=np.float64) / _CODE_TABLE_SIZE
    return np.searchsorted(thresholds, edges, side="right").astype(np.int64)


def colocated_reflectance_table(roughness: float, size: int = REFLECTANCE_TABLE_SIZE) -> np.ndarray:
    """Oren–Nayar radiance with light = viewer at cos θ = linspace(0, 1, size), (size,) float64.

    Tabulated from :func:`endo_sfs.reflectance.oren_nayar_radiance` itself.
    """
    c = np.linspace(0.0, 1.0, size)
    s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    direction = np.stack([s, np.zeros_like(c), c], axis=-1)
    return oren_nayar_radiance(np.array([0.0, 0.0, 1.0]), direction, direction, roughness)


class Renderer:
    """Renders scenes through one camera with one set of photometric parameters.

    camera: the camera model (its unit rays define the pixels, distortion
    included). photometry: :class:`Photometry`. fov_radius_px: radius of the
    circular field of view around the principal point in pixels (None: the
    whole image).
    """

    def __init__(
        self, camera: CameraModel, photometry: Photometry, fov_radius_px: float | None = None
    ) -> None:
        self.camera = camera
        self.photometry = photometry
        rays = np.array(camera.unit_rays(), dtype=np.float64, order="C")
        finite = np.all(np.isfinite(rays), axis=-1)
        self.mask = np.ascontiguousarray(camera.fov_mask(fov_radius_px) & finite)
        rays[~finite] = (0.0, 0.0, 1.0)
        #: (H, W, 3) unit rays in the optical frame (finite everywhere).
        self.rays = rays
        #: (H, W) L(x) of the photometric model.
        self.light_map = np.ascontiguousarray(photometry.light_map(camera))
        self._vignetting = photometry.vignetting(camera)
        self._table = colocated_reflectance_table(photometry.roughness)
        self._thresholds = photometry.response.code_thresholds(photometry.bit_depth)
        self._code_table = _code_table(self._thresholds)
        self._normal_table = _normal_table()

    def irradiance(self, hits: SurfaceHits) -> np.ndarray:
        """Noise-free linear irradiance (H, W, C) float64 of the hits (0 where none)."""
        p = self.photometry
        albedo = np.ascontiguousarray(hits.albedo, dtype=np.float64)
        out = np.empty(albedo.shape)  # every element is written below
        specular = p.specular_strength * hits.specular_weight
        if p.colocated:
            run_in_bands(
                _shade_colocated,
                albedo.shape[0],
                np.ascontiguousarray(hits.distance),
                np.ascontiguousarray(hits.normal),
                self.rays,
                albedo,
                self.light_map,
                self._table,
                specular,
                p.specular_shininess,
                p.exposure,
                out,
            )
            return out
        out[:] = 0.0
        hit = np.isfinite(hits.distance)
        rays = self.rays[hit]
        normal = hits.normal[hit]
        light = np.asarray(p.light_offset_m)
        from_light = hits.distance[hit][:, None] * rays - light
        r_light = np.linalg.norm(from_light, axis=-1)
        to_light = -from_light / r_light[:, None]
        to_viewer = -rays
        spot = np.maximum(from_light[:, 2] / r_light, 0.0) ** p.spot_exponent
        diffuse = oren_nayar_radiance(normal, to_light, to_viewer, p.roughness)
        half = to_light + to_viewer
        half /= np.linalg.norm(half, axis=-1, keepdims=True)
        lit = np.sum(normal * to_light, axis=-1) > 0.0
        gloss = np.where(
            lit,
            specular * np.maximum(np.sum(normal * half, axis=-1), 0.0) ** p.specular_shininess,
            0.0,
        )
        scale = p.exposure * self._vignetting[hit] * spot / (r_light * r_light)
        out[hit] = scale[:, None] * (albedo[hit] * diffuse[:, None] + gloss[:, None])
        return out

    def expose(self, irradiance: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """Sensor model: irradiance (H, W, C) -> raw codes (H, W, C) uint8/uint16.

        rng: draws the noise (required when the photometry has noise on).
        """
        p = self.photometry
        if p.noise and rng is None:
            raise SimulationParameterError("noise is on: render() needs a numpy Generator")
        dtype = np.uint8 if p.bit_depth == 8 else np.uint16
        out = np.empty(irradiance.shape, dtype=dtype)
        # One 64-bit key per frame from the generator: the frame's noise is a
        # deterministic function of the generator state.
        key = (
            np.uint64(rng.integers(0, 2**63, dtype=np.int64))
            if p.noise and rng is not None
            else np.uint64(0)
        )
        run_in_bands(
            _expose,
            irradiance.shape[0],
            np.ascontiguousarray(irradiance),
            self.mask,
            key,
            bool(p.noise),
            self._normal_table,
            float(p.full_well_electrons),
            float(p.read_noise_electrons),
            self._thresholds,
            self._code_table,
            out,
        )
        return out

    def encoding(self, channels: int) -> str:
        """sensor_msgs/Image encoding of frames with ``channels`` channels."""
        if channels == 1:
            return "mono8" if self.photometry.bit_depth == 8 else "mono16"
        if self.photometry.bit_depth != 8:
            raise SimulationParameterError("12-bit output is mono16 only; use 8 bits for rgb8")
        return "rgb8"

    def render(
        self, scene: Scene, pose: np.ndarray, rng: np.random.Generator | None = None
    ) -> RenderedFrame:
        """Render ``scene`` from the camera at ``pose`` (4, 4) T_world_camera, metres.

        rng: numpy Generator for the sensor noise (required when noise is on;
        the frame is then a deterministic function of the generator's state).
        """
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise SimulationParameterError("pose must be a finite (4, 4) matrix")
        hits = scene.trace(pose, self.rays, self.mask)
        channels = hits.albedo.shape[-1]
        encoding = self.encoding(channels)
        irradiance = self.irradiance(hits)
        raw = self.expose(irradiance, rng)
        image = raw[..., 0] if channels == 1 else raw
        depth = (hits.distance * self.rays[..., 2]).astype(np.float32)
        return RenderedFrame(image, depth, irradiance, encoding)
