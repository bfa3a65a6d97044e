"""Correction and shape from shading of one frame, exactly as the two live nodes do it.

:class:`ShadingStage` holds what the nodes hold between frames (the loaded
calibration, the camera model, the SFS warm start) and calls their cores:

* ``photometric_correction`` (``endo_calib.node``): ``to_raw_frame`` of the
  decoded image, :meth:`PhotometricCalibration.correct`, ``select_channel``,
  and its ``output_encoding``: with ``16UC1`` (the default) the irradiance
  goes through :func:`endo_io.image.encode_irradiance` and back before the
  solve, so SFS and flow see the values the live nodes receive;
* ``sfs`` (``endo_sfs.node``): :func:`endo_sfs.relative_depth.solve` with the
  node's parameters, the field-of-view mask of ``fov_radius`` and the
  previous solution as warm start; a camera change drops the warm start,
  and a frame without usable pixels gives an all-NaN depth and drops it too.

Its input and output (:class:`RawFrame` in, :class:`ShadedFrame` out) are
plain picklable data, so worker processes run it on chunks of the recording
(:mod:`endo_process.parallel`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from endo_calib.calibration import PhotometricCalibration, select_channel
from endo_calib.raw_image import to_raw_frame
from endo_io.camera import CameraModel
from endo_io.errors import Endo3dError
from endo_io.image import decode_irradiance, encode_irradiance
from endo_sfs.errors import NoValidPixelsError
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import SfsSolution, solve
from endo_sfs.warm_up import warm_up_frame


@dataclass(frozen=True)
class RawFrame:
    """One recorded image and its camera, ready for the correction.

    index: position in the recording (0-based); stamp_ns: header stamp;
    frame_id: header frame; raw: the decoded image ((H, W) or (H, W, C),
    as ``endo_io.image.image_to_array`` gives it); encoding: its ROS
    encoding; camera: its model; chunk_start: the first frame of a chunk
    (the warm start is dropped before it).
    """

    index: int
    stamp_ns: int
    frame_id: str
    raw: np.ndarray
    encoding: str
    camera: CameraModel
    chunk_start: bool = False


@dataclass(frozen=True)
class ShadedFrame:
    """The correction and SFS outputs of one frame.

    irradiance: (H, W) float32 (or (H, W, 3) for channel rgb) linear
    irradiance, None when the correction dropped the frame; with
    ``encoding`` 16UC1 the fixed point's values (decoded), as the live
    consumers see them. encoding: what ``/endoscope/image_corrected``
    carries it in (16UC1, 32FC1, or 32FC3 for channel rgb); saturated:
    pixels the 16-bit fixed point clipped at its top (6.5534). depth_relative:
    (H, W) float32 relative depth, NaN invalid; None when the correction
    dropped the frame. dropped: the cause (error class name) and one-line
    message of a drop or of an all-NaN depth, else None. solve_ms: wall
    time of the solve. timings: wall seconds of the stage's steps where it
    ran: "correct" (decoding the raw frame, the correction and the channel),
    "solve" (the whole SFS call) and the solver's own stages as "sfs.<stage>"
    (:data:`endo_sfs.relative_depth.STAGES`). worker_cpu_s: in a worker
    process, its CPU seconds (all its threads) from receiving its first frame
    to sending this one (0.0 when shaded in the calling process).
    """

    index: int
    stamp_ns: int
    frame_id: str
    camera: CameraModel
    irradiance: np.ndarray | None
    depth_relative: np.ndarray | None
    dropped: tuple[str, str] | None = None
    solve_ms: float = 0.0
    iterations: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    worker_cpu_s: float = 0.0
    encoding: str = "32FC1"
    saturated: int = 0


class ShadingStage:
    """The correction node and the SFS node back to back, without DDS.

    Args:
        calibration: the loaded ``photometric.yaml``.
        channel: the correction node's ``channel`` parameter.
        mask_extrapolated: the correction node's ``mask_extrapolated`` parameter.
        output_encoding: the correction node's ``output_encoding`` parameter
            (16UC1 or 32FC1).
        sfs_parameters: the SFS node's parameters (every name of
            ``endo_sfs.node.PARAMETERS``).
    """

    def __init__(
        self,
        calibration: PhotometricCalibration,
        channel: str,
        sfs_parameters: dict[str, Any],
        *,
        mask_extrapolated: bool = False,
        output_encoding: str = "16UC1",
    ) -> None:
        self.calibration = calibration
        self.channel = channel
        self.mask_extrapolated = mask_extrapolated
        self.output_encoding = output_encoding
        self.fov_radius = float(sfs_parameters["fov_radius"])
        self.warm_start = bool(sfs_parameters["warm_start"])
        # The solver's options among the node's parameters (endo_process.settings
        # is not imported here: it pulls in every node module, and rclpy, which
        # a worker process would load for nothing).
        self.options = SfsOptions(**{
            f.name: sfs_parameters[f.name]
            for f in dataclasses.fields(SfsOptions) if f.name in sfs_parameters
        })  # fmt: skip
        self._camera: CameraModel | None = None
        self._mask: np.ndarray | None = None
        self._previous: SfsSolution | None = None

    def reset(self) -> None:
        """Drop the warm start (the next frame is solved cold)."""
        self._previous = None

    def warm_up(self, camera: CameraModel) -> float:
        """Solve a synthetic frame of ``camera`` (kernels loaded, solve grids built); seconds.

        The stage's own warm start is untouched.
        """
        return warm_up_frame(camera, self.options)

    def _mask_for(self, camera: CameraModel) -> np.ndarray | None:
        if camera != self._camera:
            self._camera = camera
            self._previous = None
            self._mask = camera.fov_mask(self.fov_radius) if self.fov_radius > 0.0 else None
        return self._mask

    def process(self, frame: RawFrame) -> ShadedFrame:
        """Correct and solve one frame; never raises for bad input (it is reported)."""
        if frame.chunk_start:
            self.reset()
        base: dict[str, Any] = {"index": frame.index, "stamp_ns": frame.stamp_ns,
                                "frame_id": frame.frame_id, "camera": frame.camera}  # fmt: skip
        start = time.perf_counter()
        try:
            corrected = self.calibration.correct(
                to_raw_frame(frame.raw, frame.encoding), mask_extrapolated=self.mask_extrapolated
            )
            irradiance = select_channel(self.calibration, corrected, self.channel)
        except Endo3dError as error:
            return ShadedFrame(**base, irradiance=None, depth_relative=None,
                               dropped=(type(error).__name__, str(error)))  # fmt: skip
        if irradiance.ndim != 2:
            cause = ("SfsInputError",
                     "the SFS node takes 16UC1/32FC1 only (channel rgb gives 32FC3)")
            return ShadedFrame(**base, irradiance=irradiance, depth_relative=None, dropped=cause,
                               encoding="32FC3")  # fmt: skip
        # what the correction node publishes, as its consumers decode it
        encoded = encode_irradiance(irradiance, self.output_encoding)
        irradiance = decode_irradiance(encoded.pixels, encoded.encoding)
        base.update(encoding=encoded.encoding, saturated=encoded.saturated)
        mask = self._mask_for(frame.camera)
        timings = {"correct": time.perf_counter() - start}
        start = time.perf_counter()
        try:
            solution = solve(
                irradiance,
                frame.camera,
                self.options,
                mask=mask,
                warm_start=self._previous if self.warm_start else None,
            )
        except NoValidPixelsError as error:
            # As the node: an all-NaN depth keeps consumers in step.
            self._previous = None
            empty = np.full(irradiance.shape, np.nan, dtype=np.float32)
            return ShadedFrame(**base, irradiance=irradiance, depth_relative=empty,
                               dropped=(type(error).__name__, str(error)))  # fmt: skip
        except Endo3dError as error:
            return ShadedFrame(**base, irradiance=irradiance, depth_relative=None,
                               dropped=(type(error).__name__, str(error)))  # fmt: skip
        self._previous = solution
        timings["solve"] = time.perf_counter() - start
        timings.update({f"sfs.{name}": seconds for name, seconds in solution.timings.items()})
        return ShadedFrame(
            **base,
            irradiance=irradiance,
            depth_relative=solution.depth,
            solve_ms=timings["solve"] * 1e3,
            iterations=int(solution.info.iterations),
            timings=timings,
        )
