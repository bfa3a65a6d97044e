"""How well the tracker's poses can fix the depth scale: the Cramér–Rao bound on ln s.

Vision alone is scale-free: all metric information comes from the tracker.
In the best case vision gives the camera's trajectory exactly up to one
scale and one offset (and its orientation), and the tracker measures the
camera centre at its own samples:

    c_i = s · r_i + t0 + e_i,    e_i ~ N(0, Σ_i),

with r_i the vision-relative centre (world axes, unknown unit), s the scale,
t0 an unknown offset (3,) and Σ_i the (3, 3) covariance of the tracker's
camera-centre error, independent from sample to sample (endo_sim's noise is
white; a real tracker's jitter is correlated over time, which makes the
bound optimistic for it: correlated samples carry less information than as
many independent ones). With θ = ln s the model's Jacobian at sample i is
J_i = [c_i − t0, I₃] (3 × 4; the true centre minus the offset is s · r_i),
the Fisher information over samples 0..k is F_k = Σ J_iᵀ Σ_i⁻¹ J_i, and no
unbiased estimator of ln s from those samples has a standard deviation below
σ(ln s)_k = √((F_k⁻¹)₀₀), the Schur complement of the offset block. It does
not depend on t0 (the offset absorbs any reference point), only on how far
and in which directions the camera moved against the noise's shape.

On a straight line of length D with N equally spaced samples and isotropic
per-axis noise σ, σ(ln s) = σ / √(Σ (x_i − x̄)²) → σ√12 / (D√N).

The tracker's noise model (``endo_sim.tracker``): an isotropic position error
of 3-D RMS σ_p and a rotation error of angle RMS σ_r, both applied to the
marker, which is a lever arm L (camera centre minus marker origin, ~0.3 m
for a rigid scope) from the camera. Carried to the camera centre, to first
order e = δp + δω × L, so

    Σ = (σ_p² / 3) I + (σ_r² / 3) (|L|² I − L Lᵀ):

the rotation noise moves the camera across the lever arm (0.30 mm per axis
for 0.1° at 0.3 m), not along it. If vision knows the orientation, the
rotation error is no longer carried (``rotation_noise_rms_rad`` 0) and only
the position error remains.

:func:`cumulative_scale_fit` is the estimator that attains the bound in this
linear Gaussian model: the weighted least-squares fit of (s, t0) to the
tracker's centres over every sample so far.
"""

from __future__ import annotations

import numpy as np

from endo_flow.errors import FlowInputError


