"""Numba kernels of the fast-sweeping solvers (resampling: endo_sfs.resampling).

Every kernel works in place on *padded* grids: two layers of invalid nodes
surround the solve grid, so that the 5-point WENO stencils never leave the
array and no loop carries a bounds check. Invalid nodes hold ``+inf``; an
infinite neighbour is never upwind, which is exactly the state-constraint
boundary condition (no information enters through the mask edge).

Sweeps follow Zhao (2005): four Gauss–Seidel passes with alternating
orderings, repeated until the largest change of a full iteration is below the
tolerance. Nodes are skipped while *locked* (Bak, McLaughlin & Renzi 2010):
a node is unlocked only when a node within its stencil changed by more than
the tolerance (and, for the causal upwind schemes, only if that node may be
upwind of it). The near-light solver first solves every node once in
(nearly) increasing order of its value, as fast marching would, so that the
sweeps only repair. All kernels use numpy's error model: no Python exception
checks on divisions inside the loops; an infinite or NaN result is handled
by the bracketing logic instead.

Per-node cost: numba reference-counts an array each time it is passed to a
function that is not inlined, with atomic increments and decrements. In the
sweep loops that was eight such calls around every node solve (v, node,
reflectance, table), about a fifth of the sweeps' time. So every function a
node solve calls is ``inline="always"``, and the loops that allocate nothing
(:func:`_sweeps`, :func:`_ordered_pass`, :func:`_repair_steps`) are compiled
without reference counting at all (``_nrt=False``). Those loops inline the
node solve only for the default order 2; orders 1 and 3 call it, which
keeps the compilation of an empty kernel cache short (see :func:`_sweeps`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit, prange

from endo_sfs.cycles import cycle_counter
from endo_sfs.heap import heap_pop, heap_push
from endo_sfs.prefetch import prefetch
from endo_sfs.visit_order import FIRST_PASS_BUCKETS, value_order

#: LLVM fast-math flags that keep IEEE infinities and NaNs (the kernels rely
#: on +inf for invalid nodes): contraction, reciprocal, reassociation.
_FAST = {"contract", "arcp", "reassoc", "afn"}

#: numba's (private) option that compiles a kernel without reference counting;
#: only for kernels that allocate nothing (see the module docstring).
_NO_REFCOUNTS: dict[str, Any] = {"_nrt": False}

#: Below this cosine a surface is taken as grazing: the data term is infinite.
_MIN_COSINE = 1e-6
#: The per-node Newton solve ends once its residual bounds the error of
#: tan θ below this (relative); one last Newton step then refines it to
#: ~1e-6 (quadratic convergence), far below the sweeps' tolerance on v.
_NEWTON_RESIDUAL_TOL = 1e-3
_NEWTON_MAX_STEPS = 60


# --------------------------------------------------------------------------
# Local updates
# --------------------------------------------------------------------------


@njit(cache=True, nogil=True, error_model="numpy")
def godunov_eikonal_update(
    a: float, ha: float, wa: float, b: float, hb: float, wb: float, f: float
) -> float:
    """Smallest t with ((t−a)⁺/ha)² + ((t−b)⁺/hb)² = f² (Godunov upwind update).

    a, b: upwind neighbour values along x and y (+inf if none); ha, hb their
    effective spacings and wa = 1/ha², wb = 1/hb² (passed in so that the
    sweep loops divide once per update); f ≥ 0 the right-hand side of
    |∇T| = f.
    """
    if a <= b:
        p, hp, wp, q, wq = a, ha, wa, b, wb
    else:
        p, hp, wp, q, wq = b, hb, wb, a, wa
    if p == np.inf:
        return np.inf
    t = p + hp * f
    if t <= q:
        return t
    d = q - p
    w = wp + wq
    disc = w * f * f - wp * wq * d * d
    if disc < 0.0:
        disc = 0.0
    return (wp * p + wq * q + np.sqrt(disc)) / w


@njit(cache=True, nogil=True, error_model="numpy")
def colocated_cosine_scalar(radiance: float, coef_a: float, coef_b: float) -> float:
    """Scalar twin of :func:`endo_sfs.reflectance.colocated_cosine` (clamped to [0, 1])."""
    excess = radiance - coef_b
    disc = coef_a * coef_a - 4.0 * coef_b * excess
    if disc < 0.0:
        disc = 0.0
    c = 2.0 * excess / (coef_a + np.sqrt(disc))
    if c < 0.0:
        return 0.0
    if c > 1.0:
        return 1.0
    return c


#: The per-node solve reads v(F) = g(F) + v* from a table of
#: g(F) = ½·ln(R(1/√(1+F²))/A) and g'(F) on F = tan θ ∈ [0, TABLE_MAX_SLOPE]
#: (θ up to 86°), cubic Hermite between entries (error ~1e-11): a lookup in
#: place of a square root, a division and a logarithm per Newton step.
TABLE_MAX_SLOPE = 16.0
TABLE_INTERVALS = 2048
_TABLE_STEP = TABLE_MAX_SLOPE / TABLE_INTERVALS
_TABLE_INV_STEP = TABLE_INTERVALS / TABLE_MAX_SLOPE


#: Layout of the ``reflectance`` array the near-light kernels take.
REFLECTANCE_A, REFLECTANCE_B = 0, 1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _log_radiance_direct(f: float, reflectance: np.ndarray) -> tuple[float, float]:
    """g(F) = ½·ln(R(c)/A), c = 1/√(1+F²), and g'(F) = −½·R'(c)/R·F·c³.

    R(c) = A·c + B·(1 − c²) with reflectance = (A, B). g(0) = 0, so that a
    node's v(F) = g(F) + v* with v* = ½·ln(A/I) its singular value.
    """
    coef_a = reflectance[REFLECTANCE_A]
    coef_b = reflectance[REFLECTANCE_B]
    c = 1.0 / np.sqrt(1.0 + f * f)
    radiance = coef_a * c + coef_b * (1.0 - c * c)
    slope = coef_a - 2.0 * coef_b * c
    return 0.5 * np.log(radiance / coef_a), -0.5 * slope / radiance * f * c * c * c


@njit(cache=True, nogil=True, error_model="numpy")
def log_radiance_table(reflectance: np.ndarray) -> np.ndarray:
    """(TABLE_INTERVALS + 1, 4) float64: per interval k the cubic of g in t = F/step − k.

    Row k holds (c0, c1, c2, c3) with g(F) = c0 + t·(c1 + t·(c2 + t·c3)) on
    [F_k, F_k+1], F_k = k·step: the cubic Hermite interpolant of g and
    g'·step at both ends (the last row, for F = TABLE_MAX_SLOPE, is the
    constant g there). In power form a lookup is two Horner chains (value and
    slope) instead of the Hermite basis.
    """
    ends = np.empty((TABLE_INTERVALS + 1, 2))
    for k in range(TABLE_INTERVALS + 1):
        g, dg = _log_radiance_direct(k * _TABLE_STEP, reflectance)
        ends[k, 0] = g
        ends[k, 1] = dg * _TABLE_STEP
    table = np.zeros((TABLE_INTERVALS + 1, 4))
    for k in range(TABLE_INTERVALS):
        g0, d0, g1, d1 = ends[k, 0], ends[k, 1], ends[k + 1, 0], ends[k + 1, 1]
        table[k, 0] = g0
        table[k, 1] = d0
        table[k, 2] = 3.0 * (g1 - g0) - 2.0 * d0 - d1
        table[k, 3] = 2.0 * (g0 - g1) + d0 + d1
    table[TABLE_INTERVALS, 0] = ends[TABLE_INTERVALS, 0]
    return table


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _log_radiance(f: float, table: np.ndarray, reflectance: np.ndarray) -> tuple[float, float]:
    """g(F) and g'(F) from the table (cubic Hermite), directly beyond its range."""
    x = f * _TABLE_INV_STEP
    if not x < TABLE_INTERVALS:
        return _log_radiance_direct(f, reflectance)
    k = int(x)
    t = x - k
    c1 = table[k, 1]
    c2 = table[k, 2]
    c3 = table[k, 3]
    value = table[k, 0] + t * (c1 + t * (c2 + t * c3))
    slope = c1 + t * (2.0 * c2 + 3.0 * t * c3)
    return value, slope * _TABLE_INV_STEP


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def near_light_update(
    a: float,
    b: float,
    wa: float,
    wb: float,
    sa: float,
    sb: float,
    lam: float,
    v_star: float,
    reflectance: np.ndarray,
    f_guess: float,
    v_guess: float,
    dv_guess: float,
    table: np.ndarray,
) -> tuple[float, float, float]:
    """Per-node solve of the near-light Godunov equation for v = ln r.

    Finds v with

        wa·((v−a)⁺)² + wb·((v−b)⁺)² = λ²·F², F = tan θ,

    (sa = √wa, sb = √wb, passed in so that a one-sided update needs no square
    root),
    where θ is the angle whose co-located reflectance matches the data,
    R(cos θ) = I·e^{2v} (Lambertian: cos θ = I·e^{2v}). The left side grows
    with v and F falls, so the root is unique on (min(a, b), v*], with
    v* = ½·ln(A/I) the value at which the node would face the camera
    (F = 0). When v* ≤ min(a, b) the node is a singular point (a local
    minimum of distance) and v = v*.

    The unknown is F itself: v(F) = g(F) + v*, g(F) = ½·ln(R(1/√(1+F²))/A),
    is smooth down to F = 0, where v(·) has the square-root singularity that
    slows Newton on v. Safeguarded Newton on q(F) = λF − √(left side),
    seeded with ``f_guess`` (the node's previous F, or the last frame's); v(F)
    comes from ``table`` (:func:`log_radiance_table` of the same
    ``reflectance``, (A, B) of R(c) = A·c + B·(1 − c²)). When ``dv_guess``
    < 0, (``v_guess``, ``dv_guess``) are v and v' at ``f_guess`` already (the
    node's own last solve returned them), and the first Newton step takes
    them instead of a table lookup: a re-solve after a neighbour changed
    then costs one lookup less. Newton stops once the residual guarantees
    |F − F*| < 1e-3·(1 + F) (``_NEWTON_RESIDUAL_TOL``) and takes one more
    Newton step, evaluated to first order. Returns (v, F, v'(F)), the last
    < 0 only when v came from a table lookup and that one first-order step
    (so that the error of v that a next solve starts from stays ~1e-6),
    else 0.
    """
    m = a if a < b else b
    if v_star <= m:
        return v_star, 0.0, 0.0
    f_lo = 0.0
    f_hi = np.inf
    f = f_guess
    known = dv_guess < 0.0 and f > 0.0
    if not f > 0.0:
        # Small-slope start: v ≈ v* − κ·F² with κ = R'(1)/(4·R(1)), using the
        # larger one-sided term alone.
        coef_a = reflectance[REFLECTANCE_A]
        coef_b = reflectance[REFLECTANCE_B]
        kappa = (coef_a - 2.0 * coef_b) / (4.0 * coef_a)
        w = wa if (v_star - a) * (v_star - a) * wa >= (v_star - b) * (v_star - b) * wb else wb
        f = (-lam + np.sqrt(lam * lam + 4.0 * w * kappa * (v_star - m))) / (
            2.0 * np.sqrt(w) * kappa
        )
    looked_up = False
    for _ in range(_NEWTON_MAX_STEPS):
        if known:
            v = v_guess
            dv_df = dv_guess
            known = False
        else:
            g, dv_df = _log_radiance(f, table, reflectance)
            v = g + v_star
            looked_up = True
        da = v - a
        db = v - b
        # √(left side) and its derivative in v; one-sided without a root.
        # The Newton step q / (λ − √L'·v') is taken as numerator over
        # denominator, both multiplied by √L in the two-sided case
        # (√L' = P/√L, P = wa·da + wb·db): one division after the square
        # root instead of two in a row, on the step's critical path.
        if da > 0.0 and db > 0.0:
            root = np.sqrt(wa * da * da + wb * db * db)
            q = lam * f - root
            numerator = q * root
            denominator = lam * root - (wa * da + wb * db) * dv_df
        elif da > 0.0:
            root = sa * da
            q = lam * f - root
            numerator = q
            denominator = lam - sa * dv_df
        elif db > 0.0:
            root = sb * db
            q = lam * f - root
            numerator = q
            denominator = lam - sb * dv_df
        else:
            q = lam * f
            numerator = q
            denominator = lam
        if q > 0.0:
            f_hi = f
        elif q < 0.0:
            f_lo = f
        else:
            return v, f, dv_df if looked_up else 0.0
        f_new = f - numerator / denominator
        # q rises with slope ≥ λ, so |F − F*| ≤ |q|/λ: a guaranteed bound (a
        # step-size test can stop on the wrong side of the kink of √L).
        if abs(q) < lam * _NEWTON_RESIDUAL_TOL * (1.0 + f):
            if f_new > f_lo and f_new < f_hi:
                # The last step is below 1e-3·(1 + F): v(F) to first order
                # (error ~ ½g''·step², under 1e-6) instead of another lookup.
                return v + dv_df * (f_new - f), f_new, dv_df if looked_up else 0.0
            return v, f, dv_df if looked_up else 0.0
        if not (f_new > f_lo and f_new < f_hi):
            f_new = 0.5 * (f_lo + f_hi) if f_hi < np.inf else 2.0 * f + 1.0
        f = f_new
    g, dv_df = _log_radiance(f, table, reflectance)
    return g + v_star, f, dv_df


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def weno_neighbour(u: np.ndarray, i: int, j: int, di: int, dj: int, eps: float) -> float:
    """Third-order WENO stand-in for the upwind neighbour along one axis.

    Returns min(u0 − h·D⁻u, u0 + h·D⁺u) with D± the WENO3 one-sided
    derivatives (Jiang & Peng 2000) as used by Zhang, Zhao & Qian (2006);
    (di, dj) is the axis unit step (h cancels). A side whose stencil reaches an
    invalid (+inf) node falls back to the first-order neighbour.
    """
    um1 = u[i - di, j - dj]
    up1 = u[i + di, j + dj]
    first_order = um1 if um1 < up1 else up1
    um2 = u[i - 2 * di, j - 2 * dj]
    up2 = u[i + 2 * di, j + 2 * dj]
    u0 = u[i, j]
    if um2 == np.inf or um1 == np.inf or u0 == np.inf or up1 == np.inf or up2 == np.inf:
        # Mixing a high-order side with a first-order side next to the mask
        # edge sets up a two-node limit cycle; the whole axis drops to first
        # order instead.
        return first_order
    central = up1 - 2.0 * u0 + um1
    den = eps + central * central
    back = u0 - 2.0 * um1 + um2
    r = (eps + back * back) / den
    w = 1.0 / (1.0 + 2.0 * r * r)
    a_minus = u0 - 0.5 * ((1.0 - w) * (up1 - um1) + w * (3.0 * u0 - 4.0 * um1 + um2))
    fwd = u0 - 2.0 * up1 + up2
    r = (eps + fwd * fwd) / den
    w = 1.0 / (1.0 + 2.0 * r * r)
    a_plus = u0 + 0.5 * ((1.0 - w) * (up1 - um1) + w * (-3.0 * u0 + 4.0 * up1 - up2))
    return a_minus if a_minus < a_plus else a_plus


