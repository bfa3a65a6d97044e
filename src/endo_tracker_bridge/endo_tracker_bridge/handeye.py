"""Hand–eye and clock calibration of a tracked endoscope from checkerboard views.

Frames and unknowns (x_a = T_a_b · x_b):

* ``A_i = T_tracker_marker`` at the time of image i (tracker, interpolated);
* ``B_i = T_camera_target`` of image i (checkerboard PnP);
* ``X = T_marker_camera`` (the hand–eye transform, wanted);
* ``W = T_tracker_target`` (the board, fixed in the tracker frame);
* ``time_offset``: tracker_stamp = camera_time + time_offset (see
  :mod:`endo_tracker_bridge.composition`).

Every view satisfies ``A_i · X · B_i = W``. For two views i, j the relative
motions ``A_ij = A_j⁻¹ A_i`` (marker) and ``B_ij = B_j B_i⁻¹`` (camera) satisfy
the classical ``A_ij X = X B_ij``.

Steps (:func:`calibrate_hand_eye`):

1. Coarse clock search: for each candidate offset on a grid, interpolate the
   marker poses at ``image_stamp + offset`` (SLERP,
   :func:`endo_io.pose.interpolate_transforms`), solve the closed form (Park)
   and score the median spread of the implied board poses ``A_i X B_i``.
2. At the best offset, solve ``A X = X B`` with ``cv2.calibrateHandEye``:
   Tsai–Lenz (1989), Park–Martin (1994) and Daniilidis (1999); keep the one
   whose implied board poses agree best; reject views whose board pose is an
   outlier (median + 4 MAD).
3. Refine X and W by non-linear least squares on the difference between each
   measured marker pose and the one its board view predicts, weighted by the
   tracker's noise (:func:`refine_hand_eye`, scipy.optimize.least_squares).
4. Fine clock search: minimise that refined cost over the offset in a
   bracket around the coarse optimum (bounded Brent), then fit once more at
   the optimum and report the residuals (tracker and corner reprojection).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from scipy.spatial.transform import Rotation

from endo_io.camera import CameraModel
from endo_io.pose import (
    interpolate_transforms,
    invert_transform,
    rigid_transform,
    rotation_angle,
)
from endo_tracker_bridge.errors import HandEyeError

#: The closed forms: OpenCV's flag for each method name.
_OPENCV_METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
METHODS = tuple(_OPENCV_METHODS)
#: Views handed to ``cv2.calibrateHandEye`` at most (evenly spread). OpenCV
#: forms a motion from every pair of views, N (N - 1) / 2 of them at a few
#: microseconds each, so the closed form's cost grows with the square of N;
#: 100 views (4950 pairs, ~30 ms) already pin X down to the tracker's noise
#: and the least-squares refinement uses every view anyway.
CLOSED_FORM_MAX_VIEWS = 100
MS = 1_000_000


# -- the board -----------------------------------------------------------------------


@dataclass(frozen=True)
class Checkerboard:
    """A planar checkerboard target.

    ``columns`` × ``rows`` are the *inner* corners (OpenCV's pattern size),
    ``square_m`` the square side in metres. The target frame has its origin
    at the inner corner next to a dark outer corner square, x along a row of
    corners, y down the columns, z into the board (right-handed). Use a board
    with columns + rows odd (e.g. 9x6, 8x5): then only one end has a dark
    corner square and every view numbers the corners the same way.
    """

    columns: int
    rows: int
    square_m: float

    def __post_init__(self) -> None:
        if self.columns < 3 or self.rows < 3 or not self.square_m > 0.0:
            raise HandEyeError(
                f"checkerboard needs >= 3x3 inner corners and a positive square, got "
                f"{self.columns}x{self.rows}, {self.square_m} m"
            )

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(columns, rows) as OpenCV's ``patternSize``."""
        return (self.columns, self.rows)

    def object_points(self) -> np.ndarray:
        """(rows·columns, 3) float64 corner positions in the target frame, metres.

        Row-major, matching the order of OpenCV's detections.
        """
        r, c = np.mgrid[0 : self.rows, 0 : self.columns]
        points = np.stack([c.ravel(), r.ravel(), np.zeros(c.size)], axis=-1)
        return points * self.square_m


def detect_checkerboard(image: np.ndarray, board: Checkerboard) -> np.ndarray | None:
    """Find the inner corners of ``board`` in an image.

    ``image`` is (H, W) or (H, W, 3|4), uint8 or uint16. Returns (N, 2)
    float64 sub-pixel corner positions (pixel centres at integers), row-major
    like :meth:`Checkerboard.object_points`, or None when the whole board is
    not found.
    """
    gray = _gray8(image)
    # The classic detector refined by cornerSubPix is ~8x faster than the
    # sector-based one and, on rendered boards, more accurate (0.06 px vs
    # 0.16 px RMS); the sector-based one is the fallback for hard images.
    found, corners = cv2.findChessboardCorners(
        gray,
        board.pattern_size,
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK,
    )
    if found:
        points = corners.reshape(board.rows, board.columns, 2)
        spacing = min(
            float(np.min(np.linalg.norm(np.diff(points, axis=0), axis=-1))),
            float(np.min(np.linalg.norm(np.diff(points, axis=1), axis=-1))),
        )
        half_window = int(np.clip(0.35 * spacing, 2, 7))
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (half_window, half_window), (-1, -1), criteria)
    else:
        found, corners = cv2.findChessboardCornersSB(
            gray, board.pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
        )
        if not found:
            return None
    return _orient_corners(gray, np.asarray(corners, dtype=np.float64).reshape(-1, 2), board)


