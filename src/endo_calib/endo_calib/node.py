"""``photometric_correction`` node: raw images in, linear irradiance out.

Subscribes ``image_raw`` (sensor_msgs/Image, mono8/mono16/16UC1/rgb8/bgr8/
rgba8/bgra8, sensor-data QoS) and publishes ``image_corrected``: 32FC1 linear
irradiance g(v)/L(x) of the configured channel, or 32FC3 (R, G, B) with
``channel: rgb``; saturated pixels and pixels outside the field of view are
NaN. The calibration comes from the ``calibration_file`` parameter
(photometric.yaml) and is reloaded whenever the parameter is set, without a
restart. Images of another resolution with the calibration's aspect ratio
(binned or scaled streams) are corrected with a resampled light map.

A missing or corrupt calibration, an image that does not match it, or a bad
encoding: the frame is dropped with a one-line error (counted on
``/diagnostics``), nothing is published, and the node keeps running. Setting
the parameter to a file that cannot be loaded is rejected with the reason and
the previous calibration stays in use.
"""

from __future__ import annotations

import sys

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from endo_calib.calibration import OUTPUT_CHANNELS, PhotometricCalibration, select_channel
from endo_calib.errors import CalibrationError, CalibrationFileError
from endo_calib.raw_image import to_raw_frame
from endo_io.diagnostics import InputHealth
from endo_io.image import array_to_image, image_to_array
from endo_io.process import run_node
from endo_io.qos import SENSOR_DATA_QOS, create_reliable_publisher
from endo_io.stamp import stamp_to_ns


class CalibrationNotLoadedError(CalibrationFileError):
    """No usable calibration is loaded, so frames cannot be corrected."""


class PhotometricCorrectionNode(Node):
    """Applies a gray-card photometric calibration to every raw frame."""

    def __init__(self, node_name: str = "photometric_correction", **kwargs: object) -> None:
        super().__init__(node_name, **kwargs)  # type: ignore[arg-type]
        self.declare_parameter(
            "calibration_file",
            "",
            ParameterDescriptor(
                description="photometric.yaml written by endo-calibrate; reloaded when set"
            ),
        )
        self.declare_parameter(
            "channel",
            "luminance",
            ParameterDescriptor(
                description="published channel: luminance|red|green|blue (32FC1) or rgb (32FC3)"
            ),
        )
        self.health = InputHealth(self, "image input")
        self.calibration: PhotometricCalibration | None = None
        self.load_error = "calibration_file is not set"
        self.channel = str(self.get_parameter("channel").value)
        if self.channel not in OUTPUT_CHANNELS:
            self.get_logger().error(
                f"channel {self.channel!r} not one of {OUTPUT_CHANNELS}; using luminance"
            )
            self.channel = "luminance"
        self._load(str(self.get_parameter("calibration_file").value))
        self.add_on_set_parameters_callback(self._on_parameters)
        self.publisher = create_reliable_publisher(self, Image, "image_corrected")
        self.subscription = self.create_subscription(
            Image, "image_raw", self.health.guard(self._on_image), SENSOR_DATA_QOS
        )

    def _load(self, path: str) -> None:
        """Load at start-up: on failure log the cause and publish nothing until a valid file."""
        if not path:
            self.get_logger().error("no calibration: set the calibration_file parameter")
            return
        try:
            self.calibration = PhotometricCalibration.load(path)
        except CalibrationError as error:
            self.load_error = str(error)
            self.get_logger().error(f"cannot load calibration: {error}")
            self.health.set_value("calibration_error", self.load_error)
            return
        self._report_loaded(path)

    def _report_loaded(self, path: str) -> None:
        cal = self.calibration
        assert cal is not None
        self.load_error = ""
        self.health.set_value("calibration_file", path)
        self.health.set_value("calibration_error", "")
        self.get_logger().info(
            f"calibration {path}: {cal.width}x{cal.height}, {cal.bit_depth}-bit, "
            f"channels {'/'.join(cal.channel_names)}"
        )

    def _on_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Validate and apply parameter changes; a bad calibration file is rejected."""
        new_calibration: PhotometricCalibration | None = None
        new_path = ""
        channel = self.channel
        for parameter in parameters:
            if parameter.name == "channel":
                channel = str(parameter.value)
                if channel not in OUTPUT_CHANNELS:
                    return SetParametersResult(
                        successful=False, reason=f"channel must be one of {OUTPUT_CHANNELS}"
                    )
            elif parameter.name == "calibration_file":
                new_path = str(parameter.value)
                try:
                    new_calibration = PhotometricCalibration.load(new_path)
                except CalibrationError as error:
                    self.get_logger().error(f"calibration not changed: {error}")
                    return SetParametersResult(successful=False, reason=str(error))
        effective = new_calibration or self.calibration
        if (
            effective is not None
            and channel in ("red", "green", "blue", "rgb")
            and (effective.channel_names == ("mono",))
        ):
            return SetParametersResult(
                successful=False, reason=f"channel {channel!r} needs a colour calibration"
            )
        self.channel = channel
        if new_calibration is not None:
            self.calibration = new_calibration
            self._report_loaded(new_path)
        return SetParametersResult(successful=True)

    def _on_image(self, msg: Image) -> None:
        calibration = self.calibration
        if calibration is None:
            raise CalibrationNotLoadedError(f"no calibration loaded ({self.load_error})")
        frame = to_raw_frame(image_to_array(msg), msg.encoding)
        corrected = calibration.correct(frame)
        output = select_channel(calibration, corrected, self.channel)
        encoding = "32FC3" if output.ndim == 3 else "32FC1"
        self.publisher.publish(
            array_to_image(output, encoding, stamp_to_ns(msg.header.stamp), msg.header.frame_id)
        )


def main(args: list[str] | None = None) -> int:
    """Console entry point of ``photometric_correction``."""
    return run_node(PhotometricCorrectionNode, args)


if __name__ == "__main__":
    sys.exit(main())
