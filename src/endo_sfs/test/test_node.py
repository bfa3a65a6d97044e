"""The sfs node over DDS: pairing, output, parameters and bad input."""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from endo_io import topics
from endo_io.image import array_to_image, image_to_array
from endo_io.qos import SENSOR_DATA_QOS, reliable_qos
from endo_io.stamp import ns_to_stamp, stamp_to_ns
from endo_io.stamp_matching import MISMATCH_ARRIVALS
from endo_sfs.evaluation import depth_error
from endo_sfs.node import PARAMETERS, SfsNode
from endo_sfs.options import SfsOptions
from endo_sfs.relative_depth import solve
from endo_sfs.synthetic import near_light_surface, render_near_light, scene_camera

pytestmark = pytest.mark.ros

SIZE = 64


@pytest.fixture
def graph():
    """An sfs node and a test node publishing its inputs and collecting its outputs."""
    rclpy.init()  # domain from ROS_DOMAIN_ID in the environment
    # the tests publish frames back to back and follow each: every frame, not the newest
    sfs = SfsNode(parameter_overrides=[Parameter("publish_normals", value=True),
                                       Parameter("newest_frame", value=False)])
    peer = Node("sfs_test_peer")
    received: dict[str, list[Image]] = {"depth": [], "normals": []}
    peer.create_subscription(Image, topics.DEPTH_RELATIVE, received["depth"].append,
                             reliable_qos(50))
    peer.create_subscription(Image, topics.NORMALS, received["normals"].append, reliable_qos(50))
    images = peer.create_publisher(Image, topics.IMAGE_CORRECTED, SENSOR_DATA_QOS)
    infos = peer.create_publisher(CameraInfo, topics.CAMERA_INFO, SENSOR_DATA_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(sfs)
    executor.add_node(peer)

    def spin_until(condition, timeout=10.0):
        deadline = time.monotonic() + timeout
        while not condition() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        return condition()

    deadline = time.monotonic() + 10.0
    while (images.get_subscription_count() == 0 or infos.get_subscription_count() == 0
           or sfs.depth_publisher.get_subscription_count() == 0) and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    yield sfs, images, infos, received, spin_until
    executor.shutdown()
    sfs.destroy_node()
    peer.destroy_node()
    rclpy.shutdown()


def _frame(stamp_ns, image, camera, encoding="32FC1"):
    msg = array_to_image(image, encoding, stamp_ns, "endoscope_optical_frame")
    info = camera.to_camera_info(stamp_ns)
    info.header.frame_id = "endoscope_optical_frame"
    return msg, info


def test_parameters_are_declared_with_descriptions_and_ranges(graph):
    sfs, *_ = graph
    for spec in PARAMETERS:
        assert sfs.has_parameter(spec.name)
        descriptor = sfs.describe_parameter(spec.name)
        assert descriptor.description
        if isinstance(spec.default, float):
            assert descriptor.floating_point_range
        elif isinstance(spec.default, int) and not isinstance(spec.default, bool):
            assert descriptor.integer_range
    assert not sfs.set_parameters([Parameter("roughness", value=2.0)])[0].successful
    assert not sfs.set_parameters([Parameter("model", value="stereo")])[0].successful
    assert sfs.options.roughness == 0.0  # a refused change leaves the solver settings alone
    assert sfs.set_parameters([Parameter("roughness", value=0.3)])[0].successful
    assert sfs.options.roughness == 0.3 and sfs.options.mask_highlights


def test_matched_frames_give_the_library_depth_and_bad_frames_do_not_stop_the_node(graph):
    sfs, images, infos, received, spin_until = graph
    camera = scene_camera(SIZE)
    rendering = render_near_light(camera, near_light_surface("tilted_plane"))
    image = rendering.irradiance.astype(np.float32)
    stamp = 1_763_800_000_000_000_000

    # camera_info first, image second: still paired by stamp.
    msg, info = _frame(stamp, image, camera)
    infos.publish(info)
    images.publish(msg)
    assert spin_until(lambda: len(received["depth"]) == 1)
    out = received["depth"][0]
    assert out.encoding == "32FC1" and stamp_to_ns(out.header.stamp) == stamp
    assert out.header.frame_id == "endoscope_optical_frame"
    depth = image_to_array(out)
    expected = solve(image, camera, SfsOptions(mask_highlights=True)).depth
    np.testing.assert_array_equal(depth, expected)
    assert depth_error(depth, rendering.depth).abs_rel < 0.02
    assert spin_until(lambda: len(received["normals"]) == 1)
    assert received["normals"][0].encoding == "32FC3"
    normals = image_to_array(received["normals"][0])
    plane = np.asarray(near_light_surface("tilted_plane").normal)
    inner = np.all(np.isfinite(normals), axis=-1)
    assert inner.mean() > 0.9
    assert np.median(normals[inner] @ (plane / np.linalg.norm(plane))) > 0.999

    # An image whose camera_info never comes produces nothing.
    lonely, _ = _frame(stamp + 1, image, camera)
    images.publish(lonely)

    # All dark and all NaN frames: an all-NaN depth, counted as dropped.
    for k, bad in enumerate((np.zeros_like(image), np.full_like(image, np.nan))):
        msg, info = _frame(stamp + 10 + k, bad, camera)
        images.publish(msg)
        infos.publish(info)
        assert spin_until(lambda n=k: len(received["depth"]) == 2 + n)
        assert np.all(np.isnan(image_to_array(received["depth"][-1])))
    assert sfs.health.dropped["NoValidPixelsError"] == 2

    # camera_info of another size, and a wrong encoding: dropped, nothing out.
    msg, _ = _frame(stamp + 20, image, camera)
    _, wrong_info = _frame(stamp + 20, image, scene_camera(SIZE // 2))
    images.publish(msg)
    infos.publish(wrong_info)
    msg, info = _frame(stamp + 30, (image * 255).astype(np.uint8), camera, "mono8")
    images.publish(msg)
    infos.publish(info)
    assert spin_until(
        lambda: sfs.health.dropped["CameraMismatchError"] == 1
        and sfs.health.dropped["SfsInputError"] == 1
    )
    assert len(received["depth"]) == 3

    # The node is still up and solves the next good frame.
    msg, info = _frame(stamp + 40, image, camera)
    images.publish(msg)
    infos.publish(info)
    assert spin_until(lambda: len(received["depth"]) == 4)
    np.testing.assert_allclose(image_to_array(received["depth"][-1]), depth, rtol=1e-4)
    assert stamp_to_ns(received["depth"][-1].header.stamp) == stamp + 40
    assert ns_to_stamp(stamp + 40) == received["depth"][-1].header.stamp


def _values(sfs):
    return {kv.key: kv.value for kv in sfs.health.status().values}


def test_processed_counts_frames_and_implausible_or_jumping_frames_are_handled(graph):
    sfs, images, infos, received, spin_until = graph
    camera = scene_camera(SIZE)
    image = render_near_light(camera, near_light_surface("sphere")).irradiance.astype(np.float32)
    stamp = 1_763_900_000_000_000_000
    for k in range(3):  # three frames, six callbacks
        msg, info = _frame(stamp + k * 33_000_000, image, camera)
        infos.publish(info)
        images.publish(msg)
        assert spin_until(lambda n=k: len(received["depth"]) == n + 1)
    good = image_to_array(received["depth"][-1])
    assert sfs.health.processed == 3
    assert _values(sfs)["received"] == "6"

    # issue 16: a frame of 1e30 irradiance gave finite depth with status ok
    msg, info = _frame(stamp + 99_000_000, image * np.float32(1e30), camera)
    infos.publish(info)
    images.publish(msg)
    assert spin_until(lambda: len(received["depth"]) == 4)
    assert np.all(np.isnan(image_to_array(received["depth"][-1])))
    assert sfs.health.dropped["IrradianceRangeError"] == 1
    assert "above max_irradiance" in sfs.health.last_error
    assert sfs.health.processed == 3

    # a bag loop: time jumps back 3 s; the warm start goes, the frame is solved
    msg, info = _frame(stamp - 3_000_000_000, image, camera)
    infos.publish(info)
    images.publish(msg)
    assert spin_until(lambda: len(received["depth"]) == 5)
    assert sfs.health.clock_jumps == 1 and sfs.health.processed == 4
    np.testing.assert_allclose(image_to_array(received["depth"][-1]), good, rtol=1e-3)


def test_camera_info_stamped_apart_from_its_image_is_named_not_silent(graph):
    # found by a new user's rig (session 15): no depth, no log line, only a counter
    sfs, images, infos, received, spin_until = graph
    camera = scene_camera(SIZE)
    image = render_near_light(camera, near_light_surface("sphere")).irradiance.astype(np.float32)
    stamp = 1_763_900_000_000_000_000
    for k in range(MISMATCH_ARRIVALS + 2):
        msg, info = _frame(stamp + k * 33_000_000, image, camera)
        info.header.stamp = ns_to_stamp(stamp + k * 33_000_000 - 2_000_000)
        infos.publish(info)
        images.publish(msg)
        assert spin_until(lambda n=k: int(_values(sfs)["received"]) >= 2 * (n + 1))
    sfs.health.publish()  # its refresh asks the matcher, as the 1 Hz timer does
    status = sfs.health.status()
    assert status.level == DiagnosticStatus.WARN and not received["depth"]
    assert "2.000 ms apart" in status.message and "stamp_tolerance" in status.message