def _orient_corners(gray: np.ndarray, corners: np.ndarray, board: Checkerboard) -> np.ndarray:
    """Put the corner next to the board's dark outer corner square first.

    OpenCV may number a board from either end (a 180° turn). When the
    columns + rows of inner corners are odd, the two outer corner squares at
    the ends of the numbering have opposite colours, so the dark one fixes
    the origin and every view agrees; otherwise the order is left as found.
    (N, 2) corners in, (N, 2) out.
    """
    columns, rows = board.pattern_size
    if (columns + rows) % 2 == 0:
        return corners
    grid = np.stack(np.meshgrid(np.arange(columns), np.arange(rows)), axis=-1).reshape(-1, 2)
    homography, _ = cv2.findHomography(grid.astype(np.float64), corners)
    if homography is None:
        return corners
    centres = np.array([[-0.5, -0.5], [columns - 0.5, rows - 0.5]])
    pixels = cv2.perspectiveTransform(centres[None], homography)[0]
    height, width = gray.shape
    levels = []
    for u, v in np.round(pixels).astype(int):
        if not (1 <= u < width - 1 and 1 <= v < height - 1):
            return corners
        levels.append(float(np.mean(gray[v - 1 : v + 2, u - 1 : u + 2])))
    return corners if levels[0] <= levels[1] else corners[::-1].copy()


#: Inner-corner counts (columns, rows) of common calibration checkerboards,
#: tried in this order when the board given is not found. Boards with
#: columns + rows odd come first: they number their corners unambiguously.
COMMON_BOARDS: tuple[tuple[int, int], ...] = (
    (9, 6), (8, 5), (7, 6), (6, 5), (7, 4), (9, 4), (10, 7), (8, 7), (11, 8), (5, 4),
    (8, 6), (7, 5), (9, 7), (6, 4), (10, 6), (5, 3), (4, 3),
)


def find_board_size(
    images: list[np.ndarray], candidates: tuple[tuple[int, int], ...] = COMMON_BOARDS
) -> tuple[tuple[int, int], int] | None:
    """The checkerboard size (inner corners) the images show, among ``candidates``.

    Each candidate is tried on every image with OpenCV's fast check; the one
    found in the most images wins (ties: the earlier candidate).
    images: (H, W) or (H, W, C) uint8/uint16 frames, a few spread over a recording.
    Returns ((columns, rows), images it was found in), or None when no
    candidate is found in any image.
    """
    best: tuple[tuple[int, int], int] | None = None
    for columns, rows in candidates:
        found = 0
        for image in images:
            gray = _gray8(image)
            ok, _ = cv2.findChessboardCorners(
                gray, (columns, rows), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK
            )
            found += int(ok)
        if found and (best is None or found > best[1]):
            best = ((columns, rows), found)
            if found == len(images):
                break
    return best


