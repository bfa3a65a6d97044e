"""``sfs`` node: linear irradiance in, relative depth out, one frame at a time.

Subscribes ``image_corrected`` (sensor_msgs/Image 32FC1, the linear
irradiance from ``photometric_correction``; NaN = saturated or outside the
field of view) and ``camera_info``, pairs them by stamp, and publishes
``depth_relative`` (32FC1, same header, relative depth along the optical
axis, NaN invalid; see :mod:`endo_sfs.relative_depth` for the convention) and,
with ``publish_normals``, ``normals`` (32FC3 unit normals in the optical
frame).

Every frame goes through :func:`endo_sfs.relative_depth.solve`, the function
offline tools call; with ``mask_highlights`` (default true) specular
highlights are masked by :func:`endo_sfs.highlights.detect_highlights`.
The near-light solve is warm-started from the previous frame. The numba
kernels are loaded (compiled on the very first run, then from the on-disk
cache) by a warm-up solve of a tiny synthetic image before
the subscriptions exist, so the first real frame is not slow.

Bad input never stops the node: a wrong encoding, a camera_info of another
size, or a frame with no usable pixel (all dark, all saturated, all NaN) is
logged once per second and counted on ``/diagnostics``; a frame without
usable pixels still gets an all-NaN depth image, so consumers stay in step.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from endo_io.camera import CameraModel
from endo_io.diagnostics import InputHealth
from endo_io.image import array_to_image, image_to_array
from endo_io.process import run_node
from endo_io.qos import SENSOR_DATA_QOS, create_reliable_publisher
from endo_io.stamp import NS_PER_S, stamp_to_ns
from endo_io.stamp_matching import StampMatcher
from endo_sfs.errors import NoValidPixelsError, SfsError, SfsInputError
from endo_sfs.near_light import MAX_ROUGHNESS
from endo_sfs.options import DEFAULT_MAX_ITERATIONS, DEFAULT_TOLERANCE, MODELS, SfsOptions
from endo_sfs.relative_depth import SfsSolution, solve, surface_normals
from endo_sfs.synthetic import near_light_surface, render_near_light, scene_camera

#: Side of the synthetic image solved at start-up to load the kernels.
_WARM_UP_SIZE = 24
_WARM_UP_PARALLEL_SIZE = 192


def _float_range(low: float, high: float) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=low, to_value=high, step=0.0)]


def _int_range(low: int, high: int) -> list[IntegerRange]:
    return [IntegerRange(from_value=low, to_value=high, step=1)]


#: name -> (default, descriptor) of every parameter of the node.
PARAMETERS: dict[str, tuple[object, ParameterDescriptor]] = {
    "model": ("near_light", ParameterDescriptor(
        type=ParameterType.PARAMETER_STRING,
        description="reflectance geometry: near_light (light at the optical centre, 1/r²) or "
        "orthographic (the seed paper's Eikonal model)",
        additional_constraints="one of: " + ", ".join(MODELS),
    )),
    "roughness": (0.0, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="Oren–Nayar roughness σ in radians (0 = Lambertian)",
        floating_point_range=_float_range(0.0, MAX_ROUGHNESS),
    )),
    "solve_scale": (1.0, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="solve-grid density relative to the image pixels; the depth is "
        "resampled back to full size",
        floating_point_range=_float_range(0.1, 1.0),
    )),
    "tolerance": (DEFAULT_TOLERANCE, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="stop sweeping when no node changed by more than this in a full "
        "iteration (ln r for near_light, i.e. relative depth)",
        floating_point_range=_float_range(1e-9, 1e-2),
    )),
    "max_iterations": (DEFAULT_MAX_ITERATIONS, ParameterDescriptor(
        type=ParameterType.PARAMETER_INTEGER,
        description="cap on full fast-sweeping iterations (four sweeps each)",
        integer_range=_int_range(1, 1000),
    )),
    "order": (2, ParameterDescriptor(
        type=ParameterType.PARAMETER_INTEGER,
        description="upwind scheme: 1 first-order Godunov, 2 second-order, 3 WENO3 Godunov",
        integer_range=_int_range(1, 3),
    )),
    "threads": (2, ParameterDescriptor(
        type=ParameterType.PARAMETER_INTEGER,
        description="CPU threads per frame (resampling; near_light on grids of 20000+ nodes: "
        "the first pass, or the sweeps when the predicted order is poor, as two halves at "
        "once); 1 leaves the other cores to the rest of the graph and makes the output "
        "bit-reproducible",
        integer_range=_int_range(1, 64),
    )),
    "warm_start": (True, ParameterDescriptor(
        type=ParameterType.PARAMETER_BOOL,
        description="seed each near_light solve with the previous frame's solution",
    )),
    "dark_level": (0.0, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="irradiance at or below this is not data (noise floor), image units",
        floating_point_range=_float_range(0.0, 1e6),
    )),
    "fov_radius": (0.0, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="radius in pixels of the circular field of view around the principal "
        "point (0: whole image; NaN pixels are excluded anyway)",
        floating_point_range=_float_range(0.0, 1e5),
    )),
    "smoothing": (0.0, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="Gaussian σ in pixels applied to the valid irradiance before solving "
        "(noise near c ≈ 1 biases the slope; ~1 px helps 8-bit input)",
        floating_point_range=_float_range(0.0, 10.0),
    )),
    "mask_highlights": (True, ParameterDescriptor(
        type=ParameterType.PARAMETER_BOOL,
        description="detect specular highlights (saturated pixels and bright blobs over the "
        "diffuse baseline, with their shoulders) and give them no data term; they come out NaN",
    )),
    "publish_normals": (False, ParameterDescriptor(
        type=ParameterType.PARAMETER_BOOL,
        description="also publish unit surface normals on 'normals' (32FC3, optical frame)",
    )),
    "stamp_tolerance": (0.0, ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE,
        description="largest image/camera_info stamp difference of a pair, seconds "
        "(0: exact match)",
        floating_point_range=_float_range(0.0, 1.0),
    )),
    "queue_size": (10, ParameterDescriptor(
        type=ParameterType.PARAMETER_INTEGER,
        description="unmatched images and camera_infos kept while waiting for a partner",
        integer_range=_int_range(1, 100),
        read_only=True,
    )),
}


#: The node parameters that are :class:`SfsOptions` fields of the same name.
_OPTION_PARAMETERS = (
    "model", "roughness", "solve_scale", "tolerance", "max_iterations", "order", "threads",
    "dark_level", "smoothing", "mask_highlights",
)


def warm_up_kernels() -> float:
    """Solve a tiny synthetic frame with every model and order; returns seconds taken.

    The kernels' numba signatures depend only on dtypes, so this loads (or,
    on a fresh checkout, compiles) exactly what real frames use.
    """
    start = time.perf_counter()
    camera = scene_camera(_WARM_UP_SIZE)
    rendering = render_near_light(camera, near_light_surface("sphere"))
    image = rendering.irradiance.astype(np.float32)
    for order in (1, 2, 3):
        near_light = SfsOptions(model="near_light", order=order)
        previous = solve(image, camera, near_light)
        solve(image, camera, near_light, warm_start=previous)
        solve(image, camera, SfsOptions(model="orthographic", order=order, solve_scale=0.5))
    surface_normals(previous.depth, camera)
    # The two-thread first pass only runs on grids of near_light.MIN_PARALLEL_NODES+.
    camera = scene_camera(_WARM_UP_PARALLEL_SIZE)
    image = render_near_light(camera, near_light_surface("tilted_plane")).irradiance
    solve(image, camera, SfsOptions(model="near_light", threads=2))
    return time.perf_counter() - start


class SfsNode(Node):
    """Shape from shading of every matched (image_corrected, camera_info) pair."""

    def __init__(self, node_name: str = "sfs", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        for name, (default, descriptor) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor)
        model = str(self.get_parameter("model").value)
        if model not in MODELS:
            self.get_logger().error(f"model {model!r} is not one of {MODELS}; using near_light")
            self.set_parameters([Parameter("model", value="near_light")])
        self._options = self._solver_options({})
        self.add_on_set_parameters_callback(self._on_parameters)
        seconds = warm_up_kernels()
        self.get_logger().info(f"shape-from-shading kernels ready in {seconds:.2f} s")

        self.health = InputHealth(self, "image input")
        self._camera: CameraModel | None = None
        self._fov_mask: tuple[float, np.ndarray] | None = None
        self._previous: SfsSolution | None = None
        self._matcher: StampMatcher[Image, CameraInfo] = StampMatcher(
            int(self._value("queue_size")), self._tolerance_ns()
        )
        self.depth_publisher = create_reliable_publisher(self, Image, "depth_relative")
        self.normals_publisher = create_reliable_publisher(self, Image, "normals")
        self.create_subscription(
            Image, "image_corrected", self.health.guard(self._on_image), SENSOR_DATA_QOS
        )
        self.create_subscription(
            CameraInfo, "camera_info", self.health.guard(self._on_camera_info), SENSOR_DATA_QOS
        )

    # ------------------------------------------------------------------ parameters

    def _value(self, name: str) -> Any:
        return self.get_parameter(name).value

    def _tolerance_ns(self) -> int:
        return round(float(self._value("stamp_tolerance")) * NS_PER_S)

    @property
    def options(self) -> SfsOptions:
        """The solver settings every frame uses, rebuilt when a parameter changes."""
        return self._options

    def _solver_options(self, changes: dict[str, Any]) -> SfsOptions:
        """The solver settings from the parameters, with ``changes`` (name -> value) applied.

        Raises:
            SfsError: a value out of its range (UnknownModelError,
                InvalidOptionError), named in the message.
        """
        values = {name: self._value(name) for name in _OPTION_PARAMETERS}
        values.update({k: v for k, v in changes.items() if k in _OPTION_PARAMETERS})
        return SfsOptions(**values)

    def _on_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        changes = {parameter.name: parameter.value for parameter in parameters}
        try:
            options = self._solver_options(changes)
        except SfsError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self._options = options
        for parameter in parameters:
            if parameter.name in ("model", "roughness", "solve_scale"):
                self._previous = None  # the old solution no longer seeds this problem
            if parameter.name == "stamp_tolerance":
                self._matcher.tolerance_ns = round(float(parameter.value) * NS_PER_S)
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ callbacks

    def _on_image(self, msg: Image) -> None:
        pair = self._matcher.add_first(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._process(pair.first, pair.second)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        pair = self._matcher.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._process(pair.first, pair.second)

    def _camera_model(self, info: CameraInfo) -> CameraModel:
        """The camera of this frame; the cached model (and its ray table) when unchanged."""
        camera = CameraModel.from_camera_info(info)
        if self._camera is None or camera != self._camera:
            self._camera = camera
            self._previous = None
        return self._camera

    def _mask(self, camera: CameraModel) -> np.ndarray | None:
        radius = float(self._value("fov_radius"))
        if radius <= 0.0:
            return None
        if self._fov_mask is None or self._fov_mask[0] != radius or (
            self._fov_mask[1].shape != (camera.height, camera.width)
        ):
            self._fov_mask = (radius, camera.fov_mask(radius))
        return self._fov_mask[1]

    def _process(self, image_msg: Image, info: CameraInfo) -> None:
        if image_msg.encoding != "32FC1":
            raise SfsInputError(
                f"image_corrected must be 32FC1 linear irradiance, got {image_msg.encoding!r}"
            )
        irradiance = image_to_array(image_msg)
        camera = self._camera_model(info)
        stamp_ns = stamp_to_ns(image_msg.header.stamp)
        frame_id = image_msg.header.frame_id
        warm = self._previous if bool(self._value("warm_start")) else None
        start = time.perf_counter()
        try:
            solution = solve(
                irradiance, camera, self._options, mask=self._mask(camera), warm_start=warm
            )
        except NoValidPixelsError:
            # Nothing to reconstruct: say so downstream with an all-NaN depth,
            # then let the guard log and count the cause.
            empty = np.full(irradiance.shape, np.nan, dtype=np.float32)
            self.depth_publisher.publish(array_to_image(empty, "32FC1", stamp_ns, frame_id))
            self._previous = None
            raise
        elapsed_ms = (time.perf_counter() - start) * 1e3
        self._previous = solution
        self.depth_publisher.publish(array_to_image(solution.depth, "32FC1", stamp_ns, frame_id))
        if bool(self._value("publish_normals")):
            normals = surface_normals(solution.depth, camera)
            self.normals_publisher.publish(array_to_image(normals, "32FC3", stamp_ns, frame_id))
        self.health.set_value("solve_ms", f"{elapsed_ms:.1f}")
        self.health.set_value("iterations", solution.info.iterations)
        self.health.set_value("converged", solution.info.converged)
        self.health.set_value("unmatched_dropped", self._matcher.dropped)


def main(args: list[str] | None = None) -> int:
    """Console entry point of ``endo-sfs``."""
    return run_node(SfsNode, args)


if __name__ == "__main__":
    sys.exit(main())
