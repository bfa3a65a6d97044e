"""Loading the solver's numba kernels, or compiling them on the very first run.

The kernels (``cache=True``) are compiled once, in 68-82 s of CPU from an empty
cache (2026-12-02, session 10; 139-181 s before it), into the
kernel cache (:mod:`endo_io.kernel_cache`, ``~/.cache/endo3d/numba`` by
default); every later process loads them from there in about a second.
:func:`warm_up_kernels` solves tiny synthetic frames with every model and
order, so that a node's first real frame is not slow, and says up front when
it is about to compile. ``python -m endo_sfs.warm_up`` does the same once
(``make`` runs it after installing).

Whether the cache holds the kernels of these sources is remembered in a
stamp file beside the kernels, written after a complete warm-up: a digest of
the numba and Python versions and of the size and modification time of every
source file that defines cached kernels (what numba itself checks).
"""

from __future__ import annotations

import hashlib
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numba
import numpy as np

from endo_io.camera import CameraModel
from endo_io.kernel_cache import kernel_cache_dir
from endo_sfs.highlights import detect_highlights
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import solve, surface_normals
from endo_sfs.synthetic import near_light_surface, render_near_light, scene_camera

#: Said before the first compilation.
COMPILE_NOTICE = "compiling solver kernels, ~1-2 min, once (cached in {folder})"

_WARM_UP_SIZE = 24
_WARM_UP_PARALLEL_SIZE = 192
_STAMP_NAME = "endo_sfs.kernels"
#: A cached kernel's decorator (numba checks the stamp of that kernel's own file).
_CACHED_KERNEL = re.compile(r"@(?:numba\.|nb\.)?njit\([^)]*\bcache=True")


def kernel_fingerprint() -> str:
    """Digest of what decides whether cached kernels are still valid."""
    digest = hashlib.sha256(f"{numba.__version__} {sys.version}".encode())
    for source in sorted(Path(__file__).parent.glob("*.py")):
        if _CACHED_KERNEL.search(source.read_text(encoding="utf-8")):
            stat = source.stat()
            digest.update(f"{source} {stat.st_size} {stat.st_mtime_ns}".encode())
    return digest.hexdigest()


def _stamp() -> Path:
    # One stamp per source tree: numba keys its cache files by the source's path, so
    # checkouts sharing the cache folder each have kernels of their own; one shared
    # stamp flipped between them, and every start announced a compile it did not do.
    tree = hashlib.sha256(str(Path(__file__).resolve().parent).encode()).hexdigest()[:16]
    return kernel_cache_dir() / f"{_STAMP_NAME}.{tree}"


def kernels_cached() -> bool:
    """True when the kernel cache holds this source tree's kernels (no compile needed)."""
    try:
        return _stamp().read_text(encoding="utf-8").strip() == kernel_fingerprint()
    except OSError:
        return False


def warm_up_kernels(*, announce: Callable[[str], None] | None = None) -> float:
    """Solve tiny synthetic frames with every model and order.

    The kernels' numba signatures depend only on dtypes, so this loads (or,
    on the first run, compiles) exactly what real frames use.

    Args:
        announce: called with :data:`COMPILE_NOTICE` first when the kernels
            are not cached yet and are about to be compiled (a node passes its
            logger's ``info``).

    Returns:
        Seconds taken.
    """
    start = time.perf_counter()
    if announce is not None and not kernels_cached():
        announce(COMPILE_NOTICE.format(folder=kernel_cache_dir()))
    camera = scene_camera(_WARM_UP_SIZE)
    rendering = render_near_light(camera, near_light_surface("sphere"))
    image = rendering.irradiance.astype(np.float32)
    for order in (1, 2, 3):
        near_light = SfsOptions(model="near_light", order=order)
        previous = solve(image, camera, near_light)
        solve(image, camera, near_light, warm_start=previous)
        solve(image, camera, SfsOptions(model="orthographic", order=order, solve_scale=0.5))
    surface_normals(previous.depth, camera)
    # The two-thread first pass only runs on grids of near_light.MIN_PARALLEL_NODES+;
    # highlight detection, and float32 (the corrected image) beside float64.
    camera = scene_camera(_WARM_UP_PARALLEL_SIZE)
    image = render_near_light(camera, near_light_surface("tilted_plane")).irradiance
    fov = camera.fov_mask(0.48 * _WARM_UP_PARALLEL_SIZE)
    options = SfsOptions(model="near_light", threads=2, mask_highlights=True)
    for data in (image.astype(np.float32), image):
        previous = solve(data, camera, options, mask=fov)
        solve(data, camera, options, mask=fov, warm_start=previous)
    # The regions of a highlight are labelled only where there is one (a specular
    # sphere has one): without this, a fresh kernel cache compiled that kernel at a
    # node's first real frame (~0.5 s; frames 1-4 skipped at 0.3x in a fresh clone).
    shiny = render_near_light(camera, near_light_surface("sphere"), specular=2.0).irradiance
    detect_highlights(shiny.astype(np.float32), fov, None)
    try:
        _stamp().parent.mkdir(parents=True, exist_ok=True)
        _stamp().write_text(kernel_fingerprint() + "\n", encoding="utf-8")
    except OSError:
        pass  # an unwritable cache: numba compiles beside the source, we just cannot remember
    return time.perf_counter() - start


def warm_up_frame(camera: CameraModel, options: SfsOptions) -> float:
    """Solve a synthetic frame of ``camera`` with ``options``: cold, then warm-started.

    What a first real frame pays once per process and camera besides the
    kernels: the solve grids of this camera (built and cached,
    :func:`endo_sfs.grid.solve_grid`; the cold solve's coarse start has its
    own), frame-sized buffers, the highlight detection. A node calls it
    before it subscribes, so that its first frame costs what any later one
    does.

    Args:
        camera: the camera of the frames to come (its size and intrinsics).
        options: the solver settings the frames will be solved with.

    Returns:
        Seconds taken.
    """
    start = time.perf_counter()
    image = render_near_light(camera, near_light_surface("tube")).irradiance
    image = image.astype(np.float32)
    previous = solve(image, camera, options)
    solve(image, camera, options, warm_start=previous)
    return time.perf_counter() - start


def main() -> int:
    """``python -m endo_sfs.warm_up``: load or compile the kernels once; exit code 0."""
    seconds = warm_up_kernels(announce=lambda text: print(f"endo_sfs: {text}", flush=True))
    print(f"endo_sfs: solver kernels ready in {kernel_cache_dir()} ({seconds:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
