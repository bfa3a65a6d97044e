"""The photometric_correction node in-process over DDS (loopback, this run's domain).

A raw frame goes in on image_raw; image_corrected must hold exactly what
PhotometricCalibration.correct gives. Setting calibration_file reloads the
calibration without a restart; a bad file is rejected and changes nothing; a
node without a usable calibration publishes nothing and keeps running.
"""

import gc
import time

import numpy as np
import pytest
import rclpy
import yaml
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from endo_calib.calibration import PhotometricCalibration
from endo_calib.node import PhotometricCorrectionNode
from endo_calib.synthetic import synthetic_calibration
from endo_io import topics
from endo_io.errors import ParameterValidationError
from endo_io.image import (
    IRRADIANCE_PER_COUNT,
    array_to_image,
    encode_irradiance,
    image_to_array,
    image_to_irradiance,
)
from endo_io.qos import SENSOR_DATA_QOS, reliable_qos

pytestmark = pytest.mark.ros
NS = "/calib_node_test"
W, H = 64, 48
HALF_COUNT = 0.5 * IRRADIANCE_PER_COUNT + 1e-6  # the 16UC1 round trip's bound


def _assert_corrected(out, expected):
    """``out`` (16UC1 fixed point by default) holds ``expected`` to half a count, NaN alike."""
    got = image_to_irradiance(out)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got, expected, rtol=0, atol=HALF_COUNT)


def _write_calibration(path, exponent, colour=False):
    calibration = synthetic_calibration(
        W, H, colour=colour, gamma=exponent, gamma_step=0.1, falloff_step=0.3
    )
    return calibration.save(path)


@pytest.fixture
def ros():
    """(context, executor, nodes): every node in ``nodes`` is destroyed after the test.

    A node left alive keeps its publishers and subscriptions on the DDS graph of
    this process, where later tests would discover them.
    """
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes: list[Node] = []
    try:
        yield context, executor, nodes
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        # a node whose constructor raised (pytest.raises) is only referenced from
        # the exception's frames: collect it, which destroys its handle
        gc.collect()
        rclpy.shutdown(context=context)


def _start(ros, parameters):
    context, executor, nodes = ros
    node = PhotometricCorrectionNode(context=context, namespace=NS, parameter_overrides=parameters)
    nodes.append(node)
    probe = rclpy.create_node("calib_probe", namespace=NS, context=context)
    nodes.append(probe)
    received: list[Image] = []
    probe.create_subscription(Image, topics.IMAGE_CORRECTED, received.append, reliable_qos(10))
    publisher = probe.create_publisher(Image, topics.IMAGE_RAW, SENSOR_DATA_QOS)
    executor.add_node(node)
    executor.add_node(probe)
    deadline = time.monotonic() + 10.0
    while (
        publisher.get_subscription_count() == 0
        or probe.count_publishers(topics.IMAGE_CORRECTED) == 0
    ):
        executor.spin_once(timeout_sec=0.05)
        assert time.monotonic() < deadline, "node and probe did not discover each other"
    return node, publisher, received


def _exchange(executor, publisher, received, msg, expect=True, timeout=5.0):
    before = len(received)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        publisher.publish(msg)
        end = time.monotonic() + 0.2
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
            if len(received) > before:
                return received[-1]
        if not expect and time.monotonic() > deadline - timeout + 1.0:
            return None
    return None


