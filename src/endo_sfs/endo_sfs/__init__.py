"""Shape from shading by fast sweeping.

Oren–Nayar / Lambertian reflectance, the orthographic Eikonal model of the
seed paper and the near-light perspective model of Prados & Faugeras.
``endo_sfs.reconstruct(irradiance, camera, SfsOptions(...), mask=...)`` is
the entry point; the names below are imported on first use.
"""

import os
from typing import TYPE_CHECKING

from endo_io.kernel_cache import use_kernel_cache
from endo_io.lazy_exports import lazy_exports

# Compiled kernels go to ~/.cache/endo3d/numba (or NUMBA_CACHE_DIR), not beside
# the sources; numba picks the folder when a kernel is decorated, so this runs
# before any kernel module is imported.
use_kernel_cache()

# The solver's parallel regions (numba on OpenMP) are short and alternate
# with single-threaded work; OpenMP's default is to keep idle workers
# spinning, which takes a whole core from the rest of the ROS graph for
# nothing. Passive workers sleep between regions. Only applies when the
# variable is unset and before the OpenMP runtime loads (first parallel call).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

if TYPE_CHECKING:
    from endo_sfs.errors import SfsError, SfsInputError
    from endo_sfs.evaluation import DepthError, depth_error
    from endo_sfs.node import SfsNode
    from endo_sfs.options import SfsOptions
    from endo_sfs.relative_depth import SfsSolution, reconstruct, solve, surface_normals

__all__ = [
    "DepthError",
    "SfsError",
    "SfsInputError",
    "SfsNode",
    "SfsOptions",
    "SfsSolution",
    "depth_error",
    "reconstruct",
    "solve",
    "surface_normals",
]
__getattr__, __dir__ = lazy_exports(__name__)