def _gray8(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 of an (H, W) or (H, W, 3|4), uint8 or uint16 image (min-max stretched)."""
    gray = np.asarray(image)
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_RGBA2GRAY if gray.shape[2] == 4 else cv2.COLOR_RGB2GRAY)
    if gray.dtype != np.uint8:
        low, high = float(np.min(gray)), float(np.max(gray))
        stretched = (gray.astype(np.float64) - low) * (255.0 / max(high - low, 1e-12))
        gray = np.clip(stretched, 0.0, 255.0).astype(np.uint8)
    return gray


@dataclass(frozen=True)
class BoardView:
    """One image in which the board was found.

    ``stamp_ns``: image stamp (camera clock); ``corners``: (N, 2) pixels;
    ``T_camera_target``: (4, 4) PnP pose, metres; ``reprojection_rms_px``:
    RMS corner residual of that pose.
    """

    stamp_ns: int
    corners: np.ndarray = field(repr=False)
    T_camera_target: np.ndarray = field(repr=False)
    reprojection_rms_px: float


def board_view(
    stamp_ns: int, corners: np.ndarray, board: Checkerboard, camera: CameraModel
) -> BoardView:
    """Solve the board pose (PnP) of one image's corners.

    ``corners`` (N, 2) pixels in the image ``camera`` describes (any of its
    distortion models: the corners are undistorted through
    ``camera.pixels_to_rays`` and PnP runs on normalised coordinates).
    Raises HandEyeError when PnP fails.
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    object_points = board.object_points()
    rays = camera.pixels_to_rays(corners)
    if not np.all(np.isfinite(rays)):
        raise HandEyeError("a corner lies where the lens distortion cannot be inverted")
    normalised = rays[:, :2] / rays[:, 2:3]
    found, rvec, tvec = cv2.solvePnP(
        object_points, normalised, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE
    )
    if not found:
        raise HandEyeError("PnP found no board pose")
    rvec, tvec = cv2.solvePnPRefineLM(object_points, normalised, np.eye(3), None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    projected = camera.project(object_points @ T[:3, :3].T + T[:3, 3])
    rms = float(np.sqrt(np.mean(np.sum((projected - corners) ** 2, axis=-1))))
    return BoardView(int(stamp_ns), corners, T, rms)


# -- interpolation of the tracker stream ---------------------------------------------


def marker_poses_at(
    tracker_stamps_ns: np.ndarray,
    tracker_poses: np.ndarray,
    query_ns: np.ndarray,
    max_gap_ns: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate the marker pose at each query time.

    ``tracker_stamps_ns`` (M,) int64 increasing, ``tracker_poses`` (M, 4, 4)
    metres, ``query_ns`` (N,) int64 (tracker clock). A query is valid when it
    falls on a sample or between two samples at most ``max_gap_ns`` apart (a
    dropout longer than that is not bridged). Returns ((N, 4, 4) float64, NaN
    where invalid; (N,) bool valid). This is
    :func:`endo_io.pose.interpolate_transforms` (linear translation, SLERP).
    """
    return interpolate_transforms(tracker_stamps_ns, tracker_poses, query_ns, max_gap_ns)


# -- closed-form hand-eye (A X = X B) ------------------------------------------------


def _rotates_about_one_axis(T_tracker_marker: np.ndarray) -> bool:
    """Whether every marker rotation relative to the first view shares one axis.

    Then ``A X = X B`` leaves a rotation of X about that axis (and a
    translation along it) free: every closed form is degenerate.
    """
    relative = np.swapaxes(T_tracker_marker[:1, :3, :3], -1, -2) @ T_tracker_marker[1:, :3, :3]
    rotvecs = Rotation.from_matrix(relative).as_rotvec()
    singular = np.linalg.svd(rotvecs, compute_uv=False)
    return len(singular) < 2 or singular[1] / math.sqrt(len(rotvecs)) < 1e-6


def solve_hand_eye(
    T_tracker_marker: np.ndarray, T_camera_target: np.ndarray, method: str = "park"
) -> np.ndarray:
    """Closed-form T_marker_camera (4, 4) from N >= 3 views (N, 4, 4) each, metres.

    ``method`` is ``tsai``, ``park`` or ``daniilidis``, solved by
    ``cv2.calibrateHandEye`` with the marker as OpenCV's gripper and the
    tracker as its base (``T_tracker_marker`` = gripper2base,
    ``T_camera_target`` = target2cam; the result, cam2gripper, is
    T_marker_camera). OpenCV uses every pair of views i < j, with the motions
    ``A_j⁻¹ A_i`` and ``B_j B_i⁻¹``; of more than
    :data:`CLOSED_FORM_MAX_VIEWS` views an evenly spread subset is used.
    Raises HandEyeError with fewer than 3 views, an unknown method, views
    whose marker rotations share one axis, too few view pairs rotating by
    more than ~17° (``tsai``: OpenCV skips the others), or a non-finite or
    non-rotation result.
    """
    if method not in _OPENCV_METHODS:
        raise HandEyeError(f"unknown hand-eye method '{method}' (expected {', '.join(METHODS)})")
    A = np.asarray(T_tracker_marker, dtype=np.float64)
    B = np.asarray(T_camera_target, dtype=np.float64)
    if len(A) < 3:
        raise HandEyeError(f"hand-eye needs at least 3 views, got {len(A)}")
    if A.shape[1:] != (4, 4) or B.shape != A.shape:
        raise HandEyeError(f"hand-eye needs two (N, 4, 4) stacks, got {A.shape} and {B.shape}")
    if len(A) > CLOSED_FORM_MAX_VIEWS:
        pick = np.unique(np.linspace(0, len(A) - 1, CLOSED_FORM_MAX_VIEWS).round().astype(int))
        A, B = A[pick], B[pick]
    if _rotates_about_one_axis(A):
        raise HandEyeError("the marker rotates about one axis only; hand-eye is undetermined")
    try:
        R, t = cv2.calibrateHandEye(
            list(np.ascontiguousarray(A[:, :3, :3])),
            list(np.ascontiguousarray(A[:, :3, 3:])),
            list(np.ascontiguousarray(B[:, :3, :3])),
            list(np.ascontiguousarray(B[:, :3, 3:])),
            method=_OPENCV_METHODS[method],
        )
    except cv2.error as error:
        raise HandEyeError(f"cv2.calibrateHandEye ({method}) failed: {error.err}") from error
    if np.array_equal(R, np.eye(3)) and not np.any(t):
        # OpenCV's Tsai keeps only view pairs that rotate by more than ~17°
        # (2 sin(θ/2) >= 0.3, measured on 4.14); with fewer than two it logs
        # an error and returns its initial identity rotation and zero
        # translation, which no real solution equals exactly.
        raise HandEyeError(f"{method}: too few view pairs with a large rotation")
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, np.ravel(t)
    if not np.all(np.isfinite(X)):
        raise HandEyeError(f"{method}: no finite hand-eye solution (too little motion?)")
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) <= 0.0:
        raise HandEyeError(f"{method}: the hand-eye solution is not a rotation (degenerate data)")
    u, _, vt = np.linalg.svd(R)  # remove rounding, so X is rigid to machine precision
    X[:3, :3] = u @ vt
    return X


# -- residuals ---------------------------------------------------------------------------


def mean_transform(T: np.ndarray) -> np.ndarray:
    """Chordal mean (4, 4) of rigid transforms (N, 4, 4).

    The rotation is the SO(3) projection of the mean rotation matrix, the
    translation the mean translation.
    """
    u, _, vt = np.linalg.svd(np.sum(T[:, :3, :3], axis=0))
    mean = np.eye(4)
    mean[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    mean[:3, 3] = np.mean(T[:, :3, 3], axis=0)
    return mean


def target_pose(
    T_tracker_marker: np.ndarray, T_marker_camera: np.ndarray, T_camera_target: np.ndarray
) -> np.ndarray:
    """Board pose W (4, 4) in the tracker frame: mean of the views' ``A_i X B_i``."""
    return mean_transform(T_tracker_marker @ T_marker_camera @ T_camera_target)


def tracker_residuals(
    T_tracker_marker: np.ndarray,
    T_camera_target: np.ndarray,
    T_marker_camera: np.ndarray,
    T_tracker_target: np.ndarray,
) -> np.ndarray:
    """Measured vs predicted marker pose of each view, in the marker frame.

    The marker pose predicted from the board view is ``Â_i = W B_i⁻¹ X⁻¹``;
    the residual is ``A_i⁻¹ Â_i`` as (N, 6) float64: rotation vector
    (radians, 3) then translation (metres, 3). When the tracker's noise
    dominates (it does: a 0.1° tracker error moves a camera 25 cm away by
    0.4 mm, far more than PnP's error), these are the tracker's own errors,
    so weighting them by the tracker's noise gives the maximum-likelihood fit.
    """
    predicted = (
        T_tracker_target @ invert_transform(T_camera_target) @ invert_transform(T_marker_camera)
    )
    delta = invert_transform(T_tracker_marker) @ predicted
    rotation = Rotation.from_matrix(delta[:, :3, :3]).as_rotvec()
    return np.concatenate([rotation, delta[:, :3, 3]], axis=-1)


@dataclass(frozen=True)
class TrackerNoise:
    """RMS tracker error (norm over the three axes): degrees and millimetres."""

    rotation_deg: float = 0.1
    translation_mm: float = 0.25

    @classmethod
    def from_residuals(cls, residuals: np.ndarray) -> TrackerNoise:
        """RMS norms of (N, 6) :func:`tracker_residuals`, floored at 1e-5° / 1e-5 mm."""
        rotation_deg = float(np.degrees(np.sqrt(np.mean(np.sum(residuals[:, :3] ** 2, axis=-1)))))
        translation_mm = 1e3 * float(np.sqrt(np.mean(np.sum(residuals[:, 3:] ** 2, axis=-1))))
        return cls(max(rotation_deg, 1e-5), max(translation_mm, 1e-5))

    def whiten(self, residuals: np.ndarray) -> np.ndarray:
        """(N, 6) residuals divided by the per-axis standard deviation."""
        sigma_rotation = math.radians(self.rotation_deg) / math.sqrt(3.0)
        sigma_translation = 1e-3 * self.translation_mm / math.sqrt(3.0)
        return residuals / np.array([sigma_rotation] * 3 + [sigma_translation] * 3)


def _robust_inliers(errors: np.ndarray, floor: float) -> np.ndarray:
    median = float(np.median(errors))
    mad = 1.4826 * float(np.median(np.abs(errors - median)))
    return errors <= max(median + 4.0 * mad, 2.0 * median, floor)


# -- non-linear refinement ----------------------------------------------------------------


def _pack(X: np.ndarray, W: np.ndarray) -> np.ndarray:
    return np.concatenate(
        [
            Rotation.from_matrix(X[:3, :3]).as_rotvec(),
            X[:3, 3] * 1e3,
            Rotation.from_matrix(W[:3, :3]).as_rotvec(),
            W[:3, 3] * 1e3,
        ]
    )


def _unpack(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # the inverse of _pack: rotation vectors (rad) and translations (mm)
    return (
        rigid_transform(params[0:3], params[3:6] * 1e-3),
        rigid_transform(params[6:9], params[9:12] * 1e-3),
    )


def refine_hand_eye(
    T_tracker_marker: np.ndarray,
    T_camera_target: np.ndarray,
    T_marker_camera: np.ndarray,
    T_tracker_target: np.ndarray,
    noise: TrackerNoise,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares refinement of X and W on the noise-weighted tracker residuals.

    ``T_tracker_marker``, ``T_camera_target``: (N, 4, 4); X, W: (4, 4)
    starting values. Minimises Σ |whiten(tracker_residuals)|² over the six
    parameters of each of X and W. Returns (X, W, mean squared whitened
    residual per degree of freedom; about 1 when ``noise`` is right).
    """

    def residuals(params: np.ndarray) -> np.ndarray:
        X, W = _unpack(params)
        return noise.whiten(tracker_residuals(T_tracker_marker, T_camera_target, X, W)).ravel()

    start = _pack(T_marker_camera, T_tracker_target)
    solution = least_squares(residuals, start, method="lm", xtol=1e-12, ftol=1e-12)
    X, W = _unpack(solution.x)
    return X, W, float(np.mean(solution.fun**2))


def reprojection_residuals(
    T_tracker_marker: np.ndarray,
    corners: np.ndarray,
    object_points: np.ndarray,
    camera: CameraModel,
    T_marker_camera: np.ndarray,
    T_tracker_target: np.ndarray,
) -> np.ndarray:
    """Corner residuals (N, K, 2) pixels of the board predicted through the tracker.

    The board pose in view i is predicted as ``X⁻¹ A_i⁻¹ W`` and its corners
    (K, 3) projected with ``camera``; ``corners`` (N, K, 2) are the
    detections. Points behind the camera give NaN.
    """
    predicted = (
        invert_transform(T_marker_camera) @ invert_transform(T_tracker_marker) @ T_tracker_target
    )
    points = (
        np.einsum("nij,kj->nki", predicted[:, :3, :3], object_points) + predicted[:, None, :3, 3]
    )
    return camera.project(points) - corners


# -- the whole calibration --------------------------------------------------------------


@dataclass(frozen=True)
class HandEyeResult:
    """Outcome of :func:`calibrate_hand_eye`.

    Residuals are over the views kept: ``translation_rms_mm`` and
    ``rotation_rms_deg`` are the RMS differences between each measured marker
    pose and the one the calibration predicts from the board view;
    ``reprojection_rms_px`` is the RMS corner error of the board projected
    through tracker and calibration. ``closed_form`` holds each closed-form
    method's residuals before refinement. Per view (N board views, in their
    order): ``view_stamps_ns``, ``view_used`` (False: rejected as an outlier
    or without tracker poses around it), ``view_reprojection_px`` (RMS corner
    error), ``view_translation_mm`` and ``view_rotation_deg`` (tracker
    residual), NaN without tracker poses; ``corner_residuals_px``: the
    corner error magnitudes of the views used.
    """

    T_marker_camera: np.ndarray
    T_tracker_target: np.ndarray
    time_offset_ns: int
    reprojection_rms_px: float
    translation_rms_mm: float
    rotation_rms_deg: float
    method: str
    views_used: int
    views_total: int
    closed_form: dict[str, dict[str, float]]
    coarse_offsets_ms: list[float]
    coarse_costs: list[float]
    view_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    view_used: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    view_reprojection_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    view_translation_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    view_rotation_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    corner_residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class OffsetSearch:
    """Clock offset search: ``[low_ns, high_ns]`` with a coarse grid step, all ns."""

    low_ns: int = -200 * MS
    high_ns: int = 200 * MS
    step_ns: int = 4 * MS


@dataclass
class _Fit:
    A: np.ndarray
    mask: np.ndarray
    forms: dict[str, tuple[np.ndarray, TrackerNoise, float]]
    best: str
    X: np.ndarray
    W: np.ndarray
    cost: float


class _Problem:
    """Views and tracker stream, evaluated at any clock offset."""

    def __init__(
        self,
        views: list[BoardView],
        tracker_stamps_ns: np.ndarray,
        tracker_poses: np.ndarray,
        max_gap_ns: int,
        coarse_views: int,
    ) -> None:
        self.stamps = np.array([v.stamp_ns for v in views], dtype=np.int64)
        self.B = np.stack([v.T_camera_target for v in views])
        self.tracker_stamps = np.asarray(tracker_stamps_ns, dtype=np.int64)
        self.tracker_poses = np.asarray(tracker_poses, dtype=np.float64)
        self.max_gap_ns = max_gap_ns
        self.coarse_subset = np.unique(np.linspace(0, len(views) - 1, coarse_views).astype(int))

    def marker_poses(
        self, offset_ns: int, subset: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        stamps = self.stamps if subset is None else self.stamps[subset]
        return marker_poses_at(
            self.tracker_stamps, self.tracker_poses, stamps + offset_ns, self.max_gap_ns
        )

    def coarse_cost(self, offset_ns: int, noise: TrackerNoise) -> float:
        """Median squared whitened residual after a Park closed form, on a subset of views."""
        A, valid = self.marker_poses(offset_ns, self.coarse_subset)
        B = self.B[self.coarse_subset][valid]
        if valid.sum() < 5:
            return math.inf
        try:
            X = solve_hand_eye(A[valid], B, "park")
        except (HandEyeError, np.linalg.LinAlgError, ValueError):
            return math.inf
        W = target_pose(A[valid], X, B)
        whitened = noise.whiten(tracker_residuals(A[valid], B, X, W))
        return float(np.median(np.sum(whitened**2, axis=-1)))

    def closed_forms(
        self, A: np.ndarray, mask: np.ndarray, noise: TrackerNoise
    ) -> dict[str, tuple[np.ndarray, TrackerNoise, float]]:
        """Each method's X, its residual RMS (as TrackerNoise) and whitened cost."""
        results = {}
        for method in METHODS:
            try:
                X = solve_hand_eye(A[mask], self.B[mask], method)
            except (HandEyeError, np.linalg.LinAlgError, ValueError):
                continue
            W = target_pose(A[mask], X, self.B[mask])
            residuals = tracker_residuals(A[mask], self.B[mask], X, W)
            cost = float(np.mean(noise.whiten(residuals) ** 2))
            results[method] = (X, TrackerNoise.from_residuals(residuals), cost)
        if not results:
            raise HandEyeError("no closed-form hand-eye method succeeded")
        return results

    def inliers(
        self, A: np.ndarray, valid: np.ndarray, X: np.ndarray, noise: TrackerNoise
    ) -> np.ndarray:
        """Views whose whitened residual is not an outlier (median + 4 MAD), iterated."""
        mask = valid.copy()
        for _ in range(3):
            W = target_pose(A[mask], X, self.B[mask])
            whitened = noise.whiten(tracker_residuals(A[valid], self.B[valid], X, W))
            keep = _robust_inliers(np.sqrt(np.sum(whitened**2, axis=-1)), floor=3.0)
            new_mask = np.zeros_like(valid)
            new_mask[np.flatnonzero(valid)[keep]] = True
            if new_mask.sum() < 5 or np.array_equal(new_mask, mask):
                break
            mask = new_mask
            X = solve_hand_eye(A[mask], self.B[mask], "park")
        return mask

    def fit(self, offset_ns: int, noise: TrackerNoise) -> _Fit:
        """Closed forms, outlier rejection and refinement at one clock offset."""
        A, valid = self.marker_poses(offset_ns)
        if valid.sum() < 5:
            raise HandEyeError(f"only {int(valid.sum())} views have tracker poses around them")
        forms = self.closed_forms(A, valid, noise)
        best = min(forms, key=lambda m: forms[m][2])
        mask = self.inliers(A, valid, forms[best][0], noise)
        if mask.sum() < 5:
            raise HandEyeError(f"only {int(mask.sum())} views left after outlier rejection")
        X0 = forms[best][0]
        W0 = target_pose(A[mask], X0, self.B[mask])
        X, W, cost = refine_hand_eye(A[mask], self.B[mask], X0, W0, noise)
        return _Fit(A, mask, forms, best, X, W, cost)


def calibrate_hand_eye(
    views: list[BoardView],
    tracker_stamps_ns: np.ndarray,
    tracker_poses: np.ndarray,
    board: Checkerboard,
    camera: CameraModel,
    search: OffsetSearch | None = None,
    max_gap_ns: int = 60 * MS,
    coarse_views: int = 24,
) -> HandEyeResult:
    """Hand–eye transform, board pose and clock offset from board views and tracker poses.

    ``views``: board detections with camera-clock stamps; ``tracker_stamps_ns``
    (M,) int64 tracker stamps; ``tracker_poses`` (M, 4, 4) T_tracker_marker in
    metres; ``search``: range and step of the offset search
    (``OffsetSearch(0, 0)`` fixes the offset at zero); ``max_gap_ns``:
    longest tracker dropout bridged by interpolation; ``coarse_views``: views
    used on the coarse grid (all of them afterwards).
    Raises HandEyeError when fewer than 5 views remain or the views do not
    rotate enough.
    """
    search = search or OffsetSearch()
    if len(views) < 5:
        raise HandEyeError(f"hand-eye needs at least 5 board views, got {len(views)}")
    order = np.argsort(tracker_stamps_ns, kind="stable")
    problem = _Problem(
        views,
        np.asarray(tracker_stamps_ns)[order],
        np.asarray(tracker_poses)[order],
        max_gap_ns,
        coarse_views,
    )

    # 1. coarse grid, with a typical optical tracker's noise as weights
    default_noise = TrackerNoise()
    if search.high_ns > search.low_ns:
        grid = np.arange(search.low_ns, search.high_ns + 1, max(1, search.step_ns), dtype=np.int64)
    else:
        grid = np.array([search.low_ns], dtype=np.int64)
    costs = np.array([problem.coarse_cost(int(o), default_noise) for o in grid])
    if not np.any(np.isfinite(costs)):
        raise HandEyeError("no clock offset in the search range leaves 5 views with tracker poses")
    offset_ns = int(grid[int(np.argmin(costs))])

    # 2.-3. fit at the coarse optimum; the residuals then give this tracker's noise
    fit = problem.fit(offset_ns, default_noise)
    noise = TrackerNoise.from_residuals(
        tracker_residuals(fit.A[fit.mask], problem.B[fit.mask], fit.X, fit.W)
    )

    # 4. fine offset: profile of the refined cost, views and weights fixed
    if len(grid) > 1:
        mask, warm = fit.mask, {"X": fit.X, "W": fit.W}

        def profile(offset_ms: float) -> float:
            A, valid = problem.marker_poses(round(offset_ms * MS))
            use = mask & valid
            if use.sum() < 5:
                return math.inf
            X, W, cost = refine_hand_eye(A[use], problem.B[use], warm["X"], warm["W"], noise)
            warm.update(X=X, W=W)
            return cost

        step_ms = search.step_ns / MS
        low = max(search.low_ns / MS, offset_ns / MS - 2 * step_ms)
        high = min(search.high_ns / MS, offset_ns / MS + 2 * step_ms)
        fine = minimize_scalar(
            profile, bounds=(low, high), method="bounded", options={"xatol": 0.01}
        )
        offset_ns = round(float(fine.x) * MS)
        fit = problem.fit(offset_ns, noise)

    A, B, mask = fit.A[fit.mask], problem.B[fit.mask], fit.mask
    rotation_span = _rotation_span_deg(A)
    if rotation_span < 10.0:
        raise HandEyeError(
            f"the views span only {rotation_span:.1f}° of marker rotation; need >= 10°"
        )
    residual = TrackerNoise.from_residuals(tracker_residuals(A, B, fit.X, fit.W))
    corners = np.stack([v.corners for v, keep in zip(views, mask, strict=True) if keep])
    pixels = reprojection_residuals(A, corners, board.object_points(), camera, fit.X, fit.W)
    per_view = _per_view_residuals(views, fit.A, board, camera, fit.X, fit.W)
    return HandEyeResult(
        T_marker_camera=fit.X,
        T_tracker_target=fit.W,
        time_offset_ns=offset_ns,
        reprojection_rms_px=float(np.sqrt(np.nanmean(np.sum(pixels**2, axis=-1)))),
        translation_rms_mm=residual.translation_mm,
        rotation_rms_deg=residual.rotation_deg,
        method=f"{fit.best} + least-squares",
        views_used=int(mask.sum()),
        views_total=len(views),
        closed_form={
            m: {"translation_rms_mm": r.translation_mm, "rotation_rms_deg": r.rotation_deg}
            for m, (_, r, _) in fit.forms.items()
        },
        coarse_offsets_ms=[float(o) / MS for o in grid],
        coarse_costs=[float(c) for c in costs],
        view_stamps_ns=np.array([v.stamp_ns for v in views], dtype=np.int64),
        view_used=np.asarray(mask, dtype=bool),
        view_reprojection_px=per_view[0],
        view_translation_mm=per_view[1],
        view_rotation_deg=per_view[2],
        corner_residuals_px=np.linalg.norm(pixels, axis=-1).ravel(),
    )


def _per_view_residuals(
    views: list[BoardView],
    T_tracker_marker: np.ndarray,
    board: Checkerboard,
    camera: CameraModel,
    X: np.ndarray,
    W: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) RMS corner error (px), tracker translation (mm) and rotation (°) residual per view.

    NaN for views without a tracker pose (``T_tracker_marker`` NaN there).
    """
    n = len(views)
    reprojection, translation, rotation = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    valid = np.all(np.isfinite(T_tracker_marker.reshape(n, -1)), axis=1)
    if valid.any():
        A = T_tracker_marker[valid]
        B = np.stack([v.T_camera_target for v, ok in zip(views, valid, strict=True) if ok])
        corners = np.stack([v.corners for v, ok in zip(views, valid, strict=True) if ok])
        pixels = reprojection_residuals(A, corners, board.object_points(), camera, X, W)
        reprojection[valid] = np.sqrt(np.nanmean(np.sum(pixels**2, axis=-1), axis=-1))
        residuals = tracker_residuals(A, B, X, W)
        rotation[valid] = np.degrees(np.linalg.norm(residuals[:, :3], axis=-1))
        translation[valid] = 1e3 * np.linalg.norm(residuals[:, 3:], axis=-1)
    return reprojection, translation, rotation


def scaled_views(views: list[BoardView], factor: float) -> list[BoardView]:
    """The views of a board whose squares are ``factor`` times larger (PnP scales t only)."""
    out = []
    for view in views:
        T = view.T_camera_target.copy()
        T[:3, 3] *= factor
        out.append(BoardView(view.stamp_ns, view.corners, T, view.reprojection_rms_px))
    return out


def estimate_square_size(
    views: list[BoardView],
    tracker_stamps_ns: np.ndarray,
    tracker_poses: np.ndarray,
    board: Checkerboard,
    camera: CameraModel,
    search: OffsetSearch | None = None,
    *,
    max_gap_ns: int = 60 * MS,
    bounds_m: tuple[float, float] = (0.5e-3, 50e-3),
) -> float:
    """The board's square side (metres) that makes the tracker and the board views agree.

    PnP with a wrong square size scales each board pose's translation by the
    same factor, so ``A_i X B_i = W`` holds only at the right one: this
    minimises the refined whitened tracker residual over the square size
    (a log-spaced grid over ``bounds_m``, then bounded Brent), at the clock
    offset found with ``board``'s size. ``views`` were solved with ``board``.
    Raises HandEyeError when the calibration fails at every size.
    """
    first = calibrate_hand_eye(
        views, tracker_stamps_ns, tracker_poses, board, camera, search, max_gap_ns=max_gap_ns
    )
    offset_ns = first.time_offset_ns
    order = np.argsort(tracker_stamps_ns, kind="stable")
    stamps = np.asarray(tracker_stamps_ns)[order]
    poses = np.asarray(tracker_poses)[order]
    noise = TrackerNoise()

    def cost(log_square: float) -> float:
        factor = math.exp(log_square) / board.square_m
        problem = _Problem(scaled_views(views, factor), stamps, poses, max_gap_ns, 24)
        try:
            return problem.fit(offset_ns, noise).cost
        except (HandEyeError, np.linalg.LinAlgError, ValueError):
            return math.inf

    grid = np.linspace(math.log(bounds_m[0]), math.log(bounds_m[1]), 41)
    costs = np.array([cost(float(x)) for x in grid])
    if not np.any(np.isfinite(costs)):
        raise HandEyeError("no square size makes the board views agree with the tracker")
    best = int(np.argmin(costs))
    low, high = grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)]
    fine = minimize_scalar(cost, bounds=(low, high), method="bounded", options={"xatol": 1e-4})
    return float(math.exp(fine.x))


def _rotation_span_deg(T: np.ndarray) -> float:
    """Largest rotation angle (degrees) between the first view and any other."""
    relative = np.swapaxes(T[:1, :3, :3], -1, -2) @ T[:, :3, :3]
    return float(np.degrees(np.max(rotation_angle(relative))))
