"""Diffuse reflectance models: Lambertian and Oren–Nayar, forward and inverse.

Conventions (shared with ``endo_sim``, which renders with these functions):

* Vectors are unit 3-vectors in any common frame, in the last axis of
  ``(..., 3)`` arrays; they broadcast against each other.
* Radiance is per unit albedo and unit irradiance and omits the ``1/π`` of
  the BRDF: a Lambertian patch facing the light gives exactly 1.
* ``roughness`` σ is the standard deviation of the micro-facet slope angle in
  radians (Oren & Nayar 1994, qualitative model).

With the light at the viewer (an endoscope: light guide beside the lens) the
incidence and viewing angles are equal, θ_i = θ_r = θ, the azimuth difference
is zero, and Oren–Nayar reduces to

    R(c) = A·c + B·(1 − c²),   c = cos θ ∈ [0, 1],

which is equation (1) of the seed paper. :func:`colocated_cosine` inverts it
per pixel. Specular highlights are not part of this model: wet tissue's
lobe is white (it is reflected at the air/mucus interface, not scaled by the
albedo), so it cannot be folded into a reflectance per unit albedo; it is
detected and masked instead (:mod:`endo_sfs.highlights`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Below this squared tangential length an azimuth is undefined; the Oren–Nayar
#: B-term then vanishes anyway because tan β = 0 or sin α·tan β has no azimuth.
_AZIMUTH_EPS = 1e-24


def oren_nayar_coefficients(roughness: float) -> tuple[float, float]:
    """Oren–Nayar coefficients ``(A, B)`` of the qualitative model.

    A = 1 − 0.5·σ²/(σ² + 0.33),  B = 0.45·σ²/(σ² + 0.09), σ in radians (≥ 0).
    σ = 0 gives (1, 0), the Lambertian model.
    """
    sigma = float(roughness)
    if not np.isfinite(sigma) or sigma < 0.0:
        raise ValueError(f"roughness must be a finite angle >= 0 rad, got {roughness!r}")
    s2 = sigma * sigma
    return 1.0 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)


def lambertian_radiance(normals: ArrayLike, to_light: ArrayLike) -> NDArray[np.float64]:
    """Lambertian radiance ``max(n·l, 0)``.

    normals, to_light: (..., 3) unit vectors, broadcastable. Returns (...) float64.
    """
    n = np.asarray(normals, dtype=np.float64)
    light = np.asarray(to_light, dtype=np.float64)
    return np.maximum(np.sum(n * light, axis=-1), 0.0)


def oren_nayar_radiance(
    normals: ArrayLike, to_light: ArrayLike, to_viewer: ArrayLike, roughness: float
) -> NDArray[np.float64]:
    """Oren–Nayar (qualitative model) radiance, without the 1/π factor.

    cos θ_i · (A + B · max(0, cos(φ_r − φ_i)) · sin α · tan β), with
    α = max(θ_i, θ_r), β = min(θ_i, θ_r); 0 where cos θ_i ≤ 0.

    normals, to_light, to_viewer: (..., 3) unit vectors, broadcastable.
    roughness: σ in radians. Returns (...) float64. σ = 0 gives
    :func:`lambertian_radiance`.
    """
    a_coef, b_coef = oren_nayar_coefficients(roughness)
    n = np.asarray(normals, dtype=np.float64)
    light = np.asarray(to_light, dtype=np.float64)
    view = np.asarray(to_viewer, dtype=np.float64)
    cos_i = np.sum(n * light, axis=-1)
    lit = cos_i > 0.0
    if b_coef == 0.0:
        return np.where(lit, cos_i, 0.0)
    cos_r = np.sum(n * view, axis=-1)
    cos_i_c = np.clip(cos_i, -1.0, 1.0)
    cos_r_c = np.clip(cos_r, -1.0, 1.0)
    # Azimuths: project both directions onto the tangent plane.
    light_t = light - cos_i[..., None] * n
    view_t = view - cos_r[..., None] * n
    norm2 = np.sum(light_t * light_t, axis=-1) * np.sum(view_t * view_t, axis=-1)
    dot_t = np.sum(light_t * view_t, axis=-1)
    safe = norm2 > _AZIMUTH_EPS
    cos_phi = np.where(safe, dot_t / np.sqrt(np.where(safe, norm2, 1.0)), 0.0)
    # sin α · tan β with α the larger angle (smaller cosine) and β the smaller.
    cos_alpha = np.minimum(cos_i_c, cos_r_c)
    cos_beta = np.maximum(cos_i_c, cos_r_c)
    sin_alpha = np.sqrt(np.maximum(1.0 - cos_alpha * cos_alpha, 0.0))
    sin_beta = np.sqrt(np.maximum(1.0 - cos_beta * cos_beta, 0.0))
    tan_beta = sin_beta / np.maximum(cos_beta, 1e-300)
    radiance = cos_i * (a_coef + b_coef * np.maximum(cos_phi, 0.0) * sin_alpha * tan_beta)
    return np.where(lit, radiance, 0.0)


def colocated_radiance(cos_theta: ArrayLike, roughness: float) -> NDArray[np.float64]:
    """Oren–Nayar radiance with the light at the viewer: A·c + B·(1 − c²).

    Per unit albedo. cos_theta: (...) cosine of the angle between normal and
    light (= view) direction. Returns (...) float64; 0 where c ≤ 0.
    """
    a_coef, b_coef = oren_nayar_coefficients(roughness)
    c = np.asarray(cos_theta, dtype=np.float64)
    c_clip = np.clip(c, 0.0, 1.0)
    radiance = a_coef * c_clip + b_coef * (1.0 - c_clip * c_clip)
    return np.where(c > 0.0, radiance, 0.0)


def colocated_cosine(radiance: ArrayLike, roughness: float) -> NDArray[np.float64]:
    """Invert :func:`colocated_radiance` per pixel: c = cos θ from radiance I.

    Solves B·c² − A·c + (I − B) = 0 and takes the root on the physical
    branch (the one equal to 1 at I = A, continuous with the Lambertian
    c = I at B → 0), written as c = 2(I − B)/(A + √(A² − 4B(I − B))) to stay
    accurate for small B. The result is clamped to [0, 1]: I below the
    grazing value B gives 0, I above the frontal value A gives 1. NaN stays
    NaN.

    radiance: (...) float, per unit albedo × light. Returns (...) float64.
    """
    a_coef, b_coef = oren_nayar_coefficients(roughness)
    intensity = np.asarray(radiance, dtype=np.float64)
    excess = intensity - b_coef
    disc = np.maximum(a_coef * a_coef - 4.0 * b_coef * excess, 0.0)
    c = 2.0 * excess / (a_coef + np.sqrt(disc))
    return np.clip(c, 0.0, 1.0)