def test_corrects_frames_and_reloads_on_parameter_change(ros, tmp_path):
    _, executor, _ = ros
    first = _write_calibration(tmp_path / "first.yaml", 2.2)
    second = _write_calibration(tmp_path / "second.yaml", 1.0)
    node, publisher, received = _start(ros, [Parameter("calibration_file", value=str(first))])
    raw = np.random.default_rng(0).integers(0, 256, (H, W), dtype=np.uint8)
    msg = array_to_image(raw, "mono8", 123_456_789, "endoscope_optical_frame")

    out = _exchange(executor, publisher, received, msg)
    assert out is not None, "no image_corrected received"
    assert out.encoding == "16UC1" and out.header.frame_id == "endoscope_optical_frame"
    assert out.header.stamp.nanosec == 123_456_789
    expected = PhotometricCalibration.load(first).correct(raw)
    assert np.nanmax(expected) > 0.5  # the test covers a good part of the range
    # the counts are the codec's, bit for bit, and decode to the float to half a count
    np.testing.assert_array_equal(image_to_array(out), encode_irradiance(expected).pixels)
    _assert_corrected(out, expected)
    # float on request: the calibration's values as they are
    assert node.set_parameters([Parameter("output_encoding", value="32FC1")])[0].successful
    out = _exchange(executor, publisher, received, msg)
    assert out.encoding == "32FC1"
    np.testing.assert_array_equal(np.isnan(image_to_array(out)), np.isnan(expected))
    np.testing.assert_allclose(image_to_array(out), expected, rtol=1e-6)
    assert not node.set_parameters([Parameter("output_encoding", value="16FC1")])[0].successful
    assert node.set_parameters([Parameter("output_encoding", value="16UC1")])[0].successful

    result = node.set_parameters([Parameter("calibration_file", value=str(second))])[0]
    assert result.successful
    out = _exchange(executor, publisher, received, msg)
    _assert_corrected(out, PhotometricCalibration.load(second).correct(raw))

    # a missing file is rejected with its reason; the second calibration stays
    result = node.set_parameters([Parameter("calibration_file", value=str(tmp_path / "x.yaml"))])[0]
    assert not result.successful and "not found" in result.reason
    assert node.get_parameter("calibration_file").value == str(second)
    out = _exchange(executor, publisher, received, msg)
    _assert_corrected(out, PhotometricCalibration.load(second).correct(raw))
    # a frame of another aspect ratio is dropped, counted, and the node lives on
    dropped = sum(node.health.dropped.values())
    wrong = array_to_image(np.zeros((H, H), np.uint8), "mono8", 1)
    assert _exchange(executor, publisher, received, wrong, expect=False, timeout=1.5) is None
    assert node.health.dropped["CalibrationMismatchError"] >= 1
    assert sum(node.health.dropped.values()) > dropped