# --------------------------------------------------------------------------
# Sweeping drivers
# --------------------------------------------------------------------------


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def second_order_neighbour(
    u: np.ndarray, i: int, j: int, di: int, dj: int, h: float, w: float
) -> tuple[float, float, float]:
    """Upwind neighbour value, effective spacing and 1/spacing² along one axis.

    Uses the one-sided second-order difference (3u0 − 4u₋₁ + u₋₂)/2h on the
    upwind side when its second node is not higher than its first (as in
    second-order fast marching), i.e. the neighbour (4u₋₁ − u₋₂)/3 at spacing
    2h/3; otherwise the first-order neighbour at spacing h (w = 1/h²).
    """
    um1 = u[i - di, j - dj]
    up1 = u[i + di, j + dj]
    if um1 <= up1:
        n1 = um1
        n2 = u[i - 2 * di, j - 2 * dj]
    else:
        n1 = up1
        n2 = u[i + 2 * di, j + 2 * dj]
    if n2 <= n1 and n1 != np.inf:
        return (4.0 * n1 - n2) * (1.0 / 3.0), h * (2.0 / 3.0), w * 2.25
    return n1, h, w


#: Node states of the sweeping kernels (one uint8 grid instead of separate
#: "active" and "locked" masks, so that a visit reads one cache line less).
OUTSIDE, LOCKED, UNLOCKED = 0, 1, 2
#: FRESH + s (s = 0…3): not solved yet this frame, first solved in sweep s
#: of the first iteration, the sweep whose direction meets the node's
#: predicted upwind neighbours first (:func:`mark_first_sweeps`).
FRESH = 3


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def mark_first_sweeps(state: np.ndarray, key: np.ndarray) -> None:
    """Mark each unlocked node FRESH + s, s the sweep that first solves it.

    state: (ny+4, nx+4) uint8 (:func:`initial_state`), changed in place;
    key: (ny+4, nx+4) float64 the predicted values (the previous frame's v +
    shift, +inf outside). From a start at v*, a node solved in a sweep that
    runs against its upwind neighbours sees them still at v* and is solved
    again once they fall; so each node is first solved in the sweep (of the
    four of :func:`_sweeps`: (+i, +j), (+i, −j), (−i, −j), (−i, +j)) that
    visits its lower neighbour along each axis (by ``key``) before it; an
    axis with no lower neighbour takes either direction.
    """
    ny, nx = state.shape
    for i in prange(2, ny - 2):
        for j in range(2, nx - 2):
            if state[i, j] != UNLOCKED:
                continue
            centre = key[i, j]
            left = key[i, j - 1]
            right = key[i, j + 1]
            up = key[i - 1, j]
            down = key[i + 1, j]
            # dj: +1 when the lower x-neighbour is on the left, −1 on the
            # right, 0 when neither is below the node (di likewise).
            dj = 0
            if min(left, right) < centre:
                dj = 1 if left <= right else -1
            di = 0
            if min(up, down) < centre:
                di = 1 if up <= down else -1
            if di >= 0:
                state[i, j] = FRESH + (1 if dj < 0 else 0)
            else:
                state[i, j] = FRESH + (3 if dj > 0 else 2)


