"""Frames lost in transport are counted on /diagnostics by the node that misses them.

Issue 16, "Honest /diagnostics": sequence gaps on image topics (stamps
missing at the nominal rate) are counted as lost. The photometric correction
node runs in-process over DDS; a probe publishes a 30 Hz stream with three
stamps left out, one frame at a time (each waits until the node has it, so
no frame is really lost on loopback), and reads the node's status.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from endo_calib.node import PhotometricCorrectionNode
from endo_calib.synthetic import synthetic_calibration
from endo_io import topics
from endo_io.image import array_to_image
from endo_io.qos import SENSOR_DATA_QOS, reliable_qos

pytestmark = pytest.mark.ros
NS = "/lost_in_transport_test"
W, H = 64, 48
PERIOD_NS = 33_333_333
T0 = 1_790_000_000_000_000_000
MISSING = {10, 11, 20}


def test_stamps_missing_from_an_image_stream_are_counted_as_lost(tmp_path):
    calibration = synthetic_calibration(W, H).save(tmp_path / "photometric.yaml")
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    try:
        node = PhotometricCorrectionNode(
            context=context, namespace=NS,
            parameter_overrides=[Parameter("calibration_file", value=str(calibration))],
        )
        probe = rclpy.create_node("lost_probe", namespace=NS, context=context)
        corrected: list[Image] = []
        probe.create_subscription(Image, topics.IMAGE_CORRECTED, corrected.append,
                                  reliable_qos(50))
        publisher = probe.create_publisher(Image, topics.IMAGE_RAW, SENSOR_DATA_QOS)
        executor.add_node(node)
        executor.add_node(probe)
        deadline = time.monotonic() + 15.0
        while (publisher.get_subscription_count() == 0
               or probe.count_publishers(topics.IMAGE_CORRECTED) == 0):
            executor.spin_once(timeout_sec=0.05)
            assert time.monotonic() < deadline, "node and probe did not discover each other"
        topic = node.resolve_topic_name(topics.IMAGE_RAW)
        frame = np.full((H, W), 120, np.uint8)
        sent = [k for k in range(40) if k not in MISSING]
        for k in sent:
            before = node.health.processed
            msg = array_to_image(frame, "mono8", T0 + k * PERIOD_NS, "endoscope_optical_frame")
            deadline = time.monotonic() + 5.0
            while node.health.processed == before:  # resent only if loopback lost it
                publisher.publish(msg)
                end = time.monotonic() + 0.5
                while node.health.processed == before and time.monotonic() < end:
                    executor.spin_once(timeout_sec=0.02)
                assert time.monotonic() < deadline, f"frame {k} never reached the node"
        deadline = time.monotonic() + 5.0
        while len(corrected) < len(sent) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.02)
        status = node.health.status()
        values = {kv.key: kv.value for kv in status.values}
        assert values["lost"] == values[f"lost.{topic}"] == str(len(MISSING))
        assert values["processed"] == str(len(sent)) and values["dropped"] == "0"
        assert len(corrected) == len(sent)
        assert status.level == DiagnosticStatus.WARN
        assert "lost in the last" in status.message and f"missing on {topic}" in status.message
        node.destroy_node()
        probe.destroy_node()
    finally:
        executor.shutdown()
        rclpy.try_shutdown(context=context)
