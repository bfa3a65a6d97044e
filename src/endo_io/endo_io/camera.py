"""Camera model from ``sensor_msgs/CameraInfo`` or camera_calibration YAML.

A :class:`CameraModel` describes one image stream as published: its size,
intrinsics ``K`` and projection ``P`` already adjusted for binning and ROI the
way image_geometry's ``PinholeCameraModel`` does it, and the lens distortion
(``plumb_bob``, ``rational_polynomial``, ``equidistant`` or none).

Conventions (see docs/endo_io.md):

* Pixel centres are at integer coordinates (OpenCV): pixel (u, v) covers
  [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]; u right, v down.
* Rays and 3D points are in the camera's optical frame (REP 103: x right,
  y down, z forward), metres. ``R`` (stereo rectification) is kept for round
  trips but not applied: rays are in the unrectified camera frame.
* Binning/ROI (image_geometry): ``CameraInfo.width/height/K/P`` describe the
  full sensor; the published image has ``roi.width // binning_x`` columns and
  its pixel u sits at full-resolution pixel ``u * binning_x + roi.x_offset``,
  so ``fx' = fx / bx`` and ``cx' = (cx - roi.x_offset) / bx``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header

from endo_io.cdr import decode_plain_cdr, deserialize_with_rclpy
from endo_io.errors import CameraModelError, yaml_error_line
from endo_io.stamp import ns_to_stamp

#: Number of distortion coefficients of each supported ``distortion_model``
#: ("" means no distortion).
DISTORTION_COEFFICIENT_COUNTS: dict[str, int] = {
    "plumb_bob": 5,  # k1, k2, p1, p2, k3
    "rational_polynomial": 8,  # k1, k2, p1, p2, k3, k4, k5, k6
    "equidistant": 4,  # k1, k2, k3, k4 (OpenCV fisheye)
    "": 0,
}

DEFAULT_FRAME_ID = "endoscope_optical_frame"
DEFAULT_CAMERA_NAME = "endoscope"

# Undistortion is solved to this residual in normalised image coordinates
# (1e-12 x a 1000 px focal length = 1e-9 px).
_UNDISTORT_TOLERANCE = 1e-12
_NEWTON_MAX_ITERATIONS = 30


def _read_only(values: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.array(values, dtype=np.float64)
    if arr.shape != shape:
        raise CameraModelError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CameraModelError(f"{name} contains NaN or infinity")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics and distortion of one published image stream.

    Attributes:
        width, height: size in pixels of the image as published (after
            binning and ROI).
        K: (3, 3) float64 intrinsics of the published image, pixels.
        D: (n,) float64 distortion coefficients, ROS order.
        distortion_model: "plumb_bob", "rational_polynomial", "equidistant"
            or "" (none).
        R: (3, 3) rectification rotation (identity for a monocular camera).
        P: (3, 4) projection of the published image; passing an empty array
            gives ``[K | 0]``.
        binning_x, binning_y: binning factors (0 is read as 1, as in ROS).
        roi: (x_offset, y_offset, width, height) in full-sensor pixels;
            (0, 0, 0, 0) means the full sensor and is replaced by it.
        frame_id: optical frame of the images.
        camera_name: name written to calibration YAML.
        full_width, full_height: sensor size the calibration refers to
            (``CameraInfo.width/height``); 0 means derive it from the ROI, or
            from ``width * binning_x`` when the ROI is the full sensor.

    Raises:
        CameraModelError: non-positive focal length, a K that is not upper
            triangular with K[2, 2] = 1, an unknown distortion model, a D of
            the wrong length, non-finite values, or sizes that disagree with
            binning and ROI.
    """

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(0))
    distortion_model: str = ""
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    binning_x: int = 1
    binning_y: int = 1
    roi: tuple[int, int, int, int] = (0, 0, 0, 0)
    frame_id: str = DEFAULT_FRAME_ID
    camera_name: str = DEFAULT_CAMERA_NAME
    full_width: int = 0
    full_height: int = 0
    _cache: dict[str, np.ndarray] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        def put(name: str, value: Any) -> None:
            object.__setattr__(self, name, value)

        width, height = int(self.width), int(self.height)
        if width <= 0 or height <= 0:
            raise CameraModelError(f"image size must be positive, got {width}x{height}")
        put("width", width)
        put("height", height)

        K = _read_only(self.K, (3, 3), "K")
        if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
            raise CameraModelError(
                f"focal lengths must be positive, got fx={K[0, 0]:g} fy={K[1, 1]:g}"
            )
        if K[1, 0] != 0.0 or K[2, 0] != 0.0 or K[2, 1] != 0.0 or K[2, 2] != 1.0:
            raise CameraModelError(
                f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
            )
        put("K", K)

        if self.distortion_model not in DISTORTION_COEFFICIENT_COUNTS:
            raise CameraModelError(
                f"unsupported distortion model {self.distortion_model!r}; supported: "
                f"{sorted(DISTORTION_COEFFICIENT_COUNTS)}"
            )
        D = np.array(self.D, dtype=np.float64).reshape(-1)
        expected = DISTORTION_COEFFICIENT_COUNTS[self.distortion_model]
        if D.size != expected and not (self.distortion_model == "" and not np.any(D)):
            raise CameraModelError(
                f"distortion model {self.distortion_model!r} needs {expected} coefficients, "
                f"got {D.size}"
            )
        put("D", _read_only(D, D.shape, "D"))
        put("R", _read_only(self.R, (3, 3), "R"))
        P = np.asarray(self.P, dtype=np.float64)
        put("P", _read_only(np.hstack([K, np.zeros((3, 1))]) if P.size == 0 else P, (3, 4), "P"))

        bx, by = int(self.binning_x) or 1, int(self.binning_y) or 1
        if bx < 0 or by < 0:
            raise CameraModelError(f"binning must be >= 0, got {self.binning_x}x{self.binning_y}")
        put("binning_x", bx)
        put("binning_y", by)

        if len(self.roi) != 4 or any(int(v) < 0 for v in self.roi):
            raise CameraModelError(f"roi must be 4 non-negative integers, got {self.roi}")
        rx, ry, rw, rh = (int(v) for v in self.roi)
        full_roi = rx == ry == rw == rh == 0
        full_w = int(self.full_width) or (width * bx if full_roi else rx + rw)
        full_h = int(self.full_height) or (height * by if full_roi else ry + rh)
        if full_roi:
            rw, rh = full_w, full_h
        if rw == 0 or rh == 0 or rx + rw > full_w or ry + rh > full_h:
            raise CameraModelError(
                f"roi (x={rx}, y={ry}, w={rw}, h={rh}) is empty or outside the "
                f"{full_w}x{full_h} sensor"
            )
        if (rw // bx, rh // by) != (width, height):
            raise CameraModelError(
                f"image size {width}x{height} does not match roi {rw}x{rh} binned "
                f"{bx}x{by} = {rw // bx}x{rh // by}"
            )
        put("roi", (rx, ry, rw, rh))
        put("full_width", full_w)
        put("full_height", full_h)
        put("frame_id", str(self.frame_id))
        put("camera_name", str(self.camera_name))

    # ------------------------------------------------------------------ construction

    @classmethod
    def pinhole(
        cls,
        width: int,
        height: int,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        D: np.ndarray | None = None,
        distortion_model: str = "plumb_bob",
        frame_id: str = DEFAULT_FRAME_ID,
    ) -> CameraModel:
        """Return a model of a ``width`` x ``height`` image with no binning or ROI.

        ``fx, fy, cx, cy`` are pixels; ``D`` defaults to zeros of the model's
        length.
        """
        if D is None:
            D = np.zeros(DISTORTION_COEFFICIENT_COUNTS.get(distortion_model, 0))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(width, height, K, np.asarray(D), distortion_model, frame_id=frame_id)

    @classmethod
    def from_camera_info(cls, msg: CameraInfo) -> CameraModel:
        """Return the model of the images a ``CameraInfo`` describes.

        ``msg.k``/``msg.p`` (full sensor) are adjusted for binning and ROI as
        image_geometry does; ``msg.r`` and ``msg.d`` are kept as they are.

        Raises:
            CameraModelError: see :class:`CameraModel` (an uncalibrated
                camera's all-zero K fails the focal length check).
        """
        bx, by = int(msg.binning_x) or 1, int(msg.binning_y) or 1
        roi = (
            int(msg.roi.x_offset), int(msg.roi.y_offset), int(msg.roi.width), int(msg.roi.height)
        )
        full_w, full_h = int(msg.width), int(msg.height)
        if full_w == 0 or full_h == 0:
            raise CameraModelError(f"CameraInfo has zero size {full_w}x{full_h}")
        roi_w, roi_h = (full_w, full_h) if roi == (0, 0, 0, 0) else roi[2:]
        K_full = _read_only(np.reshape(msg.k, (3, 3)), (3, 3), "CameraInfo.k")
        P_full = _read_only(np.reshape(msg.p, (3, 4)), (3, 4), "CameraInfo.p")
        return cls(
            width=roi_w // bx,
            height=roi_h // by,
            K=_to_published(K_full, bx, by, roi[0], roi[1]),
            D=np.asarray(msg.d, dtype=np.float64),
            distortion_model=msg.distortion_model,
            R=np.asarray(msg.r, dtype=np.float64).reshape(3, 3),
            P=_to_published(P_full, bx, by, roi[0], roi[1]),
            binning_x=bx,
            binning_y=by,
            roi=roi,
            frame_id=msg.header.frame_id,
            full_width=full_w,
            full_height=full_h,
        )

    def to_camera_info(self, stamp_ns: int = 0) -> CameraInfo:
        """Return this model as a ``CameraInfo`` (full-sensor K/P, binning, ROI).

        No binning is written as 0 and a full-sensor ROI as all zeros, the
        values ROS drivers publish. ``from_camera_info(m.to_camera_info())``
        equals ``m``; the reverse is exact for power-of-two binning.
        """
        msg = CameraInfo()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.header.frame_id = self.frame_id
        msg.width, msg.height = self.full_width, self.full_height
        msg.distortion_model = self.distortion_model
        msg.d = self.D.tolist()
        msg.k = self.K_full.ravel()
        msg.r = self.R.ravel().copy()
        msg.p = self.P_full.ravel()
        msg.binning_x = 0 if self.binning_x == 1 else self.binning_x
        msg.binning_y = 0 if self.binning_y == 1 else self.binning_y
        if self.roi != (0, 0, self.full_width, self.full_height):
            r = msg.roi
            r.x_offset, r.y_offset, r.width, r.height = self.roi
        return msg

    @classmethod
    def load_yaml(cls, path: str | Path, frame_id: str = DEFAULT_FRAME_ID) -> CameraModel:
        """Load a camera_calibration / camera_info_manager YAML file.

        The file describes the full sensor (no binning or ROI).

        Raises:
            CameraModelError: unparsable YAML, a missing key, a matrix whose
                rows x cols disagree with its data, or an invalid model.
        """
        try:
            doc = yaml.safe_load(Path(path).read_text())
        except yaml.YAMLError as exc:
            raise CameraModelError(f"{path}: not valid YAML ({yaml_error_line(exc)})") from None
        if not isinstance(doc, dict):
            raise CameraModelError(f"{path}: expected a YAML mapping of calibration keys")

        def matrix(key: str) -> np.ndarray:
            node = doc.get(key)
            if not isinstance(node, dict) or not {"rows", "cols", "data"} <= node.keys():
                raise CameraModelError(f"{path}: {key} needs rows, cols and data")
            rows, cols, data = int(node["rows"]), int(node["cols"]), node["data"]
            try:
                values = np.array(data, dtype=np.float64)
            except (TypeError, ValueError):
                raise CameraModelError(f"{path}: {key} data is not a list of numbers") from None
            if values.ndim != 1 or values.size != rows * cols:
                raise CameraModelError(
                    f"{path}: {key} has {values.size} values for {rows}x{cols}"
                )
            return values.reshape(rows, cols)

        for key in ("image_width", "image_height", "distortion_model"):
            if key not in doc:
                raise CameraModelError(f"{path}: missing {key}")
        width, height = int(doc["image_width"]), int(doc["image_height"])
        K = matrix("camera_matrix")
        return cls(
            width=width,
            height=height,
            K=K,
            D=matrix("distortion_coefficients").ravel(),
            distortion_model=str(doc["distortion_model"] or ""),
            R=matrix("rectification_matrix") if "rectification_matrix" in doc else np.eye(3),
            P=matrix("projection_matrix") if "projection_matrix" in doc else np.zeros((0, 4)),
            frame_id=frame_id,
            camera_name=str(doc.get("camera_name", DEFAULT_CAMERA_NAME) or ""),
        )

    def save_yaml(self, path: str | Path) -> None:
        """Write the full-sensor calibration in camera_calibration's YAML layout.

        Numbers are written with enough digits to read back bit-exactly.
        Binning and ROI are properties of a stream, not of the calibration,
        and are not part of this format.
        """
        lines = [
            f"image_width: {self.full_width}",
            f"image_height: {self.full_height}",
            f"camera_name: {_yaml_name(self.camera_name)}",
            *_yaml_matrix("camera_matrix", self.K_full),
            f"distortion_model: {_yaml_name(self.distortion_model)}",
            *_yaml_matrix("distortion_coefficients", self.D.reshape(1, -1)),
            *_yaml_matrix("rectification_matrix", self.R),
            *_yaml_matrix("projection_matrix", self.P_full),
        ]
        Path(path).write_text("\n".join(lines) + "\n")

    def resized(self, width: int, height: int) -> CameraModel:
        """Return the model of this stream resampled to ``width`` x ``height``.

        The pixel mapping is the one ``cv2.resize`` uses with pixel centres
        at integers: ``u' = (u + 0.5) * width / self.width - 0.5`` (same for
        v), so ``cx' = (cx + 0.5) * sx - 0.5``. The result has no binning or
        ROI: its sensor is the resized image.

        Raises:
            CameraModelError: non-positive size, or an aspect ratio that
                differs by more than one pixel of rounding.
        """
        if width <= 0 or height <= 0:
            raise CameraModelError(f"resized size must be positive, got {width}x{height}")
        sx, sy = width / self.width, height / self.height
        if abs(sx - sy) * max(self.width, self.height) > 1.0 + 1e-9:
            raise CameraModelError(
                f"resizing {self.width}x{self.height} to {width}x{height} changes the "
                "aspect ratio"
            )
        A = np.array([[sx, 0.0, (sx - 1.0) / 2.0], [0.0, sy, (sy - 1.0) / 2.0], [0.0, 0.0, 1.0]])
        return CameraModel(
            width=width,
            height=height,
            K=A @ self.K,
            D=self.D,
            distortion_model=self.distortion_model,
            R=self.R,
            P=A @ self.P,
            frame_id=self.frame_id,
            camera_name=self.camera_name,
        )

    # ------------------------------------------------------------------ properties

    @property
    def fx(self) -> float:
        """Horizontal focal length of the published image, pixels."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Vertical focal length of the published image, pixels."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point column in the published image, pixels."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point row in the published image, pixels."""
        return float(self.K[1, 2])

    @property
    def K_full(self) -> np.ndarray:
        """(3, 3) intrinsics of the full sensor (``CameraInfo.k``)."""
        return _to_full(self.K, self.binning_x, self.binning_y, self.roi[0], self.roi[1])

    @property
    def P_full(self) -> np.ndarray:
        """(3, 4) projection of the full sensor (``CameraInfo.p``)."""
        return _to_full(self.P, self.binning_x, self.binning_y, self.roi[0], self.roi[1])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        names = [
            "width", "height", "distortion_model", "binning_x", "binning_y", "roi",
            "frame_id", "camera_name", "full_width", "full_height",
        ]
        return all(getattr(self, n) == getattr(other, n) for n in names) and all(
            np.array_equal(getattr(self, n), getattr(other, n)) for n in ("K", "D", "R", "P")
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-looking arrays inside

    # ------------------------------------------------------------------ geometry

    def pixels_to_rays(self, pixels: np.ndarray) -> np.ndarray:
        """Return unit rays through pixel positions, distortion undone.

        Args:
            pixels: (..., 2) float pixel coordinates (u, v) in the published
                image (centres at integers).

        Returns:
            (..., 3) float64 unit vectors in the optical frame (z forward).
            NaN where the distortion model has no inverse (outside the
            region where it is one-to-one).
        """
        uv = np.asarray(pixels, dtype=np.float64)
        if uv.shape[-1:] != (2,):
            raise CameraModelError(f"pixels must have shape (..., 2), got {uv.shape}")
        flat = uv.reshape(-1, 2)
        # normalised *distorted* coordinates: K^-1 [u, v, 1]
        yd = (flat[:, 1] - self.K[1, 2]) / self.K[1, 1]
        xd = (flat[:, 0] - self.K[0, 2] - self.K[0, 1] * yd) / self.K[0, 0]
        if self.distortion_model == "equidistant":
            rays = self._equidistant_rays(flat, xd, yd)
        elif not np.any(self.D):  # pinhole: no iteration needed
            rays = np.stack([xd, yd, np.ones_like(xd)], axis=-1)
        else:
            rays = self._radial_tangential_rays(flat, xd, yd)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        return rays.reshape(*uv.shape[:-1], 3)

    def unit_rays(self) -> np.ndarray:
        """Return the unit ray of every pixel of the published image.

        Returns:
            (height, width, 3) float64, read-only, unit vectors in the optical
            frame; ``rays[v, u]`` belongs to pixel centre (u, v). NaN where the
            distortion has no inverse. Computed once per model and cached.
        """
        rays = self._cache.get("unit_rays")
        if rays is None:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
            rays = self.pixels_to_rays(np.stack([u, v], axis=-1))
            rays.setflags(write=False)
            self._cache["unit_rays"] = rays
        return rays

    def depth_to_points(self, depth: np.ndarray) -> np.ndarray:
        """Back-project a REP 118 depth image to points in the optical frame.

        Each pixel's point is its unit ray scaled so that its z equals the
        depth: ``p = depth / ray_z · ray`` (through :meth:`unit_rays`, so
        distortion is undone exactly as everywhere else).

        Args:
            depth: (height, width) float depth along the optical axis, metres
                (or any unit: the points come out in the same unit); NaN,
                zero or negative where invalid.

        Returns:
            (height, width, 3) float64 points, NaN where the depth is invalid
            or the pixel has no ray.

        Raises:
            CameraModelError: ``depth`` is not (height, width).
        """
        z = np.asarray(depth, dtype=np.float64)
        if z.shape != (self.height, self.width):
            raise CameraModelError(
                f"depth is {z.shape[::-1] if z.ndim == 2 else z.shape}, camera is "
                f"{self.width}x{self.height}"
            )
        rays = self.unit_rays()
        with np.errstate(invalid="ignore", divide="ignore"):
            length = np.where(z > 0.0, z / rays[..., 2], np.nan)
        return length[..., None] * rays

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project 3D points to distorted pixel coordinates.

        Args:
            points: (..., 3) metres in the optical frame.

        Returns:
            (..., 2) float64 pixel coordinates (u, v) in the published image,
            distortion applied; NaN for points with z <= 0 or non-finite.
        """
        xyz = np.asarray(points, dtype=np.float64)
        if xyz.shape[-1:] != (3,):
            raise CameraModelError(f"points must have shape (..., 3), got {xyz.shape}")
        X, Y, Z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            in_front = Z > 0.0
            if self.distortion_model == "equidistant":
                r = np.hypot(X, Y)
                theta = np.arctan2(r, Z)
                scale = np.where(r > 0.0, _equidistant_theta_d(theta, self.D) / r, 1.0 / Z)
                xd, yd = X * scale, Y * scale
            else:
                xd, yd = _radial_tangential(X / Z, Y / Z, self.D)
        u = self.K[0, 0] * xd + self.K[0, 1] * yd + self.K[0, 2]
        v = self.K[1, 1] * yd + self.K[1, 2]
        uv = np.stack([u, v], axis=-1)
        uv[~in_front] = np.nan
        return uv

    def fov_mask(self, radius_px: float | None = None) -> np.ndarray:
        """Return a circular field-of-view mask centred on the principal point.

        Args:
            radius_px: radius in published-image pixels; None for the whole
                image.

        Returns:
            (height, width) bool, True inside the circle (pixel centres at
            distance <= radius from (cx, cy)).
        """
        if radius_px is None:
            return np.ones((self.height, self.width), dtype=bool)
        if not radius_px > 0.0:
            raise CameraModelError(f"field-of-view radius must be positive, got {radius_px}")
        du = (np.arange(self.width) - self.cx) ** 2
        dv = (np.arange(self.height) - self.cy) ** 2
        return dv[:, None] + du[None, :] <= radius_px * radius_px

    # ------------------------------------------------------------------ undistortion

    def _radial_tangential_rays(
        self, pixels: np.ndarray, xd: np.ndarray, yd: np.ndarray
    ) -> np.ndarray:
        """plumb_bob / rational_polynomial: OpenCV's estimate, refined by Newton."""
        guess = cv2.undistortPoints(pixels.reshape(-1, 1, 2), self.K, self.D).reshape(-1, 2)
        x = np.where(np.isfinite(guess[:, 0]), guess[:, 0], xd)
        y = np.where(np.isfinite(guess[:, 1]), guess[:, 1], yd)
        active = np.arange(x.size)
        for _ in range(_NEWTON_MAX_ITERATIONS):
            xa, ya = x[active], y[active]
            fx_, fy_, j00, j01, j11, _ = _radial_tangential_with_jacobian(xa, ya, self.D)
            rx, ry = fx_ - xd[active], fy_ - yd[active]
            with np.errstate(invalid="ignore"):
                moving = ~(np.hypot(rx, ry) < _UNDISTORT_TOLERANCE)
            active, xa, ya = active[moving], xa[moving], ya[moving]
            if active.size == 0:
                break
            rx, ry, j00, j01, j11 = rx[moving], ry[moving], j00[moving], j01[moving], j11[moving]
            det = j00 * j11 - j01 * j01
            with np.errstate(divide="ignore", invalid="ignore"):
                x[active] = xa - (j11 * rx - j01 * ry) / det
                y[active] = ya - (j00 * ry - j01 * rx) / det
        fx_, fy_, j00, j01, j11, scale = _radial_tangential_with_jacobian(x, y, self.D)
        with np.errstate(invalid="ignore"):
            valid = (
                (np.hypot(fx_ - xd, fy_ - yd) < _UNDISTORT_TOLERANCE)
                & (scale > 0.0)  # not folded through the centre
                & (j00 * j11 - j01 * j01 > 0.0)  # inside the one-to-one region
            )
        rays = np.stack([x, y, np.ones_like(x)], axis=-1)
        rays[~valid] = np.nan
        return rays

    def _equidistant_rays(self, pixels: np.ndarray, xd: np.ndarray, yd: np.ndarray) -> np.ndarray:
        """equidistant: solve theta_d(theta) = |(xd, yd)| by Newton from OpenCV's estimate."""
        theta_d = np.hypot(xd, yd)
        guess = cv2.fisheye.undistortPoints(pixels.reshape(-1, 1, 2), self.K, self.D).reshape(-1, 2)
        theta = np.arctan(np.hypot(guess[:, 0], guess[:, 1]))
        theta = np.where(np.isfinite(theta), theta, theta_d)
        active = np.arange(theta.size)
        for _ in range(_NEWTON_MAX_ITERATIONS):
            ta = theta[active]
            residual = _equidistant_theta_d(ta, self.D) - theta_d[active]
            with np.errstate(invalid="ignore"):
                moving = ~(np.abs(residual) < _UNDISTORT_TOLERANCE)
            active, ta, residual = active[moving], ta[moving], residual[moving]
            if active.size == 0:
                break
            with np.errstate(divide="ignore", invalid="ignore"):
                theta[active] = ta - residual / _equidistant_slope(ta, self.D)
        with np.errstate(invalid="ignore"):
            valid = (
                (np.abs(_equidistant_theta_d(theta, self.D) - theta_d) < _UNDISTORT_TOLERANCE)
                & (_equidistant_slope(theta, self.D) > 0.0)  # one-to-one region
                & (theta >= 0.0)
                & (theta < np.pi)
            )
        with np.errstate(divide="ignore", invalid="ignore"):
            direction_scale = np.where(theta_d > 0.0, np.sin(theta) / theta_d, 0.0)
        rays = np.stack([xd * direction_scale, yd * direction_scale, np.cos(theta)], axis=-1)
        rays[~valid] = np.nan
        return rays


# ---------------------------------------------------------------------- helpers


@dataclass(frozen=True)
class CameraInfoView:
    """A serialized ``sensor_msgs/CameraInfo`` with its header read (:func:`camera_info_from_cdr`).

    Attributes:
        header: the message's header (stamp, frame_id).
        data: the serialized message; :class:`CameraInfoCache` gives its model.
    """

    header: Header
    data: bytes

    @property
    def camera_bytes(self) -> bytes:
        """The bytes that describe the camera: all of ``data`` but the stamp (bytes 4–12)."""
        return bytes(self.data[:4]) + bytes(self.data[12:])


def camera_info_from_cdr(data: bytes) -> CameraInfo | CameraInfoView:
    """Read the header of a serialized ``sensor_msgs/CameraInfo``; keep the rest as bytes.

    A camera sends the same CameraInfo with every frame, only its stamp
    changing: a node that pairs it with its frames by stamp needs the header
    at each, and the model only when the camera changes, which
    :class:`CameraInfoCache` sees from the bytes after the stamp. rclpy's
    message object (~0.03–0.07 ms, its nine-element arrays included) is then
    built once per camera, not once per frame.

    Args:
        data: the serialized message, its 4-byte encapsulation header first.

    Returns:
        A :class:`CameraInfoView` (with the header rclpy would give, tested),
        or a ``CameraInfo`` for another encapsulation than plain CDR
        (:func:`endo_io.cdr.decode_plain_cdr`).

    Raises:
        UndecodableMessageError: not CDR, or the bytes end inside the header.
    """
    return decode_plain_cdr(data, CameraInfo, lambda cdr: CameraInfoView(cdr.header(), data))


class CameraInfoCache:
    """The model of a stream's CameraInfo, rebuilt only when the message describes another camera.

    A node gets a CameraInfo with every frame. Building the model costs
    ~0.03 ms, but a new model rebuilds its ray table at its first
    :meth:`CameraModel.unit_rays` (~100 ms for 640x480 plumb_bob); the cache's
    answer for the same camera (the message's fields compared) ~0.003 ms
    (bench/bench_bag_checks.py). The cached model keeps its ray table. The
    header's frame_id is part of the camera (the model carries it); its
    stamp is not. A :class:`CameraInfoView` is compared by its bytes after
    the stamp, and deserialised (rclpy) only when they differ from the
    previous message's.

    Attributes:
        model: the last model (None before the first message).
    """

    def __init__(self) -> None:
        self.model: CameraModel | None = None
        self._key: Any = None

    def model_of(self, msg: CameraInfo | CameraInfoView) -> tuple[CameraModel, bool]:
        """(the model of ``msg``, whether it differs from the previous message's).

        Raises:
            CameraModelError: as :meth:`CameraModel.from_camera_info`.
            UndecodableMessageError: a :class:`CameraInfoView` whose bytes
                do not decode as a CameraInfo.
        """
        if isinstance(msg, CameraInfoView):
            key: Any = msg.camera_bytes
            if self.model is not None and key == self._key:
                return self.model, False
            msg = deserialize_with_rclpy(msg.data, CameraInfo)
        else:
            roi = msg.roi
            key = (msg.width, msg.height, msg.distortion_model, tuple(msg.d), tuple(msg.k),
                   tuple(msg.r), tuple(msg.p), msg.binning_x, msg.binning_y, roi.x_offset,
                   roi.y_offset, roi.width, roi.height, msg.header.frame_id)
            if self.model is not None and key == self._key:
                return self.model, False
        model = CameraModel.from_camera_info(msg)
        changed = self.model is None or model != self.model
        self.model, self._key = model, key
        return model, changed


def _to_published(M: np.ndarray, bx: int, by: int, rx: int, ry: int) -> np.ndarray:
    """Full-sensor K (3,3) or P (3,4) -> published image (image_geometry's formulas)."""
    out = np.array(M, dtype=np.float64)
    out[0] = (M[0] - rx * M[2]) / bx
    out[1] = (M[1] - ry * M[2]) / by
    return out


def _to_full(M: np.ndarray, bx: int, by: int, rx: int, ry: int) -> np.ndarray:
    """Inverse of :func:`_to_published`."""
    out = np.array(M, dtype=np.float64)
    out[0] = M[0] * bx + rx * M[2]
    out[1] = M[1] * by + ry * M[2]
    return out


def _radial_tangential(
    x: np.ndarray, y: np.ndarray, D: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Apply plumb_bob / rational_polynomial distortion to normalised (x, y)."""
    xd, yd, *_ = _radial_tangential_with_jacobian(x, y, D)
    return xd, yd


def _radial_tangential_with_jacobian(
    x: np.ndarray, y: np.ndarray, D: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Distorted (xd, yd), Jacobian entries (d xd/dx, d xd/dy = d yd/dx, d yd/dy), radial scale.

    OpenCV's model with D = (k1, k2, p1, p2[, k3[, k4, k5, k6]]):
    ``c = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)``,
    ``xd = x c + 2 p1 x y + p2 (r2 + 2 x^2)``,
    ``yd = y c + p1 (r2 + 2 y^2) + 2 p2 x y``.
    """
    k = np.zeros(8)
    k[: min(D.size, 8)] = D[:8]
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    r2 = x * x + y * y
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    scale = num / den
    d_num = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3)
    d_den = k4 + r2 * (2.0 * k5 + r2 * 3.0 * k6)
    d_scale = (d_num * den - num * d_den) / (den * den)  # d scale / d r2
    xy = x * y
    xd = x * scale + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = y * scale + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    j00 = scale + 2.0 * x * x * d_scale + 2.0 * p1 * y + 6.0 * p2 * x
    j01 = 2.0 * xy * d_scale + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = scale + 2.0 * y * y * d_scale + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, j00, j01, j11, scale


def _equidistant_theta_d(theta: np.ndarray, D: np.ndarray) -> np.ndarray:
    """OpenCV fisheye: theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)."""
    k1, k2, k3, k4 = D
    t2 = theta * theta
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def _equidistant_slope(theta: np.ndarray, D: np.ndarray) -> np.ndarray:
    """d theta_d / d theta of the OpenCV fisheye model."""
    k1, k2, k3, k4 = D
    t2 = theta * theta
    return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))


def _yaml_float(value: float) -> str:
    """Shortest exact repr, with a '.' in the mantissa so YAML 1.1 reads a float."""
    text = repr(float(value))
    mantissa, sep, exponent = text.partition("e")
    if sep and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


def _yaml_name(name: str) -> str:
    """camera_calibration writes names bare; quote one only when YAML would misread it."""
    try:
        if name and "\n" not in name and yaml.safe_load(f"k: {name}") == {"k": name}:
            return name
    except yaml.YAMLError:
        pass
    return json.dumps(name)  # a JSON string is a valid YAML double-quoted scalar


def _yaml_matrix(name: str, M: np.ndarray) -> list[str]:
    rows, cols = M.shape
    body = ",\n        ".join(", ".join(_yaml_float(v) for v in row) for row in M)
    return [f"{name}:", f"  rows: {rows}", f"  cols: {cols}", f"  data: [{body}]"]
