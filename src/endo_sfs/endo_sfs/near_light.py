"""Perspective shape from shading with a point light at the optical centre.

Model (Prados & Faugeras 2005; Oren–Nayar variant after Ahmed & Farag 2006).
A surface point seen along the unit ray ω lies at S = r·ω; the light sits at
the optical centre, so light and viewing directions coincide with −ω and the
irradiance is I = R(cos θ)/r² with R the co-located reflectance
(:func:`endo_sfs.reflectance.colocated_radiance`; albedo × light = 1).
With v = ln r and |∇_g v| the gradient norm on the sphere of directions,
cos θ = 1/√(1 + |∇_g v|²), hence

    I·e^{2v} = R(1/√(1 + |∇_g v|²)).

(In Prados–Faugeras' pixel form, with u = r/f, this is
(I·f²/Q)·√(f²|∇v|² + (∇v·x)² + Q²) = e^{−2v} for the Lambertian R(c) = c.)
On the stereographic chart s of :mod:`endo_sfs.grid`, |∇_g v| = |∇_s v|/λ(s),
so the equation solved is

    |∇_s v| = λ(s)·F(s, v),   F² = 1/c(I·e^{2v})² − 1,

an Eikonal equation whose right side falls as v grows: the Hamiltonian is
strictly increasing in v, which is what makes the problem well-posed without
boundary data. The mask edge is a state constraint (no information enters),
and singular points (c = 1) come out at v* = ½·ln(A/I) by themselves.

Well-posedness in practice: where the surface's distance to the camera
*decreases* towards the mask edge (its nearest point lies outside the view),
the missing data are replaced by the state constraint and the error decays
inward like exp(−2·Δv/sin² θ). Scenes whose nearest points are in view are
recovered to discretisation accuracy.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

import numpy as np

from endo_sfs import kernels
from endo_sfs.errors import NoValidPixelsError, SfsInputError
from endo_sfs.orthographic import SolveInfo
from endo_sfs.reflectance import oren_nayar_coefficients
from endo_sfs.visit_order import FIRST_PASS_BUCKETS, split_first_pass, value_order

#: WENO smoothness regulariser, relative to the squared node spacing.
_WENO_EPS_REL = 0.1
#: Largest roughness for which the co-located Oren–Nayar model is invertible
#: (A ≥ 2B keeps R(c) monotone on [0, 1]; equality at σ ≈ 0.622 rad).
MAX_ROUGHNESS = 0.6


#: Below this many nodes the first pass is not split across threads (the
#: thread start-up and the seam cost more than they save).
MIN_PARALLEL_NODES = 20000

#: Padded work arrays kept per (grid shape, thread), so that a stream of
#: frames on one grid allocates them once: (v, node, valid, key).
_WORKSPACES: OrderedDict[
    tuple[int, int, int], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
] = OrderedDict()
_WORKSPACE_COUNT = 4


def _workspace(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The padded arrays of :func:`endo_sfs.kernels.near_light_inputs_into` for ``shape``."""
    ny, nx = shape
    slot = (ny, nx, threading.get_ident())
    arrays = _WORKSPACES.get(slot)
    if arrays is None:
        arrays = (
            np.empty((ny + 4, nx + 4)),
            np.empty((ny + 4, nx + 4, 4)),
            np.empty((ny + 4, nx + 4), dtype=np.uint8),
            np.empty((ny + 4, nx + 4)),
        )
        _WORKSPACES[slot] = arrays
        while len(_WORKSPACES) > _WORKSPACE_COUNT:
            _WORKSPACES.popitem(last=False)
    else:
        _WORKSPACES.move_to_end(slot)
    return arrays


def global_shift(
    previous: np.ndarray,
    valid: np.ndarray,
    intensity: np.ndarray,
    previous_intensity: np.ndarray | None,
) -> float:
    """The frame's global change of v*: −½·median(ln(I/I_prev)) over nodes known in both.

    The camera moving towards or away from the surface changes every v by
    about this much. previous, intensity, previous_intensity: (ny, nx);
    valid: (ny, nx) bool. Returns ln-distance units (0 when unknown).
    """
    if previous_intensity is None:
        return 0.0
    # Every other node in each direction: the median of a quarter of the
    # nodes is as good a global shift and four times cheaper.
    median = kernels.median_log_ratio(
        np.asarray(intensity, dtype=np.float64), np.asarray(valid, dtype=bool),
        np.asarray(previous, dtype=np.float64),
        np.asarray(previous_intensity, dtype=np.float64), 2,
    )
    if not np.isfinite(median):
        return 0.0
    return -0.5 * float(median)


