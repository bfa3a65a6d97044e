"""Shape from shading by fast sweeping.

Oren–Nayar / Lambertian reflectance, the orthographic Eikonal model of the
seed paper and the near-light perspective model of Prados & Faugeras.
"""