def test_colour_channels_binning_and_rgb_output(ros, tmp_path):
    _, executor, _ = ros
    path = _write_calibration(tmp_path / "rgb.yaml", 2.2, colour=True)
    node, publisher, received = _start(
        ros, [Parameter("calibration_file", value=str(path)), Parameter("channel", value="red")]
    )
    cal = PhotometricCalibration.load(path)
    rgb = np.random.default_rng(1).integers(0, 250, (H // 2, W // 2, 3), dtype=np.uint8)
    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    out = _exchange(executor, publisher, received, array_to_image(bgr, "bgr8", 5))
    assert (
        out is not None and out.encoding == "16UC1" and (out.height, out.width) == (H // 2, W // 2)
    )
    _assert_corrected(out, cal.correct(rgb)[:, :, 0])
    assert node.set_parameters([Parameter("channel", value="rgb")])[0].successful
    out = _exchange(executor, publisher, received, array_to_image(bgr, "bgr8", 6))
    assert out.encoding == "32FC3"
    data = np.frombuffer(bytes(out.data), np.float32).reshape(H // 2, W // 2, 3)
    np.testing.assert_allclose(data, cal.correct(rgb), rtol=1e-6)
    assert not node.set_parameters([Parameter("channel", value="purple")])[0].successful


def test_without_a_calibration_nothing_is_published(ros, tmp_path):
    _, executor, _ = ros
    node, publisher, received = _start(
        ros, [Parameter("calibration_file", value=str(tmp_path / "missing.yaml"))]
    )
    msg = array_to_image(np.zeros((H, W), np.uint8), "mono8", 1)
    assert _exchange(executor, publisher, received, msg, expect=False, timeout=1.5) is None
    assert node.health.dropped["CalibrationNotLoadedError"] >= 1
    path = _write_calibration(tmp_path / "late.yaml", 2.2)
    assert node.set_parameters([Parameter("calibration_file", value=str(path))])[0].successful
    assert _exchange(executor, publisher, received, msg) is not None


def test_a_colour_channel_of_a_mono_calibration_is_refused_at_start_and_at_run_time(
    ros, tmp_path
):
    context, _, _ = ros
    mono = _write_calibration(tmp_path / "mono.yaml", 2.2)
    colour = _write_calibration(tmp_path / "rgb.yaml", 2.2, colour=True)
    with pytest.raises(ParameterValidationError, match="'red' needs a colour calibration"):
        PhotometricCorrectionNode(
            context=context, namespace=NS,
            parameter_overrides=[Parameter("calibration_file", value=str(mono)),
                                 Parameter("channel", value="red")],
        )
    node, _, _ = _start(ros, [Parameter("calibration_file", value=str(mono))])
    result = node.set_parameters([Parameter("channel", value="green")])[0]
    assert not result.successful and "needs a colour calibration" in result.reason
    assert node.channel == "luminance"
    assert node.set_parameters([Parameter("calibration_file", value=str(colour))])[0].successful
    assert node.set_parameters([Parameter("channel", value="green")])[0].successful
    # Back to the mono file while publishing green: refused, the colour one stays.
    result = node.set_parameters([Parameter("calibration_file", value=str(mono))])[0]
    assert not result.successful and "needs a colour calibration" in result.reason
    assert node.calibration.channel_names == ("red", "green", "blue")
    # Both at once are checked together.
    assert node.set_parameters_atomically(
        [Parameter("calibration_file", value=str(mono)), Parameter("channel", value="luminance")]
    ).successful
    assert node.calibration.channel_names == ("mono",) and node.channel == "luminance"


def test_a_zero_light_model_is_refused_and_nothing_is_counted_processed(ros, tmp_path):
    # issue 16: a zero light model was accepted: every output NaN, counted "processed"
    _, executor, _ = ros
    calibration = synthetic_calibration(W, H, light_model_degree=4, light_source="model")
    path = calibration.save(tmp_path / "zero.yaml")
    document = yaml.safe_load(path.read_text())
    document["light_map"]["model"]["coefficients"]["mono"] = [0.0] * 15
    path.write_text(yaml.safe_dump(document))
    node, publisher, received = _start(ros, [Parameter("calibration_file", value=str(path))])
    assert "all coefficients 0" in node.load_error
    msg = array_to_image(np.full((H, W), 100, np.uint8), "mono8", 1)
    assert _exchange(executor, publisher, received, msg, expect=False, timeout=1.5) is None
    assert node.health.dropped["CalibrationNotLoadedError"] >= 1
    assert node.health.processed == 0


def test_extrapolated_values_are_counted_and_masked_on_request(ros, tmp_path):
    """Raw values above the observed range: NaN with mask_extrapolated; their share is reported."""
    _, executor, _ = ros
    calibration = synthetic_calibration(W, H, gamma=2.2)
    calibration.response_ranges = {
        "mono": {"observed": [10, 200], "extrapolated_above": 200, "top_model": "test"}
    }
    path = calibration.save(tmp_path / "ranged.yaml")
    node, publisher, received = _start(
        ros,
        [
            Parameter("calibration_file", value=str(path)),
            Parameter("mask_extrapolated", value=True),
        ],
    )
    raw = np.full((H, W), 150, np.uint8)
    raw[: H // 4] = 230  # a quarter of the frame above the observed range
    out = _exchange(executor, publisher, received, array_to_image(raw, "mono8", 7))
    assert out is not None
    image = image_to_irradiance(out)
    inside = PhotometricCalibration.load(path).fov_mask
    assert np.all(np.isnan(image[: H // 4]))
    assert np.all(np.isfinite(image[H // 4 :][inside[H // 4 :]]))
    values = {kv.key: kv.value for kv in node.health.status().values}
    assert values["extrapolated_pixel_share"] == "0.2500"
    # off: the same frame corrected everywhere inside the field of view
    assert node.set_parameters([Parameter("mask_extrapolated", value=False)])[0].successful
    out = _exchange(executor, publisher, received, array_to_image(raw, "mono8", 8))
    _assert_corrected(out, PhotometricCalibration.load(path).correct(raw))


def test_irradiance_above_the_16bit_range_saturates_and_is_counted(ros, tmp_path):
    """A light model 20x too dark gives irradiance above 6.5534: 65534, counted on /diagnostics."""
    _, executor, _ = ros
    calibration = synthetic_calibration(W, H, light_model_degree=4, light_source="model")
    path = calibration.save(tmp_path / "dark.yaml")
    document = yaml.safe_load(path.read_text())
    coefficients = document["light_map"]["model"]["coefficients"]
    coefficients["mono"] = [c / 20.0 for c in coefficients["mono"]]
    path.write_text(yaml.safe_dump(document))
    node, publisher, received = _start(ros, [Parameter("calibration_file", value=str(path))])
    raw = np.full((H, W), 250, np.uint8)
    out = _exchange(executor, publisher, received, array_to_image(raw, "mono8", 9))
    assert out is not None
    expected = PhotometricCalibration.load(path).correct(raw)
    above = np.isfinite(expected) & (expected > 6.5534)
    assert above.any()
    counts = image_to_array(out)
    assert np.all(counts[above] == 65534)
    values = {kv.key: kv.value for kv in node.health.status().values}
    assert int(values["saturated_pixels_16bit"]) >= int(np.count_nonzero(above))