@njit(cache=True, nogil=True, error_model="numpy")
def initial_state(active: np.ndarray) -> np.ndarray:
    """uint8 state grid: UNLOCKED where ``active`` (uint8 or bool), OUTSIDE elsewhere."""
    ny, nx = active.shape
    state = np.zeros((ny, nx), dtype=np.uint8)
    for i in range(ny):
        for j in range(nx):
            if active[i, j]:
                state[i, j] = UNLOCKED
    return state


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _unlock_stencil(
    state: np.ndarray,
    u: np.ndarray,
    i: int,
    j: int,
    reach: int,
    lowest: float,
    causal: bool,
) -> None:
    """Unlock the nodes whose stencil contains (i, j) after it changed.

    With a causal (upwind-only) update a node can only use a neighbour lower
    than itself, so only nodes above ``lowest`` (the smaller of the changed
    node's old and new values) need recomputing.
    """
    for k in range(1, reach + 1):
        for ni, nj in ((i - k, j), (i + k, j), (i, j - k), (i, j + k)):
            if state[ni, nj] == LOCKED and (not causal or u[ni, nj] > lowest):
                state[ni, nj] = UNLOCKED


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _unlock_dependents(
    state: np.ndarray, v: np.ndarray, i: int, j: int, order: int, lowest: float
) -> None:
    """Unlock the locked nodes whose upwind stencil reads (i, j), after it changed.

    Causal schemes (orders 1 and 2) only; ``lowest`` is the smaller of the
    changed node's old and new values. A node n reads (i, j) only through
    the upwind choices of :func:`second_order_neighbour` (or the first-order
    minimum): as its nearer neighbour n1 along an axis when (i, j) is not
    above the opposite neighbour, and, for order 2, as its second node n2
    when the node between them is n1 (not above the opposite one) and
    (i, j) is not above it. Only such nodes, and only when n lies above
    ``lowest`` (a causal node uses lower neighbours only), are unlocked;
    the ties count as reads. If a later change makes (i, j) part of n's
    stencil after all, that change unlocks n (it reads the node that
    changed), so no dependency is lost: the same fixed point, with fewer
    idle re-solves than unlocking the whole stencil reach.
    """
    for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ni = i + di
        nj = j + dj
        near = v[ni, nj]
        if state[ni, nj] == LOCKED and near > lowest and lowest <= v[ni + di, nj + dj]:
            state[ni, nj] = UNLOCKED
        if order == 2 and near != np.inf and lowest <= near:
            fi = ni + di
            fj = nj + dj
            if state[fi, fj] == LOCKED and v[fi, fj] > lowest and near <= v[fi + di, fj + dj]:
                state[fi, fj] = UNLOCKED


