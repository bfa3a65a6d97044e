"""Photometric parameters of the simulated endoscope, with realistic defaults.

The image formation model (linear irradiance E normalised so that E = 1 fills
the sensor's full well; all lengths in metres):

    E(x) = exposure · V(x) · I(ψ) · [ρ · R_ON(n, l, v; σ) + k_s · w · max(n·h, 0)^m] / r²

* a point light at ``light_offset_m`` from the optical centre, pointing
  along the optical axis, with angular spot profile I(ψ) = cos^p ψ
  (ψ: angle off the light's axis) — the light-guide fibres of an endoscope;
* 1/r² fall-off with the light-to-surface distance r;
* Oren–Nayar diffuse reflectance R_ON (:func:`endo_sfs.reflectance.oren_nayar_radiance`,
  roughness σ; σ = 0 is Lambertian) times the albedo ρ;
* a Blinn–Phong specular lobe (strength k_s, shininess m, half vector h,
  material gloss w) that easily exceeds full scale: wet mucosa's highlights
  saturate;
* lens vignetting V(θ) = cos^q θ (θ: the pixel ray's angle off the axis);
* exposure = full_scale_distance²: a white Lambertian surface facing the
  light on the axis at ``full_scale_distance_m`` reaches full scale.

The sensor then adds shot noise (Poisson, as Gaussian with variance equal to
the electron count) and read noise in electrons, clips at the full well,
applies the camera response and quantises to 8 or 12 bits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from endo_io.camera import CameraModel
from endo_sim.errors import SimulationParameterError
from endo_sim.response import CameraResponse


@dataclass(frozen=True)
class Photometry:
    """Every photometric parameter of the simulator (see the module docstring).

    roughness: Oren–Nayar σ in radians (0.3: soft, velvety mucosa).
    full_scale_distance_m: the exposure, as the distance at which a white
        Lambertian surface facing the light on the axis reaches full scale
        (0.03 m: tissue of albedo 0.4 sits at mid-range at 3–5 cm, as an
        endoscope's auto-exposure would keep it).
    light_offset_m: light position in the optical frame (0: at the optical
        centre, the co-located case photometric methods assume).
    spot_exponent: p of the spot profile cos^p ψ (1: light guides spread to
        about the lens's field of view).
    vignetting_exponent: q of cos^q θ (2: a wide-angle endoscope lens loses
        roughly half its light at 45°).
    response: the camera response curve.
    noise: add shot and read noise.
    full_well_electrons: electrons at full scale (6000: a 1.4 µm pixel of a
        chip-on-tip sensor).
    read_noise_electrons: read noise, electrons RMS (3 e⁻: a modern CMOS).
    bit_depth: 8 (mono8/rgb8) or 12 (mono16 holding 0..4095).
    specular_strength: k_s of the Blinn–Phong lobe (2.0: a mirror-like
        highlight on wet mucosa saturates at any working distance).
    specular_shininess: m of the lobe (120: highlights a few degrees wide).
    """

    roughness: float = 0.3
    full_scale_distance_m: float = 0.03
    light_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spot_exponent: float = 1.0
    vignetting_exponent: float = 2.0
    response: CameraResponse = field(default_factory=CameraResponse.gamma)
    noise: bool = True
    full_well_electrons: float = 6000.0
    read_noise_electrons: float = 3.0
    bit_depth: int = 8
    specular_strength: float = 2.0
    specular_shininess: float = 120.0

    def __post_init__(self) -> None:
        checks = [
            (0.0 <= self.roughness <= 1.5, "roughness must be in [0, 1.5] rad"),
            (
                0.001 <= self.full_scale_distance_m <= 1.0,
                "full_scale_distance_m must be in [1 mm, 1 m]",
            ),
            (len(self.light_offset_m) == 3, "light_offset_m must have 3 components"),
            (0.0 <= self.spot_exponent <= 50.0, "spot_exponent must be in [0, 50]"),
            (0.0 <= self.vignetting_exponent <= 8.0, "vignetting_exponent must be in [0, 8]"),
            (self.full_well_electrons >= 100.0, "full_well_electrons must be >= 100"),
            (self.read_noise_electrons >= 0.0, "read_noise_electrons must be >= 0"),
            (self.bit_depth in (8, 12), "bit_depth must be 8 or 12"),
            (self.specular_strength >= 0.0, "specular_strength must be >= 0"),
            (1.0 <= self.specular_shininess <= 10000.0, "specular_shininess must be in [1, 1e4]"),
        ]
        for ok, message in checks:
            if not ok:
                raise SimulationParameterError(message)
        offset = tuple(float(c) for c in self.light_offset_m)
        if max(abs(c) for c in offset) > 0.02:
            raise SimulationParameterError("light offset beyond 20 mm is not an endoscope")
        object.__setattr__(self, "light_offset_m", offset)

    @property
    def exposure(self) -> float:
        """exposure (m²): E = exposure·ρ·L·G with G = R_ON/r² in m⁻²."""
        return self.full_scale_distance_m**2

    @property
    def colocated(self) -> bool:
        """True when the light sits at the optical centre."""
        return not any(self.light_offset_m)

    @property
    def max_code(self) -> int:
        """Largest pixel value: 255 or 4095."""
        return (1 << self.bit_depth) - 1

    def light_map(self, camera: CameraModel) -> np.ndarray:
        """L(x) = I(ψ)·V(θ) per pixel, (H, W) float64, ≤ 1 and 1 on the optical axis.

        ψ is taken as the pixel ray's angle θ (exact for the light at the
        optical centre, where E = exposure·L·ρ·R_ON/r² holds exactly). 0 where
        the camera model has no ray.
        """
        rays = camera.unit_rays()
        cos_theta = np.nan_to_num(rays[..., 2], nan=0.0)
        cos_theta = np.clip(cos_theta, 0.0, 1.0)
        return cos_theta ** (self.spot_exponent + self.vignetting_exponent)

    def vignetting(self, camera: CameraModel) -> np.ndarray:
        """V(θ) alone, (H, W) float64 (for a light off the optical centre)."""
        cos_theta = np.clip(np.nan_to_num(camera.unit_rays()[..., 2], nan=0.0), 0.0, 1.0)
        return cos_theta**self.vignetting_exponent
