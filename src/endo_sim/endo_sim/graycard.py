"""Gray-card frames: uniform cards of known reflectance at a known pose.

Photometric calibration (camera response, light map) images uniform matte
cards of known reflectance, each filling the view at the same pose: the
pixel values then differ only through ρ, so g(v) ∝ ρ·L(x)·G(x) separates the
response g from the spatial light map L and the geometry G = R_ON/r². The
cards are rendered by the general renderer as a :class:`~endo_sim.planar.PlaneScene`.
"""

from __future__ import annotations

import numpy as np

from endo_io.camera import CameraModel
from endo_sim.errors import SimulationParameterError
from endo_sim.photometry import Photometry
from endo_sim.planar import PlaneScene
from endo_sim.render import Renderer

#: The seven card reflectances (20 % to 80 %), as a calibration set offers them.
GRAY_LEVELS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
#: Default card distance from the optical centre along the axis (metres): with
#: the default exposure (white reaches full scale at 3 cm) the brightest card
#: (0.8) reaches 0.8·(0.03/0.0265)² = 1.025 of full scale at the centre, i.e.
#: it just saturates there, as the calibration protocol asks (docs/calibration.md).
DEFAULT_CARD_DISTANCE_M = 0.0265


def gray_card_scene(
    reflectance: float,
    distance_m: float,
    normal: tuple[float, float, float] | np.ndarray = (0.0, 0.0, -1.0),
    channels: int = 1,
) -> PlaneScene:
    """A card through (0, 0, distance_m) with ``normal``, both in the camera frame.

    With the camera at the world origin (identity pose), camera frame = world.
    reflectance in [0, 1]; channels 1 or 3 (a neutral card: equal in all).
    """
    if not 0.0 <= reflectance <= 1.0:
        raise SimulationParameterError(f"card reflectance must be in [0, 1], got {reflectance}")
    if not distance_m > 0.0:
        raise SimulationParameterError(f"card distance must be positive, got {distance_m}")
    if channels not in (1, 3):
        raise SimulationParameterError(f"channels must be 1 or 3, got {channels}")
    return PlaneScene(
        point_world=np.array([0.0, 0.0, float(distance_m)]),
        normal_world=np.asarray(normal, dtype=np.float64),
        albedo=np.full(channels, float(reflectance)),
        name="graycard",
    )


def render_gray_card(
    camera: CameraModel,
    photometry: Photometry,
    reflectance: float,
    distance_m: float,
    normal: tuple[float, float, float] | np.ndarray = (0.0, 0.0, -1.0),
    rng: np.random.Generator | None = None,
    channels: int = 1,
    fov_radius_px: float | None = None,
) -> np.ndarray:
    """Raw frame of a gray card: (H, W) (channels 1) or (H, W, 3), uint8 or uint16.

    12-bit output holds 0..4095 in uint16 (mono16). Noise as configured in
    ``photometry`` (then ``rng`` is required). fov_radius_px: circular field
    of view (None: whole image).
    """
    renderer = Renderer(camera, photometry, fov_radius_px)
    scene = gray_card_scene(reflectance, distance_m, normal, channels)
    return renderer.render(scene, np.eye(4), rng).image


def gray_card_irradiance(
    camera: CameraModel,
    photometry: Photometry,
    reflectance: float,
    distance_m: float,
    normal: tuple[float, float, float] | np.ndarray = (0.0, 0.0, -1.0),
    rng: np.random.Generator | None = None,
    channels: int = 1,
    fov_radius_px: float | None = None,
) -> np.ndarray:
    """Noise-free linear irradiance E = ρ·L·G·exposure of the card, before the response.

    (H, W) float64 (channels 1) or (H, W, 3); 0 outside the field of view.
    ``rng`` is accepted for symmetry with :func:`render_gray_card` and unused.
    """
    del rng
    renderer = Renderer(camera, photometry, fov_radius_px)
    scene = gray_card_scene(reflectance, distance_m, normal, channels)
    irradiance = renderer.irradiance(scene.trace(np.eye(4), renderer.rays, renderer.mask))
    return irradiance[..., 0] if channels == 1 else irradiance