@njit(cache=True, nogil=True, error_model="numpy")
def eikonal_sweep(
    t: np.ndarray,
    speed: np.ndarray,
    fixed: np.ndarray,
    valid: np.ndarray,
    hx: float,
    hy: float,
    order: int,
    tolerance: float,
    max_iterations: int,
    eps: float,
) -> tuple[int, float, int]:
    """Fast sweeping for |∇T| = f on a padded grid, in place.

    t: (ny+4, nx+4) float64, +inf at invalid nodes, source values at fixed
    nodes, an upper bound (e.g. +inf) elsewhere. speed: (ny+4, nx+4) float64
    the right-hand side f ≥ 0. fixed, valid: uint8 masks of the same shape.
    order 1: first-order Godunov, T ← min(T, update) (Zhao 2005).
    order 2: second-order one-sided upwind differences, T ← min(T, update).
    order 3: WENO3 Godunov, T ← update (Zhang, Zhao & Qian 2006); start it
    from the first-order solution. Returns (iterations, last max change,
    node updates computed).
    """
    ny, nx = t.shape
    active = np.zeros((ny, nx), dtype=np.uint8)
    for i in range(2, ny - 2):
        for j in range(2, nx - 2):
            if valid[i, j] and not fixed[i, j]:
                active[i, j] = 1
    state = initial_state(active)
    reach = 1 if order == 1 else 2
    replace = order == 3
    wx = 1.0 / (hx * hx)
    wy = 1.0 / (hy * hy)
    change = np.inf
    iterations = 0
    updates = 0
    for _ in range(max_iterations):
        iterations += 1
        change = 0.0
        for sweep in range(4):
            di = 1 if sweep < 2 else -1
            dj = 1 if (sweep == 0 or sweep == 3) else -1
            i0 = 2 if di > 0 else ny - 3
            j0 = 2 if dj > 0 else nx - 3
            for ii in range(ny - 4):
                i = i0 + di * ii
                for jj in range(nx - 4):
                    j = j0 + dj * jj
                    if state[i, j] != UNLOCKED:
                        continue
                    state[i, j] = LOCKED
                    updates += 1
                    if order == 1:
                        a = min(t[i, j - 1], t[i, j + 1])
                        b = min(t[i - 1, j], t[i + 1, j])
                        new = godunov_eikonal_update(a, hx, wx, b, hy, wy, speed[i, j])
                    elif order == 2:
                        a, ha, wa = second_order_neighbour(t, i, j, 0, 1, hx, wx)
                        b, hb, wb = second_order_neighbour(t, i, j, 1, 0, hy, wy)
                        new = godunov_eikonal_update(a, ha, wa, b, hb, wb, speed[i, j])
                    else:
                        a = weno_neighbour(t, i, j, 0, 1, eps)
                        b = weno_neighbour(t, i, j, 1, 0, eps)
                        new = godunov_eikonal_update(a, hx, wx, b, hy, wy, speed[i, j])
                        # Away from the sources the solution has no local
                        # minimum; where F ≈ 0 (a singular line) the WENO
                        # extrapolation would otherwise drift downwards.
                        floor = min(
                            min(t[i, j - 1], t[i, j + 1]), min(t[i - 1, j], t[i + 1, j])
                        )
                        if new < floor:
                            new = floor
                    old = t[i, j]
                    if new == np.inf or (not replace and new >= old):
                        continue
                    diff = abs(new - old) if old != np.inf else np.inf
                    t[i, j] = new
                    if diff > tolerance:
                        _unlock_stencil(state, t, i, j, reach, new, not replace)
                        if replace:
                            state[i, j] = UNLOCKED
                    if diff > change:
                        change = diff
        if change <= tolerance:
            break
    return iterations, change, updates


#: Node solves of the heap repair after the first pass, at most, per node
#: (the sweeps take over beyond it).
REPAIR_BUDGET = 4.0
#: While more than this share of the nodes is unlocked after the first
#: pass, repair rounds are whole passes in value order (at most
#: REPAIR_ROUNDS, bucketed as the first pass with FIRST_PASS_BUCKETS).
HEAP_REPAIR_SHARE = 0.05
REPAIR_ROUNDS = 6


@njit(cache=True, nogil=True, error_model="numpy")
def _count_unlocked(state: np.ndarray) -> int:
    count = 0
    for i in range(state.shape[0]):
        for j in range(state.shape[1]):
            if state[i, j] == UNLOCKED:
                count += 1
    return count

#: Layout of the last axis of the per-node data of :func:`near_light_sweep`.
#: NODE_SEED_SLOPE: v'(F) at the seed F when the node's last solve left v and
#: F consistent (< 0), else 0 (see :func:`near_light_update`).
NODE_SEED_SLOPE, NODE_LAMBDA, NODE_V_STAR, NODE_SEED = 0, 1, 2, 3


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _near_light_node(
    v: np.ndarray,
    node: np.ndarray,
    i: int,
    j: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    eps: float,
    table: np.ndarray,
) -> float:
    """Solve node (i, j) from its current neighbours, store v and F; returns |change|.

    node: (ny+4, nx+4, 4) float64 per-node data (v'(F) at the seed, λ, v*,
    F seed), kept together so that a node's data share a cache line.
    """
    sx = 1.0 / hx
    sy = 1.0 / hy
    wx = sx * sx
    wy = sy * sy
    if order == 1:
        a = min(v[i, j - 1], v[i, j + 1])
        b = min(v[i - 1, j], v[i + 1, j])
        wa = wx
        wb = wy
        sa = sx
        sb = sy
    elif order == 2:
        a, _, wa = second_order_neighbour(v, i, j, 0, 1, hx, wx)
        b, _, wb = second_order_neighbour(v, i, j, 1, 0, hy, wy)
        sa = sx * 1.5 if wa > wx else sx
        sb = sy * 1.5 if wb > wy else sy
    else:
        a = weno_neighbour(v, i, j, 0, 1, eps)
        b = weno_neighbour(v, i, j, 1, 0, eps)
        wa = wx
        wb = wy
        sa = sx
        sb = sy
    old = v[i, j]
    new, node[i, j, NODE_SEED], node[i, j, NODE_SEED_SLOPE] = near_light_update(
        a, b, wa, wb, sa, sb, node[i, j, NODE_LAMBDA], node[i, j, NODE_V_STAR], reflectance,
        node[i, j, NODE_SEED], old, node[i, j, NODE_SEED_SLOPE], table,
    )
    v[i, j] = new
    return abs(new - old)



@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _near_light_node_called(
    v: np.ndarray,
    node: np.ndarray,
    i: int,
    j: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    eps: float,
    table: np.ndarray,
) -> float:
    """:func:`_near_light_node` as a function of its own, for any order.

    The loops of orders 1 and 3 call it (see :func:`_sweeps`): one compiled
    node solve for all of them instead of one inlined copy per loop and
    order. Compiled without reference counting, as its callers.
    """
    return _near_light_node(v, node, i, j, hx, hy, reflectance, order, eps, table)

#: Visits ahead whose stencil the ordered passes prefetch (value order jumps
#: across the grid; ~100 ns of memory latency against ~100 ns per visit).
PREFETCH_AHEAD = 4


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _prefetch_stencil(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, flat: int, nx: int
) -> None:
    """Prefetch the rows i−2…i+2 of v and state around flat node index i·nx + j, and its data."""
    for row in range(-2, 3):
        prefetch(v, flat + row * nx)
    prefetch(state, flat - 2 * nx)
    prefetch(state, flat + 2 * nx)
    prefetch(node, flat * node.shape[2])


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _ordered_pass_body(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    ordered: np.ndarray,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    eps: float,
    table: np.ndarray,
    solve_node: Callable[..., float],
) -> int:
    """Solve each unlocked node of ``ordered`` (flat indices) once, in that order.

    A node whose value changes by more than ``tolerance`` unlocks the nodes
    whose stencil holds it (:func:`_unlock_stencil`). Returns the number of
    node solves.
    """
    nx = v.shape[1]
    reach = 1 if order == 1 else 2
    causal = order != 3
    updates = 0
    for k in range(ordered.size):
        if k + PREFETCH_AHEAD < ordered.size:
            _prefetch_stencil(v, node, state, ordered[k + PREFETCH_AHEAD], nx)
        i = ordered[k] // nx
        j = ordered[k] - i * nx
        if state[i, j] != UNLOCKED:
            continue
        state[i, j] = LOCKED
        updates += 1
        old = v[i, j]
        diff = solve_node(v, node, i, j, hx, hy, reflectance, order, eps, table)
        if diff > tolerance:
            if causal:
                _unlock_dependents(state, v, i, j, order, min(v[i, j], old))
            else:
                _unlock_stencil(state, v, i, j, reach, min(v[i, j], old), causal)
    return updates


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _ordered_pass_any(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, ordered: np.ndarray, hx: float,
    hy: float, reflectance: np.ndarray, order: int, tolerance: float, eps: float, table: np.ndarray,
) -> int:
    """:func:`_ordered_pass_body` for orders 1 and 3 (not inlined, see :func:`_ordered_pass`)."""
    return _ordered_pass_body(v, node, state, ordered, hx, hy, reflectance, order, tolerance, eps,
                              table, _near_light_node_called)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _ordered_pass_order2(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, ordered: np.ndarray, hx: float,
    hy: float, reflectance: np.ndarray, tolerance: float, eps: float, table: np.ndarray,
) -> int:
    """:func:`_ordered_pass_body` for order 2."""
    return _ordered_pass_body(v, node, state, ordered, hx, hy, reflectance, 2, tolerance, eps,
                              table, _near_light_node)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _ordered_pass(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    ordered: np.ndarray,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    eps: float,
    table: np.ndarray,
) -> int:
    """:func:`_ordered_pass_body` (see there for the arguments); see :func:`_sweeps`."""
    if order != 2:
        return _ordered_pass_any(v, node, state, ordered, hx, hy, reflectance, order, tolerance,
                                    eps, table)
    return _ordered_pass_order2(v, node, state, ordered, hx, hy, reflectance, tolerance, eps,
                                table)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST)
