"""``sfs`` node: linear irradiance in, relative depth out, one frame at a time.

Subscribes ``/endoscope/image_corrected`` (sensor_msgs/Image, the linear
irradiance from ``photometric_correction``: 16UC1 fixed point or 32FC1, read
by :func:`endo_io.image.image_to_irradiance`; NaN = saturated or outside the
field of view) and ``/endoscope/camera_info``, pairs them by stamp, and
publishes ``/endoscope/depth_relative`` (32FC1, same header, relative depth
along the optical axis, NaN invalid; see :mod:`endo_sfs.relative_depth` for
the convention) and, with ``publish_normals``, ``/endoscope/normals`` (32FC3
unit normals in the optical frame); the names are :mod:`endo_io.topics`'.

Parameters are declared from the table :data:`PARAMETERS` (see
:mod:`endo_io.parameters`): a start-up value out of range or outside its
choices stops the node with one line and exit code 2; the solver settings
(:class:`endo_sfs.SfsOptions`) are rebuilt once per accepted change.

Every frame goes through :func:`endo_sfs.relative_depth.solve`, the function
offline tools call; with ``mask_highlights`` (default true) specular
highlights are masked by :func:`endo_sfs.highlights.detect_highlights`.
The near-light solve is warm-started from the previous frame. The numba
kernels are loaded (compiled on the very first run, which the node says up
front, then from the kernel cache) by :func:`endo_sfs.warm_up.warm_up_kernels`
before the publishers and subscriptions exist, and with
``warm_up_camera_file`` a synthetic frame of the stream's camera is solved
too (:func:`endo_sfs.warm_up.warm_up_frame`: its solve grids, frame-sized
buffers), so the first real frame is not slow; ``--help`` skips that. A
frame with no warm start (the first, or after a reset) starts from a coarse
solve (:data:`endo_sfs.relative_depth.COARSE_START_FACTOR`).

Bad input never stops the node: a wrong encoding, a camera_info of another
size, undecodable CDR, a frame with no usable pixel (all dark, all
saturated, all NaN) or with irradiance above ``max_irradiance`` (not
irradiance at all: 1e30), or a solve that overflows, is logged once per
second and counted on ``/diagnostics``; a frame refused for its values
still gets an all-NaN depth image, so consumers stay in step. ``processed``
counts the depth images solved and published, one per frame (not the
camera_info callbacks); frames missing from the image stream's stamps are
counted as ``lost``.

Workers: ``worker_count`` > 1 processes (``worker_index`` 0 … N − 1) share
the frames, each solving those :func:`endo_sfs.warm_start.frame_owner`
gives it by stamp and publishing on the same depth topic, so consumers get
every frame once, merged by stamp. Each worker also listens to that topic
and warm-starts from the newest solved frame of any worker
(:class:`endo_sfs.warm_start.WarmStartChain`). Time that jumps (a looped bag, a restarted camera:
:mod:`endo_io.clock_jump`) drops the warm start and the unmatched messages
with one log line, counted as ``clock_jumps``; one frame stamped far in the
future is dropped (``FutureStampError``).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from endo_io import topics
from endo_io.camera import CameraInfoCache, CameraModel
from endo_io.clock_jump import ClockJumpDetector
from endo_io.diagnostics import HEALTH_PARAMETERS, InputHealth
from endo_io.errors import Endo3dError, ParameterValidationError
from endo_io.image import (
    IRRADIANCE_ENCODINGS,
    ImageMessage,
    array_to_image_cdr,
    image_from_cdr,
    image_to_array,
    image_to_irradiance,
)
from endo_io.parameters import NodeParameters, ParameterSpec
from endo_io.process import describing_only, run_node
from endo_io.qos import (
    NEWEST_FRAME_QOS,
    SENSOR_DATA_QOS,
    create_reliable_publisher,
    reliable_qos,
)
from endo_io.stamp import NS_PER_S, stamp_to_ns
from endo_io.stamp_matching import StampMatcher
from endo_sfs.errors import (
    IrradianceRangeError,
    NoValidPixelsError,
    SfsError,
    SfsInputError,
    SolutionRangeError,
)
from endo_sfs.near_light import MAX_ROUGHNESS
from endo_sfs.options import (
    DEFAULT_MAX_IRRADIANCE,
    DEFAULT_MAX_ITERATIONS,
    DEFAULT_TOLERANCE,
    MODELS,
    SfsOptions,
)
from endo_sfs.relative_depth import solve, surface_normals
from endo_sfs.warm_start import FrameDealer, WarmStartChain
from endo_sfs.warm_up import warm_up_frame, warm_up_kernels

#: Every parameter of the node.
PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec(
        "model", "near_light",
        "reflectance geometry: near_light (light at the optical centre, 1/r²) or "
        "orthographic (the seed paper's Eikonal model)",
        choices=MODELS,
    ),
    ParameterSpec(
        "roughness", 0.0, "Oren–Nayar roughness σ in radians (0 = Lambertian)",
        range=(0.0, MAX_ROUGHNESS),
    ),
    ParameterSpec(
        "solve_scale", 1.0,
        "solve-grid density relative to the image pixels; the depth is resampled back to "
        "full size",
        range=(0.1, 1.0),
    ),
    ParameterSpec(
        "tolerance", DEFAULT_TOLERANCE,
        "stop sweeping when no node changed by more than this in a full iteration (ln r for "
        "near_light, i.e. relative depth)",
        range=(1e-9, 1e-2),
    ),
    ParameterSpec(
        "max_iterations", DEFAULT_MAX_ITERATIONS,
        "cap on full fast-sweeping iterations (four sweeps each)", range=(1, 1000),
    ),
    ParameterSpec(
        "order", 2, "upwind scheme: 1 first-order Godunov, 2 second-order, 3 WENO3 Godunov",
        range=(1, 3),
    ),
    ParameterSpec(
        "threads", 0,
        "CPU threads per frame (resampling; highlight detection's two halves and the "
        "validity pass at once; near_light on grids of 20000+ nodes: the first pass, or the "
        "sweeps when the predicted order is poor, as two halves at once); 1 leaves the other "
        "cores to the rest of the graph and makes the output bit-reproducible; 0: two on "
        "images of 150000+ pixels at solve_scale (640x480 at 1), else one",
        range=(0, 64),
    ),
    ParameterSpec(
        "warm_start", True, "seed each near_light solve with the previous frame's solution"
    ),
    ParameterSpec(
        "dark_level", 0.0,
        "irradiance at or below this is not data (noise floor), image units", range=(0.0, 1e6),
    ),
    ParameterSpec(
        "max_irradiance", DEFAULT_MAX_IRRADIANCE,
        "a frame with irradiance above this is refused as not irradiance (the correction's "
        "output stays below ~1e2), image units",
        range=(1e-6, 1e38),
    ),
    ParameterSpec(
        "fov_radius", 0.0,
        "radius in pixels of the circular field of view around the principal point (0: whole "
        "image; NaN pixels are excluded anyway)",
        range=(0.0, 1e5),
    ),
    ParameterSpec(
        "smoothing", 0.0,
        "Gaussian σ in pixels applied to the valid irradiance before solving (noise near "
        "c ≈ 1 biases the slope; ~1 px helps 8-bit input)",
        range=(0.0, 10.0),
    ),
    ParameterSpec(
        "mask_highlights", True,
        "detect specular highlights (saturated pixels and bright blobs over the diffuse "
        "baseline, with their shoulders) and give them no data term; they come out NaN",
    ),
    ParameterSpec(
        "publish_normals", False,
        "also publish unit surface normals on the normals topic (32FC3, optical frame)",
    ),
    ParameterSpec(
        "stamp_tolerance", 0.0,
        "largest image/camera_info stamp difference of a pair, seconds (0: exact match)",
        range=(0.0, 1.0),
    ),
    ParameterSpec(
        "queue_size", 10, "unmatched images and camera_infos kept while waiting for a partner",
        range=(1, 100), read_only=True,
    ),
    ParameterSpec(
        "worker_count", 1,
        "SFS processes sharing the frames (each solves every worker_count-th frame by stamp, "
        "all publish on the depth topic); 1: this node solves every frame",
        range=(1, 64), read_only=True,
    ),
    ParameterSpec(
        "worker_index", 0, "this worker's index, 0 to worker_count - 1", range=(0, 63),
        read_only=True,
    ),
    ParameterSpec(
        "warm_up_camera_file", "",
        "camera_calibration YAML of the camera whose frames will come: before it subscribes, "
        "the node solves a synthetic frame of that camera (its solve grids, frame-sized "
        "buffers), so that its first frame costs what later ones do; empty: the kernels only "
        "(the first frame then also builds the grids, ~0.1 s at 640x480)",
        read_only=True,
    ),
    ParameterSpec(
        "frame_period_s", 1.0 / 30.0,
        "the camera's frame period, seconds: frames are dealt to workers by their stamp "
        "rounded to it (every worker must use the same value)",
        range=(1e-4, 10.0), read_only=True,
    ),
    *HEALTH_PARAMETERS,
)


#: The node parameters that are :class:`SfsOptions` fields of the same name.
_OPTION_PARAMETERS = frozenset({
    "model", "roughness", "solve_scale", "tolerance", "max_iterations", "order", "threads",
    "dark_level", "max_irradiance", "smoothing", "mask_highlights",
})


def _solver_options(values: Mapping[str, Any]) -> SfsOptions:
    """The solver settings from the node's parameter values (name -> value).

    Raises:
        SfsError: a value :class:`SfsOptions` refuses, named in the message.
    """
    return SfsOptions(**{name: values[name] for name in _OPTION_PARAMETERS})


def _tolerance_ns(seconds: float) -> int:
    return round(seconds * NS_PER_S)


class SfsNode(Node):
    """Shape from shading of every matched (image_corrected, camera_info) pair."""

    def __init__(self, node_name: str = "sfs", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.parameters = NodeParameters(self, PARAMETERS)
        try:
            self._options = _solver_options(self.parameters.values())
        except SfsError as error:
            raise ParameterValidationError(str(error)) from None
        self._worker_count = int(self.parameters["worker_count"])
        self._worker_index = int(self.parameters["worker_index"])
        if self._worker_index >= self._worker_count:
            raise ParameterValidationError(
                f"parameter worker_index: {self._worker_index} is not below worker_count "
                f"{self._worker_count}"
            )
        if not describing_only():  # --help lists parameters and must not compile
            seconds = warm_up_kernels(announce=self.get_logger().info)
            self._warm_up_on_camera(str(self.parameters["warm_up_camera_file"]))
            self.get_logger().info(f"shape-from-shading kernels ready in {seconds:.2f} s")

        self.health = InputHealth(self, "image input", settings=self.parameters)
        self._frame_time = ClockJumpDetector()
        self._camera: CameraModel | None = None
        self._cameras = CameraInfoCache()
        self._fov_mask: tuple[float, np.ndarray] | None = None
        self._chain = WarmStartChain(predict=False, keep=self._worker_count)
        self._dealer = FrameDealer(
            self._worker_count, max(1, round(self.parameters["frame_period_s"] * NS_PER_S))
        )
        #: Recent inputs of the other workers' frames (stamp -> irradiance), for
        #: rebuilding their solutions as warm starts.
        self._peer_inputs: dict[int, np.ndarray] = {}
        self._peer_frames = 0
        self._matcher: StampMatcher[ImageMessage, CameraInfo] = StampMatcher(
            self.parameters["queue_size"], _tolerance_ns(self.parameters["stamp_tolerance"])
        )
        self.health.watch_matching(self._matcher, topics.IMAGE_CORRECTED, topics.CAMERA_INFO)
        self.depth_publisher = create_reliable_publisher(self, Image, topics.DEPTH_RELATIVE)
        self.normals_publisher = create_reliable_publisher(self, Image, topics.NORMALS)
        # "processed" counts published depth images (_process), not callbacks.
        self.health.subscribe(
            Image, topics.IMAGE_CORRECTED, self._on_image, NEWEST_FRAME_QOS,
            # A worker must not skip its own frame for another worker's newer
            # one: workers take every frame in arrival order (the others'
            # return at once).
            processed=False, gaps=True, newest=self._worker_count == 1,
            decode=image_from_cdr,  # the pixels stay a view of the received bytes
        )
        self.health.subscribe(
            CameraInfo, topics.CAMERA_INFO, self._on_camera_info, SENSOR_DATA_QOS,
            processed=False,
        )
        if self._worker_count > 1:
            # The other workers' output: the newest solved frame of any worker
            # warm-starts this one's next frame.
            self.health.subscribe(
                Image, topics.DEPTH_RELATIVE, self._on_peer_depth,
                reliable_qos(self._worker_count), processed=False, decode=image_from_cdr,
            )
            self.health.set_value("worker", f"{self._worker_index} of {self._worker_count}")
        self.parameters.on_change(self._apply_parameters)

    def _warm_up_on_camera(self, path: str) -> None:
        """Solve a synthetic frame of the camera in ``path`` (nothing when empty).

        Raises:
            ParameterValidationError: the file does not load as a camera.
        """
        if not path:
            return
        try:
            camera = CameraModel.load_yaml(path)
        except (OSError, Endo3dError) as error:
            raise ParameterValidationError(
                f"parameter warm_up_camera_file: {path} is not a camera_calibration YAML: {error}"
            ) from None
        seconds = warm_up_frame(camera, self._options)
        self.get_logger().info(
            f"warmed up on a {camera.width}x{camera.height} frame of {path} in {seconds:.2f} s"
        )

    # ------------------------------------------------------------------ parameters

    @property
    def options(self) -> SfsOptions:
        """The solver settings every frame uses, rebuilt when a parameter changes."""
        return self._options

    def _apply_parameters(self, changes: Mapping[str, Any], values: Mapping[str, Any]) -> None:
        """Put accepted changes into effect; an SfsError (e.g. a bad combination) refuses them."""
        if changes.keys() & _OPTION_PARAMETERS:
            self._options = _solver_options(values)
        if changes.keys() & {"model", "roughness", "solve_scale"}:
            self._chain.reset()  # the old solutions no longer seed this problem
        if "stamp_tolerance" in changes:
            self._matcher.tolerance_ns = _tolerance_ns(changes["stamp_tolerance"])

    # ------------------------------------------------------------------ callbacks

    def _on_image(self, msg: ImageMessage) -> None:
        pair = self._matcher.add_first(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._process(pair.first, pair.second)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        pair = self._matcher.add_second(stamp_to_ns(msg.header.stamp), msg)
        if pair is not None:
            self._process(pair.first, pair.second)

    def _camera_model(self, info: CameraInfo) -> CameraModel:
        """The camera of this frame; the cached model (and its ray table) when unchanged."""
        camera, changed = self._cameras.model_of(info)
        if changed:
            self._chain.reset()
        self._camera = camera
        return camera

    def _owns(self, stamp_ns: int, *, observe: bool = False) -> bool:
        """Whether this worker solves the frame stamped ``stamp_ns`` (observe: a new input)."""
        return self._dealer.owner(stamp_ns, observe=observe) == self._worker_index

    def _on_peer_depth(self, msg: ImageMessage) -> None:
        """Another worker's depth: keep it as a possible warm start."""
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self._owns(stamp_ns) or self._camera is None or msg.encoding != "32FC1":
            return  # this worker's own output, or nothing to rebuild it on yet
        depth = image_to_array(msg)
        if depth.shape != (self._camera.height, self._camera.width):
            return
        self._chain.add_depth(
            stamp_ns, depth, self._camera, self._options,
            irradiance=self._peer_inputs.pop(stamp_ns, None),
        )

    def _mask(self, camera: CameraModel) -> np.ndarray | None:
        radius = float(self.parameters["fov_radius"])
        if radius <= 0.0:
            return None
        if self._fov_mask is None or self._fov_mask[0] != radius or (
            self._fov_mask[1].shape != (camera.height, camera.width)
        ):
            self._fov_mask = (radius, camera.fov_mask(radius))
        return self._fov_mask[1]

    def _process(self, image_msg: ImageMessage, info: CameraInfo) -> None:
        if image_msg.encoding not in IRRADIANCE_ENCODINGS:
            raise SfsInputError(
                "image_corrected must be linear irradiance, 16UC1 fixed point or 32FC1, got "
                f"{image_msg.encoding!r}"
            )
        stamp_ns = stamp_to_ns(image_msg.header.stamp)
        frame_id = image_msg.header.frame_id
        if self._frame_time.is_late(stamp_ns):
            # paired after a newer frame was solved (its camera_info came late): stale,
            # skipped like a frame passed over for a newer one, not an error
            self.health.skip(topics.IMAGE_CORRECTED)
            return
        irradiance = image_to_irradiance(image_msg)  # decoded once the frame is wanted
        camera = self._camera_model(info)
        jump = self._frame_time.check(stamp_ns, time.monotonic_ns())  # raises for a wild stamp
        if jump is not None:
            self._chain.reset()
            self._peer_inputs.clear()
            self._dealer.reset()
            self.health.clock_jump(f"{jump.describe('frame time')}; warm start dropped")
        if not self._owns(stamp_ns, observe=True):
            # Another worker's frame: keep its input for rebuilding that
            # worker's solution when it arrives.
            self._peer_inputs[stamp_ns] = irradiance
            while len(self._peer_inputs) > 2 * self._worker_count:
                del self._peer_inputs[min(self._peer_inputs)]
            self._peer_frames += 1
            self.health.set_value("frames_for_other_workers", self._peer_frames)
            return
        warm = self._chain.warm_start(stamp_ns) if self.parameters["warm_start"] else None
        start = time.perf_counter()
        try:
            solution = solve(
                irradiance, camera, self._options, mask=self._mask(camera), warm_start=warm
            )
        except (NoValidPixelsError, IrradianceRangeError, SolutionRangeError):
            # Nothing to reconstruct: say so downstream with an all-NaN depth,
            # then let the guard log and count the cause.
            empty = np.full(irradiance.shape, np.nan, dtype=np.float32)
            self.depth_publisher.publish(array_to_image_cdr(empty, "32FC1", stamp_ns, frame_id))
            self._chain.reset()
            raise
        elapsed_ms = (time.perf_counter() - start) * 1e3
        self._chain.add(stamp_ns, solution)
        # CDR bytes built directly: one copy of the pixels, not the message's and rclpy's
        self.depth_publisher.publish(
            array_to_image_cdr(solution.depth, "32FC1", stamp_ns, frame_id))
        if self.parameters["publish_normals"]:
            normals = surface_normals(solution.depth, camera)
            self.normals_publisher.publish(array_to_image_cdr(normals, "32FC3", stamp_ns, frame_id))
        self.health.ok()
        self.health.set_value("solve_ms", f"{elapsed_ms:.1f}")
        self.health.set_value("iterations", solution.info.iterations)
        self.health.set_value("converged", solution.info.converged)
        self.health.set_value("unmatched_dropped", self._matcher.dropped)


def main(args: list[str] | None = None) -> int:
    """Console entry point of ``endo-sfs``."""
    return run_node(SfsNode, args, restart_on_lost_port=True)


if __name__ == "__main__":
    sys.exit(main())
