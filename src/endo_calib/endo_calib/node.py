"""``photometric_correction`` node: raw images in, linear irradiance out.

Subscribes ``/endoscope/image_raw`` (sensor_msgs/Image, mono8/mono16/16UC1/
rgb8/bgr8/rgba8/bgra8, sensor-data QoS) and publishes
``/endoscope/image_corrected`` (:mod:`endo_io.topics`): linear irradiance
g(v)/L(x) of the configured channel, in the ``output_encoding`` parameter's
encoding: ``16UC1`` fixed point by default (:func:`endo_io.image.encode_irradiance`:
1e-4 per count, 65535 = NaN, above 6.5534 saturated and counted on
``/diagnostics``), or ``32FC1`` float; 32FC3 (R, G, B) with ``channel: rgb``
whatever the parameter. Saturated pixels and pixels outside the field of view
are NaN. The calibration comes from the ``calibration_file`` parameter
(photometric.yaml) and is reloaded whenever the parameter is set, without a
restart. Images of another resolution with the calibration's aspect ratio
(binned or scaled streams) are corrected with a resampled light map.

Before it subscribes, the node corrects a synthetic raw frame of the
calibration's size (first-call costs: buffers, the light map's resampling
check), so its first real frame is as fast as any later one.

A missing or corrupt calibration (a light map or light model that is not
positive over the field of view, such as all coefficients 0, is refused at
load), an image that does not match it, a bad encoding or undecodable CDR:
the frame is dropped with a one-line error (counted on
``/diagnostics``), nothing is published, and the node keeps running. Setting
the parameter to a file that cannot be loaded is rejected with the reason and
the previous calibration stays in use. A ``channel`` the calibration cannot
give (``red`` of a mono calibration) stops the node at start-up with one
line and exit code 2, and is refused as a run-time change.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Image

from endo_calib.calibration import OUTPUT_CHANNELS, PhotometricCalibration, select_channel
from endo_calib.errors import CalibrationError, CalibrationFileError
from endo_calib.raw_image import to_raw_frame
from endo_io import topics
from endo_io.diagnostics import HEALTH_PARAMETERS, InputHealth
from endo_io.errors import ParameterValidationError
from endo_io.image import (
    IRRADIANCE_ENCODINGS,
    ImageMessage,
    array_to_image,
    array_to_image_cdr,
    encode_irradiance,
    image_from_cdr,
    image_to_array,
)
from endo_io.parameters import NodeParameters, ParameterSpec
from endo_io.process import describing_only, run_node
from endo_io.provenance import provenance_summary
from endo_io.qos import NEWEST_FRAME_QOS, create_reliable_publisher
from endo_io.stamp import stamp_to_ns


class CalibrationNotLoadedError(CalibrationFileError):
    """No usable calibration is loaded, so frames cannot be corrected."""


#: Every parameter of the node.
PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec(
        "calibration_file", "", "photometric.yaml written by endo-calibrate; reloaded when set"
    ),
    ParameterSpec(
        "channel", "luminance",
        "published channel: luminance, red, green, blue (32FC1) or rgb (32FC3); a colour "
        "channel needs a colour calibration",
        choices=OUTPUT_CHANNELS,
    ),
    ParameterSpec(
        "mask_extrapolated", False,
        "publish NaN where the raw value is above the highest value the calibration observed "
        "unsaturated (its inverse response is extrapolated there); the share of such pixels "
        "is on /diagnostics either way",
    ),
    ParameterSpec(
        "output_encoding", "16UC1",
        "encoding of a single-channel image_corrected: 16UC1 fixed point (1e-4 irradiance per "
        "count, 65535 = NaN, above 6.5534 saturated; half the bytes of 32FC1, the same SFS "
        "result) or 32FC1 float; channel rgb is always 32FC3",
        choices=IRRADIANCE_ENCODINGS,
    ),
    *HEALTH_PARAMETERS,
)


def check_channel(calibration: PhotometricCalibration, channel: str, path: str) -> None:
    """Refuse a channel the calibration cannot give (a colour channel of a mono one).

    Raises:
        ParameterValidationError: one line naming the channel and the file.
    """
    names = calibration.channel_names
    colour = channel in ("red", "green", "blue")
    if (channel == "rgb" and len(names) != 3) or (colour and channel not in names):
        raise ParameterValidationError(
            f"parameter channel: {channel!r} needs a colour calibration, but "
            f"{path or 'the calibration'} has channels {'/'.join(names)}"
        )


class PhotometricCorrectionNode(Node):
    """Applies a gray-card photometric calibration to every raw frame."""

    def __init__(self, node_name: str = "photometric_correction", **kwargs: object) -> None:
        super().__init__(node_name, **kwargs)  # type: ignore[arg-type]
        self.parameters = NodeParameters(self, PARAMETERS)
        self.health = InputHealth(self, "image input", settings=self.parameters)
        self.calibration: PhotometricCalibration | None = None
        self._saturated_pixels = 0
        self.load_error = "calibration_file is not set"
        self.publisher = create_reliable_publisher(self, Image, topics.IMAGE_CORRECTED)
        path = self.parameters["calibration_file"]
        if not path:
            self.get_logger().error("no calibration: set the calibration_file parameter")
        else:
            try:
                calibration = PhotometricCalibration.load(path)
            except CalibrationError as error:
                # The node stays up: the file may be written or fixed later.
                self.load_error = str(error)
                self.get_logger().error(f"cannot load calibration: {error}")
                self.health.set_value("calibration_error", self.load_error)
            else:
                check_channel(calibration, self.parameters["channel"], path)
                self.calibration = calibration
                self._report_loaded(path)
        self.parameters.on_change(self._apply_parameters)
        if self.calibration is not None and not describing_only():
            self._warm_up(self.calibration)
        self.subscription = self.health.subscribe(
            Image, topics.IMAGE_RAW, self._on_image, NEWEST_FRAME_QOS, gaps=True, newest=True,
            decode=image_from_cdr,  # the pixels stay a view of the received bytes
        )

    @property
    def channel(self) -> str:
        """The published channel."""
        return str(self.parameters["channel"])

    def _report_loaded(self, path: str) -> None:
        cal = self.calibration
        assert cal is not None
        self.load_error = ""
        self.health.set_value("calibration_file", path)
        self.health.set_value("calibration_error", "")
        self.get_logger().info(
            f"calibration {path}: {cal.width}x{cal.height}, {cal.bit_depth}-bit, "
            f"channels {'/'.join(cal.channel_names)}; {provenance_summary(cal.provenance)}"
        )
        for name, extent in cal.response_ranges.items():
            self.get_logger().info(
                f"calibration {name}: observed raw values {extent.get('observed')}, "
                f"top: {extent.get('top_model')}"
            )

    def _count_extrapolated(self, calibration: PhotometricCalibration, frame: Any) -> None:
        """Put the share of pixels above the observed range of the response on /diagnostics."""
        tops = [calibration.observed_top(name) for name in calibration.channel_names]
        if any(top is None for top in tops):
            return
        limit = min(t for t in tops if t is not None)
        above = frame > limit
        if above.ndim == 3:
            above = above.any(axis=-1)
        share = float(np.count_nonzero(above)) / max(above.size, 1)
        self.health.set_value("extrapolated_pixel_share", f"{share:.4f}")

    def _apply_parameters(self, changes: Mapping[str, Any], values: Mapping[str, Any]) -> None:
        """Load a new calibration file and check the channel against it; refuse on failure.

        Raises:
            CalibrationError: the new file does not load (the previous one stays).
            ParameterValidationError: the channel does not fit the calibration.
        """
        calibration = self.calibration
        if "calibration_file" in changes:
            try:
                calibration = PhotometricCalibration.load(values["calibration_file"])
            except CalibrationError as error:
                self.get_logger().error(f"calibration not changed: {error}")
                raise
        if calibration is not None:
            check_channel(calibration, values["channel"], values["calibration_file"])
        if calibration is not self.calibration:
            self.calibration = calibration
            self._report_loaded(values["calibration_file"])

    def _warm_up(self, calibration: PhotometricCalibration) -> None:
        """Correct a synthetic raw frame of the calibration's size, as a real one will be."""
        start = time.perf_counter()
        colour = len(calibration.channel_names) == 3
        if colour and calibration.bit_depth > 8:
            return  # no colour encoding of more than 8 bits comes in (see to_raw_frame)
        encoding = "rgb8" if colour else "mono8" if calibration.bit_depth <= 8 else "mono16"
        size = (calibration.height, calibration.width)
        shape = (*size, 3) if colour else size
        code = (1 << calibration.bit_depth) // 2
        dtype = np.uint8 if calibration.bit_depth <= 8 else np.uint16
        raw = array_to_image(np.full(shape, code, dtype), encoding, 0, "warm_up")
        try:
            self._correct(calibration, raw)
        except CalibrationError:
            return  # a calibration that does not fit its own size: the frames will say so
        self.get_logger().info(
            f"warmed up on a {calibration.width}x{calibration.height} {encoding} frame in "
            f"{time.perf_counter() - start:.2f} s"
        )

    def _correct(
        self, calibration: PhotometricCalibration, msg: ImageMessage
    ) -> tuple[bytes, Any]:
        """(the corrected image's CDR bytes, the raw frame) of one raw image message.

        The bytes are built directly (:func:`endo_io.image.array_to_image_cdr`: one
        copy of the pixels, not the message's, its conversion's and rclpy's).
        """
        frame = to_raw_frame(image_to_array(msg), msg.encoding)
        mask = bool(self.parameters["mask_extrapolated"])
        corrected = calibration.correct(frame, mask_extrapolated=mask)
        output = select_channel(calibration, corrected, self.channel)
        stamp = stamp_to_ns(msg.header.stamp)
        if output.ndim == 3:
            return array_to_image_cdr(output, "32FC3", stamp, msg.header.frame_id), frame
        encoded = encode_irradiance(output, str(self.parameters["output_encoding"]))
        if encoded.saturated:
            self._saturated_pixels += encoded.saturated
            self.health.set_value("saturated_pixels_16bit", self._saturated_pixels)
        return array_to_image_cdr(encoded.pixels, encoded.encoding, stamp,
                                  msg.header.frame_id), frame

    def _on_image(self, msg: ImageMessage) -> None:
        calibration = self.calibration
        if calibration is None:
            raise CalibrationNotLoadedError(f"no calibration loaded ({self.load_error})")
        output, frame = self._correct(calibration, msg)
        self._count_extrapolated(calibration, frame)
        self.publisher.publish(output)


def main(args: list[str] | None = None) -> int:
    """Console entry point of ``endo-photometric-correction``.

    Also installed under its old name ``photometric_correction`` for one release.
    """
    return run_node(PhotometricCorrectionNode, args, restart_on_lost_port=True)


if __name__ == "__main__":
    sys.exit(main())