def _repair(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    eps: float,
    table: np.ndarray,
    budget: int,
) -> int:
    """Solve the unlocked nodes in increasing order of their current value, with a heap.

    A node solved before one of its upwind neighbours was final is unlocked
    when that neighbour changes; taking the unlocked nodes lowest first
    (and the ones they unlock in turn) repairs such a misordering in about
    one solve per affected node. Stops after ``budget`` solves, leaving any
    unlocked rest to the sweeps. Causal orders (1, 2) only. Returns the
    number of node solves.
    """
    ny, nx = v.shape
    count = 0
    for i in range(ny):
        for j in range(nx):
            if state[i, j] == UNLOCKED:
                count += 1
    capacity = 2 * count + 64
    keys = np.empty(capacity)
    items = np.empty(capacity, dtype=np.int64)
    size = 0
    for i in range(ny):
        for j in range(nx):
            if state[i, j] == UNLOCKED:
                size = heap_push(keys, items, size, v[i, j], i * nx + j)
    solves = 0
    while True:
        size, solves, full = _repair_steps(
            v, node, state, keys, items, size, solves, budget, hx, hy, reflectance, order,
            tolerance, eps, table,
        )
        if not full:
            return solves
        keys = np.concatenate((keys, np.empty(keys.size)))
        items = np.concatenate((items, np.empty(items.size, dtype=np.int64)))


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _repair_steps_body(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    keys: np.ndarray,
    items: np.ndarray,
    size: int,
    solves: int,
    budget: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    eps: float,
    table: np.ndarray,
    solve_node: Callable[..., float],
) -> tuple[int, int, bool]:
    """The heap loop of :func:`_repair` until done or the heap might overflow.

    Compiled without numba's reference counting (nothing here allocates), so
    the hot loop makes no atomic reference-count calls per node. Returns
    (heap size, solves so far, True if it stopped because a node's unlocks
    might not fit: the caller grows the heap and calls again).
    """
    nx = v.shape[1]
    reach = 1 if order == 1 else 2
    while size > 0 and solves < budget:
        if keys.size - size < 4 * reach:
            return size, solves, True
        flat, size = heap_pop(keys, items, size)
        i = flat // nx
        j = flat - i * nx
        if state[i, j] != UNLOCKED:
            continue
        state[i, j] = LOCKED
        solves += 1
        old = v[i, j]
        diff = solve_node(v, node, i, j, hx, hy, reflectance, order, eps, table)
        if diff <= tolerance:
            continue
        lowest = min(v[i, j], old)
        for k in range(1, reach + 1):
            for ni, nj in ((i - k, j), (i + k, j), (i, j - k), (i, j + k)):
                if state[ni, nj] == LOCKED and v[ni, nj] > lowest:
                    state[ni, nj] = UNLOCKED
                    size = heap_push(keys, items, size, v[ni, nj], ni * nx + nj)
    return size, solves, False


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _repair_steps_any(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, keys: np.ndarray, items: np.ndarray,
    size: int, solves: int, budget: int, hx: float, hy: float, reflectance: np.ndarray, order: int,
    tolerance: float, eps: float, table: np.ndarray,
) -> tuple[int, int, bool]:
    """:func:`_repair_steps_body` for orders 1 and 3 (not inlined, see :func:`_repair_steps`)."""
    return _repair_steps_body(v, node, state, keys, items, size, solves, budget, hx, hy,
                              reflectance, order, tolerance, eps, table, _near_light_node_called)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _repair_steps_order2(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, keys: np.ndarray, items: np.ndarray,
    size: int, solves: int, budget: int, hx: float, hy: float, reflectance: np.ndarray,
    tolerance: float, eps: float, table: np.ndarray,
) -> tuple[int, int, bool]:
    """:func:`_repair_steps_body` for order 2."""
    return _repair_steps_body(v, node, state, keys, items, size, solves, budget, hx, hy,
                              reflectance, 2, tolerance, eps, table, _near_light_node)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _repair_steps(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    keys: np.ndarray,
    items: np.ndarray,
    size: int,
    solves: int,
    budget: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    eps: float,
    table: np.ndarray,
) -> tuple[int, int, bool]:
    """:func:`_repair_steps_body` (see there for the arguments); see :func:`_sweeps`."""
    if order != 2:
        return _repair_steps_any(v, node, state, keys, items, size, solves, budget, hx, hy,
                                 reflectance, order, tolerance, eps, table)
    return _repair_steps_order2(v, node, state, keys, items, size, solves, budget, hx, hy,
                                reflectance, tolerance, eps, table)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, parallel=True)
def _parallel_pass(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    ordered: np.ndarray,
    split: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    eps: float,
    table: np.ndarray,
) -> int:
    """:func:`_ordered_pass` of ordered[:split] and ordered[split:] on two threads.

    The two lists cover disjoint regions; the only shared writes are unlocks
    along their seam (which the caller repeats) and each thread reads the
    other's values there as they are (8-byte stores do not tear on the
    targets numba supports).
    """
    counts = np.zeros(2, dtype=np.int64)
    for half in prange(2):
        part = ordered[:split] if half == 0 else ordered[split:]
        counts[half] = _ordered_pass(
            v, node, state, part, hx, hy, reflectance, order, tolerance, eps, table
        )
    return counts[0] + counts[1]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST)
