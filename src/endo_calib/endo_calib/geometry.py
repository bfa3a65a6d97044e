"""The geometry term G(x) of a flat gray card at a known pose.

With the light at the optical centre (an endoscope's light guides sit beside
the lens, millimetres from it), a card point seen along the unit ray ``u`` of
pixel ``x`` lies at ``p = t·u``; the light reaches it from direction ``-u``
over distance ``r = t``. For a Lambertian card the irradiance that reaches the
pixel is proportional to

    G(x) = cos θ / r²,   cos θ = n_c · u,  r = d / (n_c · u),

with ``n_c`` the card's unit normal turned away from the camera and ``d`` the
distance of the card plane from the optical centre. A fronto-parallel card at
distance ``d`` gives ``G = u_z³ / d²``.

The card is taken as Lambertian, as a photographic gray card is made to be; a
rough (Oren–Nayar) surface would reflect ``A·cos θ + B·sin² θ`` instead, and
its calibration would put that angular error into the light map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from endo_calib.errors import CalibrationError

if TYPE_CHECKING:
    from endo_io.camera import CameraModel


class CardPoseError(CalibrationError, ValueError):
    """A card pose is not a plane in front of the camera."""


@dataclass(frozen=True)
class CardPose:
    """Pose and surface of a flat gray card in the camera's optical frame.

    normal:
        Unit normal of the card surface (any length; normalised here) in the
        REP 103 optical frame, pointing back towards the camera: a
        fronto-parallel card has ``(0, 0, -1)``.
    distance_m:
        Distance of the card plane from the optical centre in metres (> 0).
    """

    normal: tuple[float, float, float] = (0.0, 0.0, -1.0)
    distance_m: float = 0.05

    def unit_normal(self) -> NDArray[np.float64]:
        """The card normal as a unit (3,) float64 vector, checked to face the camera."""
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        length = float(np.linalg.norm(n))
        if not np.isfinite(length) or length == 0.0:
            raise CardPoseError(f"card normal {self.normal!r} is not a direction")
        n = n / length
        if n[2] >= 0.0:
            raise CardPoseError(
                f"card normal {self.normal!r} faces away from the camera (needs z < 0)"
            )
        if not (np.isfinite(self.distance_m) and self.distance_m > 0.0):
            raise CardPoseError(f"card distance must be > 0 m, got {self.distance_m!r}")
        return n


def geometry_term_from_rays(rays: NDArray[np.floating], pose: CardPose) -> NDArray[np.float64]:
    """Geometry term of a flat card for given viewing rays.

    rays: (..., 3) unit rays in the optical frame (x right, y down, z forward).
    pose: the card's pose.
    Returns (...) float64 in 1/m²: cos θ/r², 0 where a ray misses the card
    (parallel to it or hitting it from behind).
    """
    n = pose.unit_normal()
    u = np.asarray(rays, dtype=np.float64)
    cos_theta = -(u @ n)  # angle between the ray and the normal turned towards the camera
    hits = cos_theta > 1e-9
    safe = np.where(hits, cos_theta, 1.0)
    range_m = pose.distance_m / safe
    return np.where(hits, safe / (range_m * range_m), 0.0)


def geometry_term(camera: CameraModel, pose: CardPose | None = None) -> NDArray[np.float64]:
    """Geometry term G(x) = cos θ / r² of a card for every pixel of ``camera``.

    camera: an ``endo_io.camera.CameraModel`` (its ``unit_rays()`` undo distortion).
    pose: the card's pose; fronto-parallel at 5 cm by default (the distance of a
    fronto-parallel card only scales G, which the calibration absorbs).
    Returns (H, W) float64 in 1/m².
    """
    return geometry_term_from_rays(camera.unit_rays(), pose or CardPose())
