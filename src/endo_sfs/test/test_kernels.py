"""Local updates of the sweeping kernels and the solve grids."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from endo_sfs import kernels
from endo_sfs.cycles import COUNTER_AVAILABLE
from endo_sfs.grid import build_solve_grid
from endo_sfs.reflectance import colocated_cosine, colocated_radiance, oren_nayar_coefficients
from endo_sfs.synthetic import scene_camera
from endo_sfs.visit_order import split_first_pass, value_order


def test_godunov_update_is_exact_for_planes():
    # T = 0.3x + 0.4y on a grid of spacing (0.5, 0.25): |∇T| = 0.5.
    hx, hy = 0.5, 0.25
    t = kernels.godunov_eikonal_update(-0.3 * hx, hx, hx**-2, -0.4 * hy, hy, hy**-2, 0.5)
    assert t == pytest.approx(0.0, abs=1e-15)
    # One-sided when the other neighbour is too high or missing.
    assert kernels.godunov_eikonal_update(1.0, 0.1, 100.0, np.inf, 0.1, 100.0, 2.0) == 1.2
    assert kernels.godunov_eikonal_update(np.inf, 1.0, 1.0, np.inf, 1.0, 1.0, 1.0) == np.inf


MODELS = [0.0, 0.3]  # σ


@pytest.mark.parametrize("sigma", MODELS)
def test_near_light_update_solves_its_discrete_equation(sigma):
    rng = np.random.default_rng(5)
    coef_a, coef_b = oren_nayar_coefficients(sigma)
    reflectance = np.array([coef_a, coef_b])

    def residual(v, a, b, wa, wb, lam, intensity):
        lhs = wa * max(v - a, 0.0) ** 2 + wb * max(v - b, 0.0) ** 2
        c = colocated_cosine(intensity * np.exp(2.0 * v), sigma)
        return np.sqrt(lhs) - lam * np.sqrt(1.0 / c**2 - 1.0)

    table = kernels.log_radiance_table(reflectance)
    singular = 0
    for _ in range(200):
        wa, wb = rng.uniform(1e4, 4e4, 2)
        lam = rng.uniform(1.5, 2.0)
        intensity = rng.uniform(0.3, 1.0)
        v_star = 0.5 * np.log(coef_a / intensity)
        a, b = v_star + rng.uniform(-0.05, 0.005, 2)
        v, tan_theta, dv = kernels.near_light_update(
            a, b, wa, wb, np.sqrt(wa), np.sqrt(wb), lam, v_star, reflectance, 0.0, 0.0, 0.0,
            table,
        )
        if v_star <= min(a, b):
            assert v == v_star and tan_theta == 0.0
            singular += 1
            continue
        # A re-solve after a neighbour moved, started from this solve's
        # (F, v, v'): one table lookup less, the same root.
        a_moved = a - 2e-4
        exact_moved = brentq(residual, min(a_moved, b) + 1e-12, v_star - 1e-15,
                             args=(a_moved, b, wa, wb, lam, intensity), xtol=1e-14)
        assert dv < 0.0
        again, _, _ = kernels.near_light_update(
            a_moved, b, wa, wb, np.sqrt(wa), np.sqrt(wb), lam, v_star, reflectance, tan_theta,
            v, dv, table,
        )
        assert again == pytest.approx(exact_moved, abs=2e-7)
        c = 1.0 / np.sqrt(1.0 + tan_theta**2)
        assert colocated_radiance(c, sigma) == pytest.approx(
            intensity * np.exp(2 * v), rel=1e-7
        )
        args = (a, b, wa, wb, lam, intensity)
        exact = brentq(residual, min(a, b) + 1e-12, v_star - 1e-15, args=args, xtol=1e-14)
        # ln r to 1e-7: a relative depth error of 1e-7.
        assert v == pytest.approx(exact, abs=1e-7)
    assert 0 < singular < 200


@pytest.mark.parametrize("sigma", MODELS)
def test_log_radiance_table_matches_the_closed_form(sigma):
    coef_a, coef_b = oren_nayar_coefficients(sigma)
    reflectance = np.array([coef_a, coef_b])
    table = kernels.log_radiance_table(reflectance)

    def log_radiance(f):  # relative to the value facing the camera, R(1) = A
        return 0.5 * np.log(colocated_radiance(1.0 / np.sqrt(1.0 + f * f), sigma) / coef_a)

    for f in np.concatenate([np.linspace(0.0, 15.99, 997), [16.0, 20.0, 300.0]]):
        value, slope = kernels._log_radiance(f, table, reflectance)
        # Cubic Hermite on 2048 intervals: about 1e-10.
        assert value == pytest.approx(log_radiance(f), abs=1e-9)
        if f == 0.0:
            assert slope == 0.0  # ln R(c) is even in F
            continue
        step = min(1e-6, 0.5 * f)
        numeric = (log_radiance(f + step) - log_radiance(f - step)) / (2.0 * step)
        assert slope == pytest.approx(numeric, rel=1e-5, abs=1e-5)


def test_weno_neighbour_is_exact_on_quadratics_and_falls_back_at_edges():
    u = np.array([[0.0, 1.0, 4.0, 9.0, 16.0]]).T @ np.ones((1, 5))  # u = i² along axis 0
    # Central node 2: D⁻ and D⁺ of i² at i = 2 are exact (4): min(4−4, 4+4) = 0.
    assert kernels.weno_neighbour(u, 2, 2, 1, 0, 1e-6) == pytest.approx(0.0, abs=1e-3)
    u[0, 2] = np.inf
    assert kernels.weno_neighbour(u, 2, 2, 1, 0, 1e-6) == 1.0  # first-order neighbour


def test_gnomonic_grid_of_an_undistorted_camera_is_the_pixel_grid():
    camera = scene_camera(64)
    grid = build_solve_grid(camera, "gnomonic", 1.0)
    assert grid.identity and grid.shape == (64, 64)
    assert grid.spacing == pytest.approx((1 / camera.fx, 1 / camera.fy))


def test_stereographic_grid_round_trips_a_smooth_function_through_distortion():
    camera = scene_camera(128, distortion=-0.2)
    grid = build_solve_grid(camera, "stereographic", 1.0)
    rays = camera.unit_rays()
    field = np.exp(rays[..., 0]) + rays[..., 1] ** 2
    valid = np.ones(field.shape, bool)
    nodes, node_valid = grid.to_nodes(field, valid)
    expected = np.exp(grid.node_rays[..., 0]) + grid.node_rays[..., 1] ** 2
    assert node_valid.mean() > 0.5
    # Bilinear sampling error grows with the distortion towards the corners;
    # inside the 56-pixel circle it stays at the 1e-4 level.
    radius = np.hypot(grid.node_pixel_x - camera.cx, grid.node_pixel_y - camera.cy)
    inner_nodes = node_valid & (radius < 56)
    np.testing.assert_allclose(nodes[inner_nodes], expected[inner_nodes], atol=1e-4)
    back = grid.to_pixels(np.where(node_valid, nodes, np.nan), valid)
    inner = camera.fov_mask(56)
    np.testing.assert_allclose(back[inner], field[inner], atol=2e-4)
    # The chart is conformal with factor λ = 2/(1+|s|²) ∈ (1, 2] here.
    assert np.all(grid.conformal_factor_sq <= 4.0) and np.all(grid.conformal_factor_sq > 1.0)


def _bowl(ny: int, nx: int, centre: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A padded value field rising away from ``centre`` and its value-ordered valid nodes."""
    i, j = np.mgrid[0 : ny + 4, 0 : nx + 4].astype(np.float64)
    values = np.hypot(i - centre[0], j - centre[1])
    valid = np.zeros((ny + 4, nx + 4), dtype=np.uint8)
    valid[2:-2, 2:-2] = 1
    return values, value_order(np.where(valid, values, np.inf), valid, 1.0)