def _check_centres(centres: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(centres, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise FlowInputError(f"{name} must be (N, 3) metres, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise FlowInputError(f"{name} holds NaN or infinite values")
    return array


def _check_covariances(covariances: np.ndarray, count: int) -> np.ndarray:
    array = np.asarray(covariances, dtype=np.float64)
    if array.shape != (count, 3, 3):
        raise FlowInputError(f"covariances must be ({count}, 3, 3) m², got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise FlowInputError("covariances hold NaN or infinite values")
    if np.any(np.linalg.eigvalsh(0.5 * (array + array.transpose(0, 2, 1)))[:, 0] <= 0.0):
        raise FlowInputError("covariances must be positive definite")
    return array


def lever_arms(T_world_camera: np.ndarray, T_marker_camera: np.ndarray) -> np.ndarray:
    """The lever arm L = camera centre − marker origin in world axes, per pose.

    Args:
        T_world_camera: (N, 4, 4) float64 camera poses, metres.
        T_marker_camera: (4, 4) float64 hand–eye transform (the camera's pose in
            the marker frame), metres.

    Returns:
        (N, 3) float64 metres: R_world_marker · t_marker_camera.

    Raises:
        FlowInputError: a transform of the wrong shape.
    """
    poses = np.asarray(T_world_camera, dtype=np.float64)
    hand_eye = np.asarray(T_marker_camera, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise FlowInputError(f"T_world_camera must be (N, 4, 4), got shape {poses.shape}")
    if hand_eye.shape != (4, 4):
        raise FlowInputError(f"T_marker_camera must be (4, 4), got shape {hand_eye.shape}")
    # R_world_marker = R_world_camera · R_marker_cameraᵀ
    R_world_marker = poses[:, :3, :3] @ hand_eye[:3, :3].T
    return np.asarray(R_world_marker @ hand_eye[:3, 3], dtype=np.float64)


def camera_centre_covariances(
    lever: np.ndarray, position_noise_rms_m: float, rotation_noise_rms_rad: float
) -> np.ndarray:
    """Covariance of the tracker-derived camera centre, per sample.

    Σ = (σ_p² / 3) I + (σ_r² / 3) (|L|² I − L Lᵀ): an isotropic marker
    position error of 3-D RMS σ_p plus an isotropic marker rotation error of
    angle RMS σ_r carried over the lever arm L (first order).

    Args:
        lever: (N, 3) float64 lever arms in world axes, metres (:func:`lever_arms`).
        position_noise_rms_m: σ_p, 3-D RMS of the marker position error, metres.
        rotation_noise_rms_rad: σ_r, angle RMS of the marker rotation error,
            radians (0: orientation known, e.g. from vision).

    Returns:
        (N, 3, 3) float64 covariances, m².

    Raises:
        FlowInputError: a bad shape, a negative noise, or no noise at all.
    """
    arms = _check_centres(lever, "lever")
    if position_noise_rms_m < 0.0 or rotation_noise_rms_rad < 0.0:
        raise FlowInputError("tracker noise must be >= 0")
    if position_noise_rms_m == 0.0:
        raise FlowInputError("position noise must be > 0 (without it the bound is 0)")
    eye = np.eye(3)
    length2 = np.einsum("ni,ni->n", arms, arms)
    perpendicular = length2[:, None, None] * eye - arms[:, :, None] * arms[:, None, :]
    return np.asarray(
        (position_noise_rms_m**2 / 3.0) * eye + (rotation_noise_rms_rad**2 / 3.0) * perpendicular,
        dtype=np.float64,
    )


def _cumulative_normal_equations(
    regressors: np.ndarray, covariances: np.ndarray, measured: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Prefix sums of Aᵀ W A (N, 4, 4) and Aᵀ W y (N, 4), A_i = [r_i, I₃]."""
    weights = np.linalg.inv(covariances)  # (N, 3, 3)
    n = regressors.shape[0]
    design = np.zeros((n, 3, 4))
    design[:, :, 0] = regressors
    design[:, :, 1:] = np.eye(3)
    normal = np.einsum("nji,njk,nkl->nil", design, weights, design)
    rhs = None
    if measured is not None:
        rhs = np.cumsum(np.einsum("nji,njk,nk->ni", design, weights, measured), axis=0)
    return np.cumsum(normal, axis=0), rhs


def scale_information_bound(centres: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Cramér–Rao bound on ln s from the samples 0..k, for every k.

    Args:
        centres: (N, 3) float64 true camera centres at the tracker's samples,
            in time order, metres (any origin).
        covariances: (N, 3, 3) float64 covariance of each sample's camera-centre
            error, m² (:func:`camera_centre_covariances`).

    Returns:
        (N,) float64: the least standard deviation of ln s (dimensionless; ×100
        for percent) that any unbiased estimator using samples 0..k can reach;
        ``inf`` while the samples do not fix the scale (all at one point).

    Raises:
        FlowInputError: a bad shape, a non-finite value or a covariance that is
            not positive definite.
    """
    points = _check_centres(centres, "centres")
    cov = _check_covariances(covariances, points.shape[0])
    if points.shape[0] == 0:
        return np.empty(0)
    # the offset absorbs any origin: centre on the first sample for conditioning
    normal, _ = _cumulative_normal_equations(points - points[0], cov, None)
    a = normal[:, 0, 0]
    b = normal[:, 1:, 0]
    offset_block = normal[:, 1:, 1:]
    explained = np.einsum("ni,ni->n", b, np.linalg.solve(offset_block, b[:, :, None])[:, :, 0])
    schur = a - explained
    # below round-off of a: no motion yet, no information
    informative = schur > 1e-9 * np.maximum(a, np.finfo(np.float64).tiny)
    bound = np.full(points.shape[0], np.inf)
    bound[informative] = 1.0 / np.sqrt(schur[informative])
    return bound


def cumulative_scale_fit(
    relative: np.ndarray, measured: np.ndarray, covariances: np.ndarray
) -> np.ndarray:
    """ln s of the weighted least-squares fit measured ≈ s · relative + t0, per prefix.

    The efficient estimator of the bound's model: with Gaussian errors of
    the given covariances its standard deviation is
    :func:`scale_information_bound` (of the true centres).

    Args:
        relative: (N, 3) float64 vision-relative camera centres r_i (world
            axes, any unit and origin), in time order.
        measured: (N, 3) float64 tracker-derived camera centres, metres.
        covariances: (N, 3, 3) float64 covariance of each measured centre, m².

    Returns:
        (N,) float64 ln s fitted on samples 0..k; NaN while the fit is not
        determined (no motion yet) or gives s ≤ 0.

    Raises:
        FlowInputError: bad shapes, non-finite values or a covariance that is not
            positive definite.
    """
    rel = _check_centres(relative, "relative")
    meas = _check_centres(measured, "measured")
    if meas.shape != rel.shape:
        raise FlowInputError(f"measured {meas.shape} and relative {rel.shape} differ in shape")
    cov = _check_covariances(covariances, rel.shape[0])
    if rel.shape[0] == 0:
        return np.empty(0)
    rel0 = rel - rel[0]
    normal, rhs = _cumulative_normal_equations(rel0, cov, meas - meas[0])
    assert rhs is not None
    scale = np.full(rel.shape[0], np.nan)
    bound = scale_information_bound(rel0, cov)  # finite: the relative path moved
    ok = np.isfinite(bound)
    if ok.any():
        solution = np.linalg.solve(normal[ok], rhs[ok][:, :, None])[:, 0, 0]
        scale[ok] = solution
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(scale > 0.0, np.log(np.where(scale > 0.0, scale, 1.0)), np.nan)


def known_rotation_translation(
    points: np.ndarray,
    rays: np.ndarray,
    rotation: np.ndarray,
    iterations: int = 8,
    cauchy_rad: float = 0.004,
) -> tuple[np.ndarray, int]:
    """The translation t of a view whose rotation is known, from points and their rays.

    Each point X (reference camera frame) is seen along the unit ray b in the
    view: b × (R X + t) = 0, linear in t. Solved by least squares over every
    point, each row divided by the point's distance (so the residual is an
    angle), then reweighted (Cauchy on the angle, so a track on the wrong
    point loses its weight) ``iterations`` times.

    Args:
        points: (N, 3) float64 points in the reference frame, any unit.
        rays: (N, 3) float64 unit rays of the same points in the view.
        rotation: (3, 3) float64 R_view_reference.
        iterations: reweighting rounds after the first solve.
        cauchy_rad: the Cauchy weight's scale (half weight at this angle), radians.

    Returns:
        ((3,) float64 t_view_reference in the points' unit, number of points
        within ``cauchy_rad`` at the end). The view's centre in the reference
        frame is −Rᵀ t.

    Raises:
        FlowInputError: shapes that disagree or fewer than 3 finite points off
            the reference centre.
    """
    X = np.asarray(points, dtype=np.float64)
    b = np.asarray(rays, dtype=np.float64)
    R = np.asarray(rotation, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or b.shape != X.shape or R.shape != (3, 3):
        raise FlowInputError(
            f"points {X.shape} and rays {b.shape} must be (N, 3), rotation {R.shape} (3, 3)"
        )
    # A point at the reference centre has no direction: it cannot weigh in.
    ok = np.isfinite(X).all(axis=1) & np.isfinite(b).all(axis=1) & (np.linalg.norm(X, axis=1) > 0.0)
    if ok.sum() < 3:
        raise FlowInputError(
            f"{int(ok.sum())} finite points off the centre: a translation needs at least 3"
        )
    Y, b = X[ok] @ R.T, b[ok]
    distance = np.linalg.norm(Y, axis=1)
    # [b]× rows: b × t = −b × Y
    cross = np.zeros((len(b), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2] = -b[:, 2], b[:, 1]
    cross[:, 1, 0], cross[:, 1, 2] = b[:, 2], -b[:, 0]
    cross[:, 2, 0], cross[:, 2, 1] = -b[:, 1], b[:, 0]
    rhs = -np.cross(b, Y)
    weight = 1.0 / distance
    t = np.zeros(3)
    inliers = len(b)
    for _ in range(iterations + 1):
        A = (cross * weight[:, None, None]).reshape(-1, 3)
        y = (rhs * weight[:, None]).reshape(-1)
        t = np.linalg.lstsq(A, y, rcond=None)[0]
        angle = np.linalg.norm(np.cross(b, Y + t), axis=1) / np.maximum(
            np.linalg.norm(Y + t, axis=1), 1e-12
        )
        robust = 1.0 / (1.0 + (angle / cauchy_rad) ** 2)
        inliers = int(np.sum(angle <= cauchy_rad))
        weight = np.sqrt(robust) / distance
    return t, inliers


def segmented_scale_fit(
    segments: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[float, float]:
    """ln s and its standard deviation over several segments of vision-relative path.

    Each segment g is measured ≈ s · relative + t0_g with its own offset t0_g
    (a new reference view: a new origin and a new SFS unit, which the one
    common s averages, as the sequence's oracle scale does). The offsets are
    eliminated (Schur complement per segment); s is the weighted least-squares
    value over every sample.

    Args:
        segments: per segment (relative (M, 3) any unit, measured (M, 3)
            metres, covariances (M, 3, 3) m²), M ≥ 1.

    Returns:
        (ln s, its standard deviation from the covariances); (NaN, inf)
        while the segments hold no motion, NaN ln s if s ≤ 0.

    Raises:
        FlowInputError: a segment with no sample, shapes that disagree,
            non-finite values or a covariance that is not positive definite.
    """
    information = 0.0
    score = 0.0
    for index, (relative, measured, covariances) in enumerate(segments):
        r = _check_centres(relative, f"segment {index}'s relative centres")
        y = _check_centres(measured, f"segment {index}'s measured centres")
        if len(r) == 0 or len(y) != len(r):
            raise FlowInputError(
                f"segment {index} holds {len(r)} relative and {len(y)} measured centres:"
                " it needs the same number, at least 1"
            )
        W = np.linalg.inv(_check_covariances(covariances, len(r)))
        r = r - r[0]
        y = y - y[0]
        Wr = np.einsum("nij,nj->ni", W, r)
        sum_W = W.sum(axis=0)
        sum_Wr = Wr.sum(axis=0)
        sum_Wy = np.einsum("nij,nj->ni", W, y).sum(axis=0)
        inv = np.linalg.inv(sum_W)
        information += float(np.einsum("ni,ni->", Wr, r) - sum_Wr @ inv @ sum_Wr)
        score += float(np.einsum("ni,ni->", Wr, y) - sum_Wr @ inv @ sum_Wy)
    if information <= 0.0:
        return float("nan"), float("inf")
    s = score / information
    if s <= 0.0:
        return float("nan"), float("inf")
    return float(np.log(s)), float(1.0 / (np.sqrt(information) * s))