def near_light_sweep(
    v: np.ndarray,
    node: np.ndarray,
    valid: np.ndarray,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    max_iterations: int,
    eps: float,
    table: np.ndarray,
    first_pass: np.ndarray,
    split: int,
    seam: np.ndarray,
    sweep_split: int,
    first_sweeps: np.ndarray,
    ticks: np.ndarray,
) -> tuple[int, float, int]:
    """Fast sweeping of the near-light perspective SFS equation, in place.

    v: (ny+4, nx+4) float64 log-distance ln r, +inf at invalid nodes, the
    start values elsewhere (v*, see :func:`near_light_inputs`).
    node: (ny+4, nx+4, 4) float64 per-node ln I, conformal factor λ,
    singular value v* = ½·ln(A/I), and the F = tan θ seeding the node's
    next Newton solve (overwritten with each new F; ≤ 0 means none), in the
    layout ``NODE_*``; seeding F from the previous frame
    starts each solve near its root.
    order: 1 (first-order Godunov), 2 (:func:`second_order_neighbour`) or 3
    (:func:`weno_neighbour`). reflectance: (A, B) of the co-located
    R(c) = A·c + B·(1 − c²); table: its :func:`log_radiance_table`. The node update
    replaces the value (the scheme is monotone in its neighbours and strictly
    increasing in v through e^{2v}, so any start converges).

    first_pass: (n,) int64 flat indices into the padded grid, or empty. When
    given, every node is first solved once in this order (the causal schemes
    are exact in one pass when a node's upwind neighbours come before it,
    i.e. in increasing order of the solution, as in fast marching; see
    :func:`value_order`); the nodes this leaves unlocked (solved before an
    upwind neighbour was final) are repaired lowest first (:func:`_repair`),
    and the sweeps then only revisit nodes whose stencil changed by more
    than the tolerance since.

    split > 0: first_pass[:split] and first_pass[split:] are two regions of
    the grid (each in its own value order) whose first passes run on two
    threads at once; seam: (m,) int64 flat indices of the nodes within the
    stencil reach of the boundary between them, solved again afterwards
    (see :func:`split_first_pass`). The result is the same fixed point, up to
    the tolerance.

    sweep_split > 0: the sweeps first run on two threads, padded rows
    [2, sweep_split) and [sweep_split, ny − 2) each until it settles, then
    on one thread over the whole grid (nodes within the stencil reach of
    the seam unlocked again first).

    first_sweeps: (ny+4, nx+4) float64 predicted values (+inf outside), or
    empty. When given and there is no first pass (causal orders), each node
    is first solved in the sweep that visits its predicted lower neighbours
    before it (:func:`mark_first_sweeps`) rather than in the first sweep
    that reaches it: the same fixed point (to the tolerance), fewer solves
    against neighbours still at their start values.

    ticks: (3,) int64, or empty. When given, receives the cycle counter
    (:func:`endo_sfs.cycles.cycle_counter`) at the start, at the start of
    the one-thread finish after a two-thread first pass or split sweeps
    (the end when there was none), and at the end, so that the caller can
    split the kernel's wall time.
    Returns (iterations, last max change of v, node updates computed).
    """
    timed = ticks.size >= 3
    if timed:
        ticks[0] = cycle_counter()
        ticks[1] = -1
    ny, nx = v.shape
    state = initial_state(valid)  # the padding of ``valid`` is 0: OUTSIDE
    if first_pass.size == 0 and first_sweeps.size > 0 and order != 3:
        mark_first_sweeps(state, first_sweeps)
    reach = 1 if order == 1 else 2
    updates = 0
    if first_pass.size > 0:
        if split > 0:
            updates += _parallel_pass(
                v, node, state, first_pass, split, hx, hy, reflectance, order, tolerance, eps,
                table,
            )
            # The two halves unlock each other's nodes along the seam without
            # synchronisation, so an unlock may be lost there: solve every
            # node near the seam once more.
            for k in range(seam.size):
                i = seam[k] // nx
                j = seam[k] - i * nx
                if state[i, j] == LOCKED:
                    state[i, j] = UNLOCKED
            if timed:
                ticks[1] = cycle_counter()
        else:
            updates += _ordered_pass(
                v, node, state, first_pass, hx, hy, reflectance, order, tolerance, eps, table
            )
        # Nodes solved before an upwind neighbour was final are unlocked
        # again; repair them in increasing order of their current values
        # (nearly the solution's), so a misordering does not cascade
        # through the sweeps. While many are unlocked, whole passes in value
        # order (prefetched, O(N)) are cheaper than a heap (O(log N) and a
        # cache miss per node); the heap then finishes the few left.
        for _ in range(REPAIR_ROUNDS):
            if _count_unlocked(state) <= HEAP_REPAIR_SHARE * first_pass.size:
                break
            updates += _ordered_pass(
                v, node, state, value_order(v, valid, FIRST_PASS_BUCKETS), hx, hy,
                reflectance, order, tolerance, eps, table,
            )
        updates += _repair(
            v, node, state, hx, hy, reflectance, order, tolerance, eps, table,
            int(REPAIR_BUDGET * first_pass.size),
        )
        if _count_unlocked(state) == 0:
            # Every node is consistent with its final stencil: a sweep
            # would only confirm it.
            if timed:
                _end_ticks(ticks)
            return 0, 0.0, updates
    spans = row_spans(valid)
    dirty = np.zeros(ny, dtype=np.uint8)
    if sweep_split > 0:
        # Each half sweeps its own rows on its own thread until it settles;
        # the halves unlock each other's nodes along the seam without
        # synchronisation, so every node there is unlocked again and the
        # sweeps below finish on one thread.
        updates += _parallel_sweeps(
            v, node, state, spans, dirty, sweep_split, hx, hy, reflectance, order, tolerance,
            max_iterations, eps, table,
        )
        for i in range(max(2, sweep_split - reach), min(ny - 2, sweep_split + reach)):
            for j in range(2, nx - 2):
                if state[i, j] == LOCKED:
                    state[i, j] = UNLOCKED
        if timed:
            ticks[1] = cycle_counter()
    iterations, change, more = _sweeps(
        v, node, state, spans, dirty, 2, ny - 2, hx, hy, reflectance, order, tolerance,
        max_iterations, eps, table,
    )
    if timed:
        _end_ticks(ticks)
    return iterations, change, updates + more


@njit(cache=True, nogil=True, error_model="numpy")
def _end_ticks(ticks: np.ndarray) -> None:
    """The end read of :func:`near_light_sweep`'s ``ticks`` (finish start = end if unset)."""
    ticks[2] = cycle_counter()
    if ticks[1] < 0:
        ticks[1] = ticks[2]


@njit(cache=True, nogil=True, error_model="numpy")
def row_spans(valid: np.ndarray) -> np.ndarray:
    """Per row of ``valid`` ((ny, nx) uint8), the columns [begin, end) of its nonzero entries.

    Returns (ny, 2) int64, (0, 0) for a row with none.
    """
    ny, nx = valid.shape
    spans = np.zeros((ny, 2), dtype=np.int64)
    for i in range(ny):
        begin = -1
        end = 0
        for j in range(nx):
            if valid[i, j]:
                if begin < 0:
                    begin = j
                end = j + 1
        if begin >= 0:
            spans[i, 0] = begin
            spans[i, 1] = end
    return spans


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, inline="always")
def _sweeps_body(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    spans: np.ndarray,
    dirty: np.ndarray,
    row_begin: int,
    row_end: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    max_iterations: int,
    eps: float,
    table: np.ndarray,
    solve_node: Callable[..., float],
) -> tuple[int, float, int]:
    """Locked fast sweeping of the unlocked nodes of rows [row_begin, row_end), in place.

    Inlined into the order-2 kernel (:func:`_sweeps`) with the order a
    constant and ``solve_node`` :func:`_near_light_node` (inlined in turn), so
    that the per-node solve of the other orders is compiled out of the loop
    instead of sitting beside it in registers; the kernel of orders 1 and 3
    passes :func:`_near_light_node_called`, which it calls. ``solve_node`` is
    an argument, not a global, so that numba inlines the node solve only
    where the kernel names it (each inlining of it costs seconds of
    compilation, see :func:`_sweeps`).

    Four Gauss–Seidel sweeps per iteration with alternating orderings, until
    no node changed by more than ``tolerance`` (or ``max_iterations``).
    spans: (ny, 2) int64 per padded row, the columns [begin, end) that hold
    its valid nodes (:func:`row_spans`); dirty: (ny,) uint8 scratch, one
    flag per row. A row is scanned only while flagged: every row holding an
    unlocked node is flagged first, a row's flag is cleared as its scan
    starts and set again (with the rows within the stencil reach) whenever
    a node changes by more than the tolerance, which is when nodes are
    unlocked. Once most nodes have settled the sweeps skip the settled rows
    instead of testing every node of them, and never test the nodes outside
    the rows' spans (the field of view's corners): the same visits of the
    unlocked nodes in the same order, so the same result bit for bit.
    A node in state FRESH + s (:func:`mark_first_sweeps`) is passed over
    until sweep s (its row stays flagged), then solved as an unlocked one.
    Returns (iterations, last max change, node solves).
    """
    reach = 1 if order == 1 else 2
    causal = order != 3
    rows = row_end - row_begin
    for i in range(row_begin, row_end):
        dirty[i] = 0
        for j in range(spans[i, 0], spans[i, 1]):
            if state[i, j] >= UNLOCKED:
                dirty[i] = 1
                break
    updates = 0
    change = np.inf
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        change = 0.0
        for sweep in range(4):
            di = 1 if sweep < 2 else -1
            dj = 1 if (sweep == 0 or sweep == 3) else -1
            i0 = row_begin if di > 0 else row_end - 1
            for ii in range(rows):
                i = i0 + di * ii
                if dirty[i] == 0:
                    continue
                dirty[i] = 0
                begin = spans[i, 0]
                end = spans[i, 1]
                j0 = begin if dj > 0 else end - 1
                fresh = FRESH + sweep
                for jj in range(end - begin):
                    j = j0 + dj * jj
                    s = state[i, j]
                    if s != UNLOCKED and s != fresh:
                        if s > UNLOCKED:
                            # A fresh node of a later sweep: keep the row.
                            dirty[i] = 1
                        continue
                    state[i, j] = LOCKED
                    updates += 1
                    old = v[i, j]
                    diff = solve_node(v, node, i, j, hx, hy, reflectance, order, eps, table)
                    if diff > tolerance:
                        if causal:
                            _unlock_dependents(state, v, i, j, order, min(v[i, j], old))
                        else:
                            _unlock_stencil(state, v, i, j, reach, min(v[i, j], old), causal)
                            state[i, j] = UNLOCKED
                        for k in range(i - reach, i + reach + 1):
                            dirty[k] = 1
                    if diff > change:
                        change = diff
        if change <= tolerance:
            break
    return iterations, change, updates



