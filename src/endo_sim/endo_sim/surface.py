"""What a scene returns per ray: distance, normal, albedo; and the scene interface.

Every scene (colon, abdomen, gray card, checkerboard) answers one question
for the renderer: for each unit ray of the camera at a pose, where does it
first meet the surface, which way does the surface face, and how much light
does it reflect there. The renderer never looks at a scene's geometry
otherwise, which is what lets one renderer serve every scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numba as nb
import numpy as np


@dataclass(frozen=True, eq=False)
class SurfaceHits:
    """First hits of a camera's rays.

    distance: (H, W) float64 metres along each unit ray; NaN where the pixel
        is outside the field of view or the ray hits nothing.
    normal: (H, W, 3) float64 unit surface normal in the camera (optical)
        frame, oriented towards the camera (n·ray < 0); 0 where no hit.
    albedo: (H, W, C) float64 diffuse reflectance in [0, 1], C = 1 or 3;
        0 where no hit.
    specular_weight: the material's gloss, multiplying the photometry's
        specular strength (0: matte).
    """

    distance: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    specular_weight: float


@nb.njit(cache=True, nogil=True, inline="always")
def no_hit(distance: np.ndarray, normal: np.ndarray, uv: np.ndarray, i: int, j: int) -> None:
    """Mark pixel (i, j) of a ray caster's outputs as "no hit": NaN distance, zeros."""
    distance[i, j] = math.nan
    normal[i, j, 0] = 0.0
    normal[i, j, 1] = 0.0
    normal[i, j, 2] = 0.0
    uv[i, j, 0] = 0.0
    uv[i, j, 1] = 0.0


class Scene(Protocol):
    """Anything the renderer can draw."""

    @property
    def name(self) -> str:
        """Short name of the scene (``colon``, ``graycard``, ...)."""
        ...

    def trace(self, pose: np.ndarray, rays: np.ndarray, mask: np.ndarray) -> SurfaceHits:
        """First hits of ``rays``.

        pose: (4, 4) float64 T_world_camera (metres); rays: (H, W, 3) float64
        unit rays in the camera frame; mask: (H, W) bool pixels to trace.
        """
        ...