def solve_near_light(
    intensity: np.ndarray,
    valid: np.ndarray,
    conformal_factor_sq: np.ndarray,
    spacing: tuple[float, float],
    *,
    roughness: float = 0.0,
    order: int = 1,
    tolerance: float = 1e-6,
    max_iterations: int = 100,
    warm_start: np.ndarray | None = None,
    warm_start_intensity: np.ndarray | None = None,
    warm_start_slope: np.ndarray | None = None,
    threads: int = 1,
    first_pass: bool = True,
    first_sweeps: bool = False,
    timings: dict[str, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, SolveInfo]:
    """Log-distance v = ln r per node of a stereographic solve grid.

    intensity: (ny, nx) float irradiance per unit albedo × light, > 0 at valid
    nodes. valid: (ny, nx) bool. conformal_factor_sq: (ny, nx) λ². spacing:
    (hx, hy) chart units per node. roughness: Oren–Nayar σ in radians,
    0 ≤ σ ≤ 0.6. order: 1 (Godunov) or 3 (WENO3 Godunov; a cold start runs
    first order first). tolerance: stop when no node of a full iteration
    changed v by more than this (relative distance). warm_start: (ny, nx) v
    from the previous frame (NaN where unknown) or None; warm_start_intensity:
    that frame's (ny, nx) node irradiance, if known (see
    :func:`global_shift` and :func:`endo_sfs.kernels.near_light_inputs`);
    warm_start_slope: that frame's (ny, nx) F = tan θ per node, if known
    (Newton seeds). threads: 2 runs the first pass of large grids as two
    halves at once (:func:`endo_sfs.visit_order.split_first_pass`); the result
    then agrees with one thread's to the tolerance, not bit for bit.
    first_pass: solve every node once in predicted value order before
    sweeping (orders 1 and 2); False sweeps from the start, which is
    cheaper when the predicted order is poor (see
    :func:`endo_sfs.relative_depth.solve`, which chooses). first_sweeps:
    with a warm start and no first pass, solve each node first in the sweep
    that meets its predicted upwind neighbours first
    (:func:`endo_sfs.kernels.mark_first_sweeps`). timings: if
    given, receives the wall seconds of the stages ("inputs", "order",
    "sweeps", "finish", "outputs"; "finish" is the one-thread end of the
    sweeps after a two-thread first pass or split sweeps, 0 on one thread,
    and "sweeps" the rest of them).
    Returns ((ny, nx) float64 v, NaN at invalid nodes; (ny, nx) float64
    F = tan θ, the angle between surface normal and ray, NaN at invalid
    nodes; info).
    """
    if order not in (1, 2, 3):
        raise SfsInputError(f"order must be 1, 2 or 3, got {order}")
    if not 0.0 <= roughness <= MAX_ROUGHNESS:
        raise SfsInputError(f"roughness must be in [0, {MAX_ROUGHNESS}] rad, got {roughness}")
    start = time.perf_counter()
    intensity = np.asarray(intensity, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(intensity) & (intensity > 0.0)
    if not valid.any():
        raise NoValidPixelsError("no node with a positive, finite irradiance")
    coef_a, coef_b = oren_nayar_coefficients(roughness)
    reflectance = np.array([coef_a, coef_b])
    previous = np.empty((0, 0))
    previous_slope = np.empty((0, 0))
    shift = 0.0
    if warm_start is not None:
        if warm_start.shape != intensity.shape:
            raise SfsInputError(
                f"warm_start has shape {warm_start.shape}, expected {intensity.shape}"
            )
        previous = np.asarray(warm_start, dtype=np.float64)
        shift = global_shift(previous, valid, intensity, warm_start_intensity)
        if warm_start_slope is not None and warm_start_slope.shape == intensity.shape:
            previous_slope = np.asarray(warm_start_slope, dtype=np.float64)
    # The sweeps start from v*, above the solution, so values only fall and
    # the scheme stays causal; the previous frame orders the first pass and
    # seeds each node's Newton solve.
    v, node, valid_p, key = _workspace(intensity.shape)
    kernels.near_light_inputs_into(
        intensity, valid, np.asarray(conformal_factor_sq, dtype=np.float64), previous,
        previous_slope, shift, reflectance, v, node, valid_p, key,
    )
    stages: dict[str, float] = {} if timings is None else timings
    stages["inputs"] = (now := time.perf_counter()) - start
    start = now
    hx, hy = spacing
    eps = _WENO_EPS_REL * hx * hy
    updates = 0
    table = kernels.log_radiance_table(reflectance)
    # Causal schemes: one pass in increasing order of the start values first
    # (nearly the order of the solution), then sweeps repair the rest.
    no_pass = np.empty(0, dtype=np.int64)
    no_key = np.empty((0, 0))
    nodes = int(np.count_nonzero(valid_p))
    if order == 3 and warm_start is None:
        _, _, updates = kernels.near_light_sweep(
            v, node, valid_p, hx, hy, reflectance, 2, tolerance, max_iterations, eps, table,
            value_order(key, valid_p, FIRST_PASS_BUCKETS), 0, no_pass, 0, no_key, no_pass,
        )
    ordered, split, seam, sweep_split = no_pass, 0, no_pass, 0
    parallel = threads > 1 and nodes >= MIN_PARALLEL_NODES
    if order != 3 and first_pass:
        ordered = value_order(key, valid_p, FIRST_PASS_BUCKETS)
        if parallel:
            ordered, split, seam = split_first_pass(ordered, v.shape[1], 1 if order == 1 else 2)
    elif order != 3 and parallel:
        # Sweeps alone: two halves of equal node count, split by rows.
        sweep_split = int(np.searchsorted(np.cumsum(valid_p.sum(axis=1)), nodes // 2))
    stages["order"] = (now := time.perf_counter()) - start
    start = now
    ticks = np.zeros(3, dtype=np.int64)
    iterations, change, more = kernels.near_light_sweep(
        v, node, valid_p, hx, hy, reflectance, order, tolerance, max_iterations, eps, table,
        ordered, split, seam, sweep_split,
        key if first_sweeps and warm_start is not None else no_key, ticks,
    )
    seconds = (now := time.perf_counter()) - start
    # The one-thread finish's share of the kernel, by its cycle counts.
    total = int(ticks[2] - ticks[0])
    # the share is clamped: a counter that is not constant-rate or not synchronised
    # between cores must not make a negative or oversized stage
    share = min(max(int(ticks[2] - ticks[1]) / total, 0.0), 1.0) if total > 0 else 0.0
    finish = seconds * share
    stages["sweeps"] = seconds - finish
    stages["finish"] = finish
    start = now
    info = SolveInfo(
        int(iterations), float(change), bool(change <= tolerance), int(updates + more)
    )
    log_r, slope = kernels.near_light_outputs(v, node, valid)
    stages["outputs"] = time.perf_counter() - start
    return log_r, slope, info