def test_split_first_pass_cuts_through_the_nearest_point_along_the_flow():
    ny, nx = 60, 80
    # Nearest point at the left edge, middle row: flow to the right, so the
    # seam is the row through it and both halves keep their value order.
    values, ordered = _bowl(ny, nx, (31.0, 2.0))
    out, split, seam = split_first_pass(ordered, nx + 4, 2)
    rows = out // (nx + 4)
    assert 0.25 * ordered.size <= split <= 0.75 * ordered.size
    assert np.all(rows[:split] < 31) and np.all(rows[split:] >= 31)
    assert sorted(out.tolist()) == sorted(ordered.tolist())
    for part in (out[:split], out[split:]):
        assert np.all(np.diff(values.ravel()[part]) >= -1.0)  # bucketed order kept
    assert set((seam // (nx + 4)).tolist()) == {29, 30, 31, 32}
    # Nearest point in a corner: no balanced cut, one thread.
    _, corner = _bowl(ny, nx, (2.0, 2.0))
    assert split_first_pass(corner, nx + 4, 2)[1] == 0


@pytest.mark.parametrize("split", [False, True])
def test_any_first_pass_order_reaches_the_fixed_point_of_the_sweeps(split):
    camera = scene_camera(96)
    grid = build_solve_grid(camera, "stereographic", 1.0)
    rng = np.random.default_rng(3)
    ny, nx = grid.shape
    intensity = np.exp(rng.normal(0.0, 0.02, (ny, nx))) * 0.5 * (1.0 + 0.3 * np.hypot(
        *np.mgrid[-1 : 1 : ny * 1j, -1 : 1 : nx * 1j]))
    valid = np.ones((ny, nx), dtype=bool)
    reflectance = np.array(oren_nayar_coefficients(0.3))
    table = kernels.log_radiance_table(reflectance)
    hx, hy = grid.spacing
    empty = np.empty(0, dtype=np.int64)

    def run(first_pass: np.ndarray, parts: int, seam: np.ndarray, rows: int = 0,
            key: np.ndarray | None = None) -> np.ndarray:
        v, node, valid_p, _ = kernels.near_light_inputs(
            intensity, valid, grid.conformal_factor_sq, np.empty((0, 0)), np.empty((0, 0)),
            0.0, reflectance,
        )
        ticks = np.full(3, -7, dtype=np.int64)
        _, change, _ = kernels.near_light_sweep(
            v, node, valid_p, hx, hy, reflectance, 2, 1e-9, 500, 0.0, table, first_pass,
            parts, seam, rows, np.empty((0, 0)) if key is None else key, ticks,
        )
        assert change <= 1e-9
        # The cycle counts that split the kernel's time: start ≤ start of the
        # one-thread finish ≤ end, the finish empty without two threads.
        if COUNTER_AVAILABLE:
            assert 0 < ticks[0] <= ticks[1] <= ticks[2]
        else:
            assert ticks[0] == ticks[1] == ticks[2] == 0
        if parts == 0 and rows == 0:
            assert ticks[1] == ticks[2]
        return v[2:-2, 2:-2]

    reference = run(empty, 0, empty)  # plain sweeps
    # A scrambled first pass: every misordering must be repaired.
    scrambled = rng.permutation(np.flatnonzero(np.pad(valid, 2).ravel())).astype(np.int64)
    parts, seam = 0, empty
    if split:
        half = scrambled.size // 2
        rows = scrambled // (nx + 4)
        scrambled = np.concatenate([scrambled[rows < ny // 2 + 2], scrambled[rows >= ny // 2 + 2]])
        parts = int(np.sum(rows < ny // 2 + 2))
        assert abs(parts - half) < 0.1 * half
        seam_rows = (scrambled // (nx + 4) >= ny // 2) & (scrambled // (nx + 4) < ny // 2 + 4)
        seam = scrambled[seam_rows]
    # Equal up to the per-node Newton accuracy (~1e-7), far below the default
    # sweep tolerance (1e-4; these sweeps stop at 1e-9).
    np.testing.assert_allclose(run(scrambled, parts, seam), reference, atol=1e-6)
    # Sweeps alone, the two halves of the rows first swept on two threads.
    np.testing.assert_allclose(run(empty, 0, empty, ny // 2 + 2), reference, atol=1e-6)
    # Each node first solved in the sweep its predicted upwind neighbours
    # suggest (a noisy prediction, as the previous frame's solution is).
    key = np.pad(reference + rng.normal(0.0, 0.01, reference.shape), 2, constant_values=np.inf)
    np.testing.assert_allclose(run(empty, 0, empty, key=key), reference, atol=1e-6)
    np.testing.assert_allclose(run(empty, 0, empty, ny // 2 + 2, key), reference, atol=1e-6)


def test_first_sweeps_meet_the_predicted_upwind_neighbours_first():
    # Sweeps (+i, +j), (+i, −j), (−i, −j), (−i, +j); a key rising along +j
    # and +i has its lower neighbours at −j and −i: sweep 0, and so on.
    i, j = np.mgrid[0:6, 0:7].astype(float)
    for key, sweep in ((i + j, 0), (i - j, 1), (-i - j, 2), (j - i, 3), (0.0 * i, 0), (-j, 1)):
        state = kernels.initial_state(np.pad(np.ones(key.shape, dtype=np.uint8), 2))
        kernels.mark_first_sweeps(state, np.pad(key, 2, constant_values=np.inf))
        # Inside (an edge node has no lower neighbour across the edge).
        assert np.all(state[3:-3, 3:-3] == kernels.FRESH + sweep)
        assert np.all(state[2:-2, 2:-2] >= kernels.FRESH)
        assert np.all(state[:2] == kernels.OUTSIDE)