@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _sweeps_any(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, spans: np.ndarray, dirty: np.ndarray,
    row_begin: int, row_end: int, hx: float, hy: float, reflectance: np.ndarray, order: int,
    tolerance: float, max_iterations: int, eps: float, table: np.ndarray,
) -> tuple[int, float, int]:
    """:func:`_sweeps_body` for orders 1 and 3 (not inlined, see :func:`_sweeps`)."""
    return _sweeps_body(v, node, state, spans, dirty, row_begin, row_end, hx, hy, reflectance,
                        order, tolerance, max_iterations, eps, table, _near_light_node_called)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _sweeps_order2(
    v: np.ndarray, node: np.ndarray, state: np.ndarray, spans: np.ndarray, dirty: np.ndarray,
    row_begin: int, row_end: int, hx: float, hy: float, reflectance: np.ndarray,
    tolerance: float, max_iterations: int, eps: float, table: np.ndarray,
) -> tuple[int, float, int]:
    """:func:`_sweeps_body` for order 2."""
    return _sweeps_body(v, node, state, spans, dirty, row_begin, row_end, hx, hy, reflectance,
                        2, tolerance, max_iterations, eps, table, _near_light_node)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, **_NO_REFCOUNTS)
def _sweeps(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    spans: np.ndarray,
    dirty: np.ndarray,
    row_begin: int,
    row_end: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    max_iterations: int,
    eps: float,
    table: np.ndarray,
) -> tuple[int, float, int]:
    """:func:`_sweeps_body` (see there for the arguments), compiled twice.

    The default order 2 has a kernel of its own with the node solve inlined
    and the order a constant, so that the other orders' neighbour choices
    are compiled out of the loop (:func:`_sweeps_order2`); orders 1 and 3
    share one kernel that calls the node solve (:func:`_near_light_node_called`,
    one compiled copy for the three loops). The same holds for
    :func:`_ordered_pass` and :func:`_repair_steps`. Most of the compile
    time was numba inlining ``inline="always"`` functions (it compiles the
    callee's IR again at every call site, with the callees it inlines in
    turn): with one kernel per order, and the node solve inlined even into
    the kernels that then dropped it, an empty kernel cache took ~150 s of
    CPU to fill (~75 s now, docs/sfs.md "Cost per frame", session 10).
    """
    if order != 2:
        return _sweeps_any(v, node, state, spans, dirty, row_begin, row_end, hx, hy,
                           reflectance, order, tolerance, max_iterations, eps, table)
    return _sweeps_order2(v, node, state, spans, dirty, row_begin, row_end, hx, hy,
                          reflectance, tolerance, max_iterations, eps, table)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST, parallel=True)
def _parallel_sweeps(
    v: np.ndarray,
    node: np.ndarray,
    state: np.ndarray,
    spans: np.ndarray,
    dirty: np.ndarray,
    split_row: int,
    hx: float,
    hy: float,
    reflectance: np.ndarray,
    order: int,
    tolerance: float,
    max_iterations: int,
    eps: float,
    table: np.ndarray,
) -> int:
    """:func:`_sweeps` of padded rows [2, split_row) and [split_row, ny − 2) on two threads.

    The halves flag each other's rows along the seam without
    synchronisation; the caller unlocks the seam again and sweeps once more.
    """
    ny = v.shape[0]
    counts = np.zeros(2, dtype=np.int64)
    for half in prange(2):
        begin = 2 if half == 0 else split_row
        end = split_row if half == 0 else ny - 2
        counts[half] = _sweeps(
            v, node, state, spans, dirty, begin, end, hx, hy, reflectance, order, tolerance,
            max_iterations, eps, table,
        )[2]
    return counts[0] + counts[1]


# --------------------------------------------------------------------------
# Inputs of the sweeps, one pass over the image
# --------------------------------------------------------------------------


