"""endo-process gives what the live nodes' own code gives, frame by frame.

The four nodes (correction, SFS, tracker bridge, flow) are built in this
process (real rclpy nodes with their real parameters) and fed the phantom
bag's messages by calling their subscription callbacks directly, in bag
order; their publishers are captured. The
offline run of the same frames must match: corrected images bit for bit,
relative depth bit for bit (one solver thread on both sides, which the
solver makes bit-reproducible), camera poses exactly, and the flow node's
metric depth and scale bit for bit.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message

from endo_calib.node import PhotometricCorrectionNode
from endo_flow.node import FlowNode
from endo_io import topics
from endo_io.bag import BagReader, deserialize
from endo_io.image import image_to_array
from endo_io.pose import pose_to_matrix
from endo_io.stamp import stamp_to_ns
from endo_process.runner import ProcessOptions, process_bag
from endo_process.settings import load_settings
from endo_sfs.node import SfsNode
from endo_tracker_bridge.node import TrackerBridgeNode

from .conftest import PHANTOM

FRAMES = 27  # the scale becomes usable (and metric depth appears) after ~20 frames

pytestmark = pytest.mark.ros


def _capture(publisher: Any) -> list[Any]:
    sent: list[Any] = []

    def keep(msg: Any) -> None:
        # the flow node publishes the CDR bytes it builds (endo_io.image.array_to_image_cdr)
        sent.append(deserialize_message(msg, publisher.msg_type) if isinstance(msg, bytes) else msg)

    publisher.publish = keep
    return sent


def _callback(node: Any, topic: str) -> Any:
    name = node.resolve_topic_name(topic)
    (subscription,) = [s for s in node.subscriptions if s.topic_name == name]
    callback = subscription.callback
    if len(inspect.signature(callback).parameters) == 2:  # (message, rclpy's message info)
        return lambda msg: callback(msg, None)  # no middleware here: no receive time
    return callback


def _live_outputs(photometric: Path, handeye: Path, params: Path) -> dict[str, dict[int, Any]]:
    settings = load_settings(params, solve_scale=0.5)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        correction = PhotometricCorrectionNode(
            context=context,
            parameter_overrides=[Parameter("calibration_file", value=str(photometric))],
        )
        sfs = SfsNode(
            context=context,
            parameter_overrides=[
                Parameter("roughness", value=settings.sfs["roughness"]),
                Parameter("solve_scale", value=0.5),
                Parameter("threads", value=1),
            ],
        )
        bridge = TrackerBridgeNode(
            context=context,
            parameter_overrides=[
                Parameter("handeye_file", value=str(handeye)),
                Parameter("T_world_tracker", value=list(settings.bridge["T_world_tracker"])),
                Parameter("ros_topic", value=topics.TRACKER_POSE),
            ],
        )
        corrected = _capture(correction.publisher)
        depth = _capture(sfs.depth_publisher)
        poses = _capture(bridge._camera_publisher)
        on_raw = _callback(correction, topics.IMAGE_RAW)
        on_corrected = _callback(sfs, topics.IMAGE_CORRECTED)
        on_info = _callback(sfs, topics.CAMERA_INFO)
        on_pose = _callback(bridge, topics.TRACKER_POSE)
        images = 0
        infos: dict[int, Any] = {}
        with BagReader(PHANTOM) as reader:
            for message in reader.messages(
                [topics.IMAGE_RAW, topics.CAMERA_INFO, topics.TRACKER_POSE]
            ):
                msg = deserialize(message)
                if message.topic == topics.TRACKER_POSE:
                    on_pose(msg)
                elif message.topic == topics.CAMERA_INFO:
                    infos[stamp_to_ns(msg.header.stamp)] = msg
                    if images <= FRAMES:
                        on_info(msg)
                elif images < FRAMES:
                    images += 1
                    before = len(corrected)
                    on_raw(msg)
                    for out in corrected[before:]:
                        on_corrected(out)
        # The flow node gets the bridge's poses, then each frame's three messages.
        flow = FlowNode(context=context)
        metric = _capture(flow.depth_pub)
        scale = _capture(flow.scale_pub)
        for pose in poses:
            _callback(flow, topics.CAMERA_POSE)(pose)
        depth_by_stamp = {stamp_to_ns(m.header.stamp): m for m in depth}
        for image in corrected:
            stamp = stamp_to_ns(image.header.stamp)
            _callback(flow, topics.CAMERA_INFO)(infos[stamp])
            _callback(flow, topics.IMAGE_CORRECTED)(image)
            _callback(flow, topics.DEPTH_RELATIVE)(depth_by_stamp[stamp])
        for node in (correction, sfs, bridge, flow):
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    return {
        "corrected": {stamp_to_ns(m.header.stamp): image_to_array(m) for m in corrected},
        "depth": {stamp_to_ns(m.header.stamp): image_to_array(m) for m in depth},
        "poses": {stamp_to_ns(m.header.stamp): pose_to_matrix(m)[0] for m in poses},
        "metric": {stamp_to_ns(m.header.stamp): image_to_array(m) for m in metric},
        "scale": {stamp_to_ns(m.header.stamp): (m.vector.x, m.vector.y, m.vector.z)
                  for m in scale},
    }


def _offline_outputs(path: Path) -> dict[str, dict[int, Any]]:
    wanted = {topics.IMAGE_CORRECTED: "corrected", topics.DEPTH_RELATIVE: "depth",
              topics.CAMERA_POSE: "poses", topics.DEPTH: "metric",
              topics.SCALE: "scale"}  # fmt: skip
    out: dict[str, dict[int, Any]] = {name: {} for name in wanted.values()}
    with BagReader(path) as reader:
        for message in reader.messages(list(wanted)):
            msg = deserialize(message)
            stamp = stamp_to_ns(msg.header.stamp)
            if message.topic == topics.CAMERA_POSE:
                out["poses"][stamp] = pose_to_matrix(msg)[0]
            elif message.topic == topics.SCALE:
                out["scale"][stamp] = (msg.vector.x, msg.vector.y, msg.vector.z)
            else:
                out[wanted[message.topic]][stamp] = image_to_array(msg)
    return out


def test_offline_run_matches_the_live_nodes_frame_by_frame(
    calibrations: tuple[Path, Path], phantom_params: Path, tmp_path: Path
) -> None:
    photometric, handeye = calibrations
    params = tmp_path / "threads1.yaml"
    params.write_text(
        phantom_params.read_text().replace("sfs:\n  ros__parameters:\n",
                                           "sfs:\n  ros__parameters:\n    threads: 1\n")
    )  # fmt: skip
    report = process_bag(ProcessOptions(
        bag=PHANTOM, output=tmp_path / "offline.mcap", calibration=photometric, handeye=handeye,
        params=params, solve_scale=0.5, jobs=1, max_frames=FRAMES, progress=False,
    ))  # fmt: skip
    assert report.frames_shaded == FRAMES
    offline = _offline_outputs(tmp_path / "offline.mcap")
    live = _live_outputs(photometric, handeye, phantom_params)

    assert sorted(offline["corrected"]) == sorted(live["corrected"])
    assert len(live["corrected"]) == FRAMES
    for stamp, image in live["corrected"].items():
        np.testing.assert_array_equal(offline["corrected"][stamp], image)
    assert sorted(offline["depth"]) == sorted(live["depth"])
    for stamp, depth in live["depth"].items():
        assert np.isfinite(depth).mean() > 0.4  # the FOV circle is 59 % of the image
        np.testing.assert_array_equal(offline["depth"][stamp], depth)
    # Every tracker sample of the bag, through the same chain.
    # Every tracker sample of the bag went through the same chain; the offline
    # output of these first frames ends at the last frame's stamp.
    assert len(live["poses"]) == 180
    last = max(live["depth"])
    covered = sorted(stamp for stamp in live["poses"] if stamp <= last)
    assert sorted(offline["poses"]) == covered and len(covered) > 2 * FRAMES - 4
    for stamp in covered:
        np.testing.assert_allclose(offline["poses"][stamp], live["poses"][stamp], rtol=0,
                                   atol=1e-12)  # fmt: skip
    # The flow step: the flow node's own metric depth and scale, frame by frame.
    assert len(live["scale"]) == FRAMES
    assert sorted(offline["scale"]) == sorted(live["scale"])
    for stamp, value in live["scale"].items():
        np.testing.assert_array_equal(offline["scale"][stamp], value)
    assert len(live["metric"]) >= 5
    assert sorted(offline["metric"]) == sorted(live["metric"])
    for stamp, depth in live["metric"].items():
        np.testing.assert_array_equal(offline["metric"][stamp], depth)
