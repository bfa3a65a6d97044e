"""Shape from shading by fast sweeping.

Oren–Nayar / Lambertian reflectance, the orthographic Eikonal model of the
seed paper and the near-light perspective model of Prados & Faugeras.
``endo_sfs.reconstruct(irradiance, camera, ...)`` is the entry point.
"""

from endo_sfs.relative_depth import SfsSolution, reconstruct, solve

__all__ = ["SfsSolution", "reconstruct", "solve"]