@njit(cache=True, nogil=True, error_model="numpy")
def median_log_ratio(
    intensity: np.ndarray,
    valid: np.ndarray,
    previous: np.ndarray,
    previous_intensity: np.ndarray,
    stride: int,
) -> float:
    """Median of ln(I/I_prev) over every ``stride``-th node each way known in both frames.

    intensity, previous_intensity, previous: (ny, nx) float64; valid: (ny, nx)
    bool. A node counts when valid, its previous v is finite and both
    intensities are finite and positive. Returns the median (the mean of the
    two middle values for an even count; NaN when no node counts).

    The logarithm is increasing, so the middle samples of ln(I/I_prev) are
    the logarithms of the middle ratios: the ratios are selected and only
    those one or two are logged (the same value as ``np.median`` of every
    logged sample, bit for bit, at about half its cost: 0.41 against
    0.78 ms with the shift's Python on the 640×480 phantom's ~29 000
    samples).
    """
    ny, nx = intensity.shape
    out = np.empty(((ny + stride - 1) // stride) * ((nx + stride - 1) // stride))
    m = 0
    for i in range(0, ny, stride):
        for j in range(0, nx, stride):
            now = intensity[i, j]
            before = previous_intensity[i, j]
            if valid[i, j] and np.isfinite(previous[i, j]) and now > 0.0 and before > 0.0 \
                    and np.isfinite(now) and np.isfinite(before):
                out[m] = now / before
                m += 1
    if m == 0:
        return np.nan
    half = m // 2
    ratios = np.partition(out[:m], half)
    upper = np.log(ratios[half])
    if m % 2 == 1:
        return upper
    # the largest of the lower half is the other middle value
    return (np.log(np.max(ratios[:half])) + upper) / 2.0


@njit(cache=True, nogil=True, error_model="numpy")
def near_light_inputs(
    intensity: np.ndarray,
    valid: np.ndarray,
    conformal_factor_sq: np.ndarray,
    previous: np.ndarray,
    previous_slope: np.ndarray,
    shift: float,
    reflectance: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Padded start values, per-node data, validity and ordering key of :func:`near_light_sweep`.

    :func:`near_light_inputs_into` on new arrays; see there.
    Returns (v (ny+4, nx+4) float64, +inf outside; node (ny+4, nx+4, 4) in
    the ``NODE_*`` layout; valid (ny+4, nx+4) uint8; key (ny+4, nx+4)
    float64, +inf outside).
    """
    ny, nx = intensity.shape
    v = np.empty((ny + 4, nx + 4))
    key = np.empty((ny + 4, nx + 4))
    node = np.empty((ny + 4, nx + 4, 4))
    valid_p = np.empty((ny + 4, nx + 4), dtype=np.uint8)
    near_light_inputs_into(
        intensity, valid, conformal_factor_sq, previous, previous_slope, shift, reflectance,
        v, node, valid_p, key,
    )
    return v, node, valid_p, key


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def near_light_inputs_into(
    intensity: np.ndarray,
    valid: np.ndarray,
    conformal_factor_sq: np.ndarray,
    previous: np.ndarray,
    previous_slope: np.ndarray,
    shift: float,
    reflectance: np.ndarray,
    v: np.ndarray,
    node: np.ndarray,
    valid_p: np.ndarray,
    key: np.ndarray,
) -> None:
    """Fill the padded inputs of :func:`near_light_sweep` (every element, so any buffer will do).

    intensity: (ny, nx) float64 (used where ``valid``); valid: (ny, nx) bool;
    conformal_factor_sq: (ny, nx) λ². previous: (ny, nx) the previous frame's
    v (NaN where unknown), or an empty array for a cold start;
    previous_slope: (ny, nx) the previous frame's F = tan θ per node (NaN
    where unknown), or empty; shift: the frame's global change of v.
    Outputs, overwritten: v (ny+4, nx+4) float64, +inf outside; node
    (ny+4, nx+4, 4) in the ``NODE_*`` layout; valid_p (ny+4, nx+4) uint8;
    key (ny+4, nx+4) float64, +inf outside. A caller that solves frame after
    frame on one grid passes the same buffers each time (no allocation, no
    page faults on 10 MB at 640×480).

    The start is always v* = ½·ln(A/I), an upper bound of the solution, so
    that values only fall and the causal schemes stay causal, however the
    surface moved. The previous frame does not enter the start values; it
    gives the order of the first pass (its v + shift, which orders the nodes
    almost as the new solution will; v* where unknown) and each node's Newton
    seed: the node's previous F where known (the surface's slope to the ray
    changes little between frames), else the slope the data imply at
    previous + shift; 0 cold.
    """
    ny, nx = intensity.shape
    coef_a = reflectance[REFLECTANCE_A]
    coef_b = reflectance[REFLECTANCE_B]
    warm = previous.size > 0
    slopes = previous_slope.size > 0
    log_a = np.log(coef_a)
    for p in prange(ny + 4):
        i = p - 2
        for q in range(nx + 4):
            j = q - 2
            v[p, q] = np.inf
            key[p, q] = np.inf
            valid_p[p, q] = 0
            node[p, q, NODE_SEED_SLOPE] = 0.0
            node[p, q, NODE_LAMBDA] = 1.0
            node[p, q, NODE_V_STAR] = 0.0
            node[p, q, NODE_SEED] = 0.0
            if i < 0 or i >= ny or j < 0 or j >= nx:
                continue
            value = intensity[i, j]
            if not (valid[i, j] and value > 0.0 and np.isfinite(value)):
                continue
            log_i = np.log(value)
            v_star = 0.5 * (log_a - log_i)
            order_key = v_star
            seed = 0.0
            if warm:
                before = previous[i, j]
                if np.isfinite(before):
                    guess = before + shift
                    order_key = guess
                    if slopes and previous_slope[i, j] > 0.0:
                        seed = previous_slope[i, j]
                    else:
                        c = colocated_cosine_scalar(value * np.exp(2.0 * guess), coef_a, coef_b)
                        seed = np.sqrt(max(1.0 / (c * c) - 1.0, 0.0)) if c > 1e-3 else 1e3
            valid_p[p, q] = 1
            v[p, q] = v_star
            key[p, q] = order_key
            node[p, q, NODE_SEED_SLOPE] = 0.0  # v = v*: not v(seed)
            node[p, q, NODE_LAMBDA] = np.sqrt(conformal_factor_sq[i, j])
            node[p, q, NODE_V_STAR] = v_star
            node[p, q, NODE_SEED] = seed


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def near_light_outputs(
    v: np.ndarray, node: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The solution and slopes of the valid nodes from the padded grids, in one pass.

    v: (ny+4, nx+4) float64; node: (ny+4, nx+4, 4) (``NODE_SEED`` holds the
    last F); valid: (ny, nx) bool. Returns ((ny, nx) float64 v and
    (ny, nx) float64 F = tan θ, both NaN where not valid).
    """
    ny, nx = valid.shape
    log_r = np.empty((ny, nx))
    slope = np.empty((ny, nx))
    for i in prange(ny):
        for j in range(nx):
            if valid[i, j]:
                log_r[i, j] = v[i + 2, j + 2]
                slope[i, j] = node[i + 2, j + 2, NODE_SEED]
            else:
                log_r[i, j] = np.nan
                slope[i, j] = np.nan
    return log_r, slope


@njit(cache=True, nogil=True, error_model="numpy")
def orthographic_inputs(
    intensity: np.ndarray,
    valid: np.ndarray,
    coef_a: float,
    coef_b: float,
    singular_tolerance: float,
    boundary: np.ndarray,
    sign: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Padded arrays of :func:`eikonal_sweep` for the orthographic model.

    intensity: (ny, nx) float64; valid: (ny, nx) bool (nodes with a
    non-finite intensity are dropped). F = √(1/c² − 1) with c the co-located
    cosine. Sources: the finite values of ``boundary`` times ``sign`` when
    ``boundary`` is (ny, nx); otherwise (``boundary`` of size 0) the nodes
    with c ≥ max(c) − singular_tolerance, at ``sign`` × 1.
    Returns (t, speed, fixed, valid) padded by two nodes.
    """
    ny, nx = intensity.shape
    t = np.full((ny + 4, nx + 4), np.inf)
    speed = np.full((ny + 4, nx + 4), np.inf)
    fixed = np.zeros((ny + 4, nx + 4), dtype=np.uint8)
    valid_p = np.zeros((ny + 4, nx + 4), dtype=np.uint8)
    c_max = -1.0
    for i in range(ny):
        for j in range(nx):
            value = intensity[i, j]
            if not valid[i, j] or not np.isfinite(value):
                continue
            c = colocated_cosine_scalar(value, coef_a, coef_b)
            valid_p[i + 2, j + 2] = 1
            speed[i + 2, j + 2] = np.sqrt(1.0 / (c * c) - 1.0) if c > 0.0 else np.inf
            if c > c_max:
                c_max = c
    use_boundary = boundary.size > 0
    threshold = c_max - singular_tolerance
    for i in range(ny):
        for j in range(nx):
            if not valid_p[i + 2, j + 2]:
                continue
            if use_boundary:
                value = boundary[i, j]
                if np.isfinite(value):
                    t[i + 2, j + 2] = sign * value
                    fixed[i + 2, j + 2] = 1
            else:
                f = speed[i + 2, j + 2]
                c = 1.0 / np.sqrt(1.0 + f * f)
                if c >= threshold:
                    t[i + 2, j + 2] = sign
                    fixed[i + 2, j + 2] = 1
    return t, speed, fixed, valid_p


