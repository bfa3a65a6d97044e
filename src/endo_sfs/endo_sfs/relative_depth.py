"""Public API: relative depth from one linear irradiance image.

``reconstruct`` is what offline tools, tests and the ``sfs`` node call.
``solve`` does the same and also returns what the next frame needs for a
warm start (the node-grid solution) and how the sweeps ended.

Conventions:

* Input: linear irradiance (after the camera response and the light map have
  been undone by ``endo_calib``), per unit albedo × light power, so that a
  Lambertian patch facing the light at distance r reads 1/r².
* Output: (H, W) float32 depth along the optical axis (REP 118 layout), NaN
  where invalid. It is relative: an albedo × light product ρ ≠ 1 scales every
  depth by √ρ (near-light model), and nothing is renormalised per frame, so
  the factor that ``endo_flow`` estimates to make it metric stays constant
  while albedo and gain do.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field, replace

import cv2
import numba
import numpy as np

from endo_io.camera import CameraModel
from endo_sfs.errors import (
    CameraMismatchError,
    IrradianceRangeError,
    NoValidPixelsError,
    SfsInputError,
    SolutionRangeError,
)
from endo_sfs.grid import SolveGrid, solve_grid
from endo_sfs.highlights import detect_highlights
from endo_sfs.near_light import solve_near_light
from endo_sfs.options import SfsOptions
from endo_sfs.orthographic import SolveInfo, solve_orthographic
from endo_sfs.resampling import depth_from_log_distance, usable_pixels
from endo_sfs.second_thread import beside

#: The settings a solve uses when none are given.
DEFAULT_OPTIONS = SfsOptions()
#: A near-light solve with no warm start at solve_scale >= COARSE_START_MIN_SCALE
#: starts from a solve of the same frame at COARSE_START_FACTOR of that scale.
#: From flat start values the value-ordered first pass costs ~7 node solves per
#: node; from the coarse solution the sweeps cost ~3.0-3.2. On the 640x480 phantom
#: with the node's settings: 80-87 ms instead of 182-237 ms, the depth within
#: 3e-4-2.1e-3 (relative, largest pixel) of the cold solve's at the default
#: tolerance (a node's first frame, and every frame with warm_start off).
COARSE_START_FACTOR = 0.25
COARSE_START_MIN_SCALE = 0.5


@dataclass(frozen=True)
class SfsSolution:
    """One solved frame.

    depth: (H, W) float32 relative depth along the optical axis, NaN invalid.
    node_solution: (ny, nx) float64 solution on the solve grid (ln r for the
    near-light model, depth for the orthographic one), NaN where invalid.
    node_irradiance: (ny, nx) float64 the data resampled to the grid.
    grid: the solve grid it lives on. valid: (H, W) bool pixels that had
    data. info: how the sweeps ended. model: the model solved.
    node_slope: near-light only, (ny, nx) float64 tan θ (angle between the
    surface normal and the ray) per node, NaN invalid; the next frame's
    Newton seeds.
    ordered_work: near-light only, node solves per node the last time a
    frame of this warm-start chain was solved with the value-ordered first
    pass; frames_since_ordered: frames since then; ordered_retries: retries
    of the ordered pass in a row that cost more than the limit (see
    :func:`_use_first_pass`). timings: wall seconds of the solve's stages
    (:data:`STAGES`; near-light only, empty otherwise).
    """

    depth: np.ndarray
    node_solution: np.ndarray
    node_irradiance: np.ndarray
    grid: SolveGrid
    valid: np.ndarray
    info: SolveInfo
    model: str
    node_slope: np.ndarray | None = None
    ordered_work: float | None = None
    frames_since_ordered: int = 0
    ordered_retries: int = 0
    timings: dict[str, float] = field(default_factory=dict)


#: The stages of a near-light solve timed in :attr:`SfsSolution.timings`:
#: the validity pass (finite, dark, saturated, mask, brightest value),
#: highlight detection, resampling to the nodes, the solver's inputs
#: (global shift, padded arrays), ordering and splitting, the sweeps (and
#: first pass), the sweeps' one-thread finish after two threads (0 on one
#: thread), unpadding, and the resampling back to depth. With two threads
#: and highlight masking the validity pass runs on the second thread while
#: this one detects the highlights (:mod:`endo_sfs.second_thread`), and
#: "validity" is what is left to wait for after the detection.
STAGES = ("validity", "highlights", "to_nodes", "inputs", "order", "sweeps", "finish",
          "outputs", "to_pixels")


@dataclass(frozen=True)
class PredictedStart:
    """A warm start predicted for the current frame, on the previous frame's solve grid.

    Made by :func:`endo_sfs.pose_prediction.predict_warm_start`.

    node_solution: (ny, nx) float64 predicted ln r (NaN where the previous
    surface is not seen). node_irradiance: (ny, nx) float64 the previous
    irradiance moved with it (and scaled by the distance change), for the
    solver's global shift. node_slope: (ny, nx) float64 the previous tan θ
    moved with it (Newton seeds), or None. grid: the solve grid.
    ordered_work, frames_since_ordered, ordered_retries: the warm-start
    chain's bookkeeping, carried over from the previous :class:`SfsSolution`.
    """

    node_solution: np.ndarray
    node_irradiance: np.ndarray | None
    node_slope: np.ndarray | None
    grid: SolveGrid
    ordered_work: float | None = None
    frames_since_ordered: int = 0
    ordered_retries: int = 0


def valid_pixels(
    irradiance: np.ndarray,
    mask: np.ndarray | None = None,
    dark_level: float = 0.0,
    saturation: float | None = None,
) -> np.ndarray:
    """Pixels usable as data: finite, above ``dark_level``, below ``saturation``.

    irradiance: (H, W) float; mask: optional (H, W) bool (e.g. the circular
    field of view). Returns (H, W) bool.
    """
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(irradiance) & (irradiance > dark_level)
        if saturation is not None:
            valid &= irradiance < saturation
    if mask is not None:
        valid &= mask
    return valid


def smooth_irradiance(irradiance: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass of the valid pixels only (normalised convolution).

    irradiance: (H, W) float; valid: (H, W) bool; sigma: pixels (0: none).
    Invalid pixels neither contribute nor change. Returns (H, W) float64.
    Near c ≈ 1 the slope √(1/c² − 1) amplifies noise and rectifies it into
    a bias; σ ≈ 1 px cuts 8-bit noise about 3.5× for an O(σ²) blur of the
    shading.
    """
    if sigma <= 0.0:
        return np.asarray(irradiance, dtype=np.float64)
    weight = valid.astype(np.float64)
    data = np.where(valid, irradiance, 0.0).astype(np.float64)
    blurred = cv2.GaussianBlur(data, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    norm = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(valid, blurred / norm, irradiance)


def _check_inputs(
    irradiance: np.ndarray, camera: CameraModel, mask: np.ndarray | None
) -> np.ndarray:
    image = np.asarray(irradiance)
    if image.ndim != 2:
        raise SfsInputError(f"irradiance must be a single-channel (H, W) image, got {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise SfsInputError(
            f"irradiance must be linear float (endo_calib output), got dtype {image.dtype}"
        )
    if image.shape != (camera.height, camera.width):
        raise CameraMismatchError(
            f"image is {image.shape[1]}x{image.shape[0]} but camera_info is "
            f"{camera.width}x{camera.height}"
        )
    if mask is not None and np.shape(mask) != image.shape:
        raise SfsInputError(f"mask has shape {np.shape(mask)}, expected {image.shape}")
    return image


def _check_irradiance_range(image: np.ndarray, max_irradiance: float) -> None:
    """Refuse a frame whose finite values exceed ``max_irradiance`` (not irradiance).

    Raises:
        IrradianceRangeError: one line with the peak and the bound.
    """
    peak = float(np.max(image, where=np.isfinite(image), initial=-np.inf))
    if peak > max_irradiance:
        raise IrradianceRangeError(
            f"irradiance reaches {peak:.3g}, above max_irradiance {max_irradiance:.3g}: not "
            "linear irradiance from the photometric correction (frame refused)"
        )


def _check_solution(depth: np.ndarray, model: str) -> None:
    """Refuse a solution with infinite (or, near-light, zero) depth: the solve overflowed.

    Raises:
        SolutionRangeError: one line naming how many pixels.
    """
    with np.errstate(invalid="ignore"):
        bad = np.isinf(depth)
        if model == "near_light":
            bad |= depth <= 0.0
    count = int(np.count_nonzero(bad))
    if count:
        raise SolutionRangeError(
            f"the {model} solve overflowed: {count} pixels of depth are infinite or not "
            "positive (frame refused)"
        )


WarmStart = SfsSolution | PredictedStart | np.ndarray


def _warm_nodes(
    warm_start: WarmStart | None, grid: SolveGrid
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The previous ln r on ``grid`` (NaN where unknown); its data and slopes if known."""
    if warm_start is None:
        return None, None, None
    if isinstance(warm_start, PredictedStart):
        if warm_start.grid is grid:
            return warm_start.node_solution, warm_start.node_irradiance, warm_start.node_slope
        return None, None, None  # another camera or solve_scale: nothing to predict from
    if isinstance(warm_start, SfsSolution):
        if warm_start.grid is grid and warm_start.model == "near_light":
            return warm_start.node_solution, warm_start.node_irradiance, warm_start.node_slope
        warm_start = warm_start.depth
    return log_distance_nodes(warm_start, grid), None, None


def log_distance_nodes(depth: np.ndarray, grid: SolveGrid) -> np.ndarray:
    """ln r on the nodes of a stereographic ``grid`` from an (H, W) depth image.

    depth: (H, W) float depth along the optical axis, NaN invalid. Returns
    (ny, nx) float64, NaN where a node's four pixels are not all finite.

    Raises:
        SfsInputError: the depth is not the grid's camera's size.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != grid.pixel_rays.shape[:2]:
        raise SfsInputError(
            f"warm_start depth has shape {depth.shape}, expected {grid.pixel_rays.shape[:2]}"
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        log_r = np.log(depth / grid.pixel_rays[..., 2])
    log_r_nodes, ok = grid.to_nodes(np.nan_to_num(log_r), np.isfinite(log_r))
    return np.where(ok, log_r_nodes, np.nan)


#: A warm-start chain keeps the value-ordered first pass while it costs at
#: most this many node solves per node; above it (a poorly predicted order:
#: noisy texture, fast motion) frames are swept from the start, which costs
#: about 3.3-3.9 solves per node whatever the order, and the ordered pass is
#: tried again RETRY_FIRST_PASS frames later. Each retry that costs more than
#: the limit again doubles the wait, up to RETRY_FIRST_PASS_MAX frames (2.7 s
#: at 30 fps): on the phantom video every retry fails (9 of 9 over its 90
#: frames) and costs 1.7-2.5x a swept frame at full resolution on two threads
#: (the split first pass mostly falls back to one thread there; docs/sfs.md,
#: "Sweeps alone when the order is poor").
FIRST_PASS_WORK_LIMIT = 2.5
RETRY_FIRST_PASS = 10
RETRY_FIRST_PASS_MAX = 80


def retry_interval(ordered_retries: int) -> int:
    """Frames from an ordered pass that cost too much to the next try, after ``ordered_retries``.

    ordered_retries: the retries in a row that cost more than
    :data:`FIRST_PASS_WORK_LIMIT` (0 after the pass that started the sweeps).
    Returns RETRY_FIRST_PASS·2^ordered_retries, at most RETRY_FIRST_PASS_MAX.
    """
    return min(RETRY_FIRST_PASS << min(ordered_retries, 16), RETRY_FIRST_PASS_MAX)


def _use_first_pass(warm_start: WarmStart | None) -> bool:
    """Whether to solve this frame with the value-ordered first pass.

    On the synthetic tube sequence the previous frame's order is nearly the
    solution's (1.02-1.05 solves per node with it); on the textured, noisy
    phantom video it is not (3.7-4.4, against 3.8 for sweeps alone, which
    visit memory in order and cost less per solve).
    """
    if not isinstance(warm_start, SfsSolution | PredictedStart):
        return True
    if warm_start.ordered_work is None:
        return True
    if warm_start.ordered_work <= FIRST_PASS_WORK_LIMIT:
        return True
    interval = retry_interval(warm_start.ordered_retries)
    return warm_start.frames_since_ordered + 1 >= interval


@contextmanager
def _numba_threads(threads: int) -> Iterator[None]:
    """Run the block with numba's parallel kernels on at most ``threads`` threads."""
    previous = numba.get_num_threads()
    # numba.config sets its NUMBA_* names at run time, out of mypy's sight.
    pool_size: int = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]
    numba.set_num_threads(min(threads, pool_size))
    try:
        yield
    finally:
        numba.set_num_threads(previous)


def solve(
    irradiance: np.ndarray,
    camera: CameraModel,
    options: SfsOptions = DEFAULT_OPTIONS,
    *,
    mask: np.ndarray | None = None,
    warm_start: WarmStart | None = None,
    boundary_depth: np.ndarray | None = None,
) -> SfsSolution:
    """Shape from shading of one frame; see :func:`reconstruct` for the arguments.

    Returns an :class:`SfsSolution` (its ``depth`` is what ``reconstruct``
    returns; pass the whole solution as the next frame's ``warm_start``).
    """
    if not isinstance(options, SfsOptions):
        raise SfsInputError(f"options must be an SfsOptions, got {type(options).__name__}")
    if not options.threads:
        shape = np.shape(irradiance)
        # Not an image: one thread, and _check_inputs names the bad shape below.
        height, width = shape if len(shape) == 2 else (0, 0)
        options = replace(options, threads=options.solve_threads(height, width))
    model = options.model
    if model == "near_light" and warm_start is None and (
        options.solve_scale >= COARSE_START_MIN_SCALE
    ):
        coarse = replace(options, solve_scale=options.solve_scale * COARSE_START_FACTOR)
        # nothing usable that coarse: solve cold
        with suppress(NoValidPixelsError, SolutionRangeError):
            warm_start = solve(irradiance, camera, coarse, mask=mask)
    # numba's thread count is per calling thread: set it for this call only.
    with _numba_threads(options.threads):
        image = _check_inputs(irradiance, camera, mask)
        if model == "near_light":
            return _solve_near_light(image, camera, options, mask, warm_start)
        _check_irradiance_range(image, options.max_irradiance)
        valid = valid_pixels(image, mask, options.dark_level, options.saturation)
        if options.mask_highlights:
            valid &= ~detect_highlights(image, mask, options.saturation,
                                        downsample=options.detection_downsample(image.shape[0]))
        grid = solve_grid(camera, "gnomonic", options.solve_scale)
        valid &= grid.pixel_has_ray
        if not valid.any():
            raise NoValidPixelsError(
                "no usable pixel: the frame is all dark, saturated, NaN or masked"
            )
        nodes, node_valid = grid.to_nodes(
            smooth_irradiance(image, valid, options.smoothing), valid
        )
        if not node_valid.any():
            raise NoValidPixelsError("no usable pixel survives resampling to the solve grid")
        boundary_nodes = None
        if boundary_depth is not None:
            if boundary_depth.shape != image.shape:
                raise SfsInputError(
                    f"boundary_depth has shape {boundary_depth.shape}, expected {image.shape}"
                )
            known = np.isfinite(boundary_depth)
            values, ok = grid.to_nodes(np.nan_to_num(boundary_depth), known)
            boundary_nodes = np.where(ok, values, np.nan)
        node_solution, info = solve_orthographic(
            nodes, node_valid, grid.spacing, roughness=options.roughness,
            order=options.order, singular_tolerance=options.singular_tolerance,
            boundary_depth=boundary_nodes, concave=options.concave,
            tolerance=options.tolerance, max_iterations=options.max_iterations,
        )
        depth = grid.to_pixels(node_solution, valid).astype(np.float32)
        _check_solution(depth, model)
        return SfsSolution(
            depth=depth, node_solution=node_solution, node_irradiance=nodes, grid=grid,
            valid=valid, info=info, model=model,
        )


def _solve_near_light(
    image: np.ndarray,
    camera: CameraModel,
    options: SfsOptions,
    mask: np.ndarray | None,
    warm_start: WarmStart | None,
) -> SfsSolution:
    """:func:`solve` for the near-light model, every per-pixel pass fused where it can be.

    The same arithmetic as the orthographic path's separate steps
    (valid_pixels, to_nodes, to_pixels), in fewer passes over the image;
    the stages' wall times go to :attr:`SfsSolution.timings`.
    """
    timings: dict[str, float] = {}
    start = time.perf_counter()
    grid = solve_grid(camera, "stereographic", options.solve_scale)
    region = np.empty((0, 0), dtype=bool) if mask is None else np.ascontiguousarray(mask, bool)
    saturation = np.inf if options.saturation is None else options.saturation

    def validity() -> tuple[np.ndarray, float]:
        return usable_pixels(image, region, grid.pixel_has_ray, options.dark_level, saturation)

    highlights = None
    if options.mask_highlights and options.threads > 1:
        # The validity pass on the second thread while this one detects the
        # highlights (which then start their own second-thread part);
        # "validity" is the wait for it after the detection.
        timings["validity"] = 0.0  # (the stages in their usual order)
        started = beside(validity)
        highlights = detect_highlights(image, mask, options.saturation,
                                       downsample=options.detection_downsample(image.shape[0]),
                                       threads=options.threads)  # fmt: skip
        timings["highlights"] = (now := time.perf_counter()) - start
        start = now
        valid, peak = started.result()
    else:
        valid, peak = validity()
    if peak > options.max_irradiance:
        raise IrradianceRangeError(
            f"irradiance reaches {peak:.3g}, above max_irradiance "
            f"{options.max_irradiance:.3g}: not linear irradiance from the photometric "
            "correction (frame refused)"
        )
    timings["validity"] = (now := time.perf_counter()) - start
    start = now
    if highlights is None and options.mask_highlights:
        highlights = detect_highlights(image, mask, options.saturation,
                                       downsample=options.detection_downsample(image.shape[0]))
    if highlights is not None:
        valid &= ~highlights
    if "highlights" not in timings:
        timings["highlights"] = (now := time.perf_counter()) - start
        start = now
    if not valid.any():
        raise NoValidPixelsError(
            "no usable pixel: the frame is all dark, saturated, NaN or masked"
        )
    data = image if options.smoothing <= 0.0 else smooth_irradiance(
        image, valid, options.smoothing
    )
    nodes, node_valid = grid.to_nodes(data, valid)
    if not node_valid.any():
        raise NoValidPixelsError("no usable pixel survives resampling to the solve grid")
    timings["to_nodes"] = time.perf_counter() - start
    warm_log_r, warm_irradiance, warm_slope = _warm_nodes(warm_start, grid)
    first_pass = _use_first_pass(warm_start)
    log_r, node_slope, info = solve_near_light(
        nodes, node_valid, grid.conformal_factor_sq, grid.spacing,
        roughness=options.roughness, order=options.order,
        tolerance=options.tolerance, max_iterations=options.max_iterations,
        warm_start=warm_log_r, warm_start_intensity=warm_irradiance,
        warm_start_slope=warm_slope, threads=options.threads, first_pass=first_pass,
        first_sweeps=options.first_sweeps, timings=timings,
    )
    ordered_work: float | None = None
    frames_since_ordered = 0
    ordered_retries = 0
    if first_pass:
        ordered_work = info.updates / max(1, int(node_valid.sum()))
        if (
            isinstance(warm_start, SfsSolution | PredictedStart)
            and warm_start.grid is grid
            and warm_start.ordered_work is not None
            and warm_start.ordered_work > FIRST_PASS_WORK_LIMIT
            and ordered_work > FIRST_PASS_WORK_LIMIT
        ):
            # A retry from sweeps that did not pay either: wait longer for the next.
            ordered_retries = warm_start.ordered_retries + 1
    elif isinstance(warm_start, SfsSolution | PredictedStart):
        ordered_work = warm_start.ordered_work
        frames_since_ordered = warm_start.frames_since_ordered + 1
        ordered_retries = warm_start.ordered_retries
    start = time.perf_counter()
    depth, overflowed = depth_from_log_distance(
        log_r, grid.pixel_node_x, grid.pixel_node_y, valid, grid.pixel_ray_z
    )
    if overflowed:
        raise SolutionRangeError(
            f"the near_light solve overflowed: {overflowed} pixels of depth are infinite or "
            "not positive (frame refused)"
        )
    timings["to_pixels"] = time.perf_counter() - start
    return SfsSolution(
        depth=depth,
        node_solution=log_r,
        node_irradiance=nodes,
        grid=grid,
        valid=valid,
        info=info,
        model="near_light",
        node_slope=node_slope,
        ordered_work=ordered_work,
        frames_since_ordered=frames_since_ordered,
        ordered_retries=ordered_retries,
        timings=timings,
    )


def reconstruct(
    irradiance: np.ndarray,
    camera: CameraModel,
    options: SfsOptions = DEFAULT_OPTIONS,
    *,
    mask: np.ndarray | None = None,
    warm_start: WarmStart | None = None,
    boundary_depth: np.ndarray | None = None,
) -> np.ndarray:
    """Relative depth from one linear irradiance image by shape from shading.

    Example::

        options = SfsOptions(roughness=0.3, mask_highlights=True)
        depth = reconstruct(irradiance, camera, options, mask=camera.fov_mask(200.0))

    Args:
        irradiance: (H, W) float linear irradiance per unit albedo × light
            (see the module docstring). NaN, values ≤ ``options.dark_level``
            and values ≥ ``options.saturation`` are not data.
        camera: the image's camera model (same size as the image); its
            per-pixel ray table handles distortion.
        options: the solver settings (:class:`endo_sfs.SfsOptions`: model,
            roughness, solve_scale, tolerance, order, ...), validated when
            built.
        mask: optional (H, W) bool of pixels to use (e.g. the circular FOV).
        warm_start: the previous frame's :class:`SfsSolution` (cheapest) or
            its (H, W) depth, or None (near-light at solve_scale >= 0.5: a
            solve at a quarter of the scale first, :data:`COARSE_START_FACTOR`).
            Used by the near-light model only.
        boundary_depth: orthographic model only: (H, W) relative depth
            where known, NaN elsewhere; the Eikonal's sources instead of the
            singular points (see
            :func:`endo_sfs.orthographic.solve_orthographic`).

    Returns:
        (H, W) float32 relative depth along the optical axis, NaN invalid.

    Raises:
        CameraMismatchError: the camera's size differs from the image's.
        NoValidPixelsError: no usable pixel (all dark, saturated, NaN).
        SfsInputError: bad arrays (shape, dtype) or ``options`` not an
            :class:`SfsOptions`.
    """
    return solve(
        irradiance, camera, options, mask=mask, warm_start=warm_start,
        boundary_depth=boundary_depth,
    ).depth


def surface_normals(depth: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Unit surface normals of a depth map, facing the camera.

    depth: (H, W) float depth along the optical axis (any unit), NaN invalid.
    Returns (H, W, 3) float32 normals in the optical frame (n·ray < 0), NaN
    where a neighbour is missing.
    """
    rays = camera.unit_rays()
    points = camera.depth_to_points(depth)
    du = np.full_like(points, np.nan)
    dv = np.full_like(points, np.nan)
    du[:, 1:-1] = points[:, 2:] - points[:, :-2]
    dv[1:-1] = points[2:] - points[:-2]
    normals = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        flip = np.sum(normals * rays, axis=-1) > 0.0
    normals[flip] *= -1.0
    return normals.astype(np.float32)
