"""endo_process.inputs.CameraInfoPairing: one model per camera, as the live nodes decide it.

The offline pairing and the live nodes share endo_io.camera.CameraInfoCache:
a camera_info that only restamps the camera reuses the model (and its ray
tables); another intrinsic or another frame_id builds a new one (the model
carries the frame_id, so one with the old frame_id is never reused).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped

from endo_io import topics
from endo_io.bag import BagWriter
from endo_io.bag.serde import serialize
from endo_io.camera import CameraModel
from endo_io.image import array_to_image
from endo_process.inputs import CameraInfoPairing, InputTopics, open_recording, recording_streams

MS = 1_000_000
CAMERA = CameraModel.pinhole(64, 48, 60.0, 61.0, 31.5, 23.5)
ZOOMED = CameraModel.pinhole(64, 48, 70.0, 71.0, 31.5, 23.5)


def _bag(path: Path, infos: list[tuple[int, CameraModel, str]]) -> None:
    with BagWriter(path) as writer:
        writer.add_topic(topics.IMAGE_RAW, "sensor_msgs/msg/Image")
        writer.add_topic(topics.CAMERA_INFO, "sensor_msgs/msg/CameraInfo")
        writer.add_topic(topics.TRACKER_POSE, "geometry_msgs/msg/PoseStamped")
        writer.write(topics.IMAGE_RAW, serialize(array_to_image(
            np.zeros((48, 64, 3), np.uint8), "rgb8", 1 * MS, "cam")), 1 * MS)
        writer.write(topics.TRACKER_POSE, serialize(PoseStamped()), 1 * MS)
        for stamp, model, frame_id in infos:
            info = model.to_camera_info(stamp)
            info.header.frame_id = frame_id
            writer.write(topics.CAMERA_INFO, serialize(info), stamp)


def test_a_restamped_camera_reuses_its_model_and_another_frame_id_does_not(tmp_path):
    path = tmp_path / "cameras.mcap"
    _bag(path, [(10 * MS, CAMERA, "cam"), (20 * MS, CAMERA, "cam"),
                (30 * MS, CAMERA, "other_optical_frame"), (40 * MS, ZOOMED, "other_optical_frame")])
    inputs = open_recording(path, InputTopics())
    streams = recording_streams(inputs)
    try:
        pairing = CameraInfoPairing(inputs, streams)
        assert pairing.at(5 * MS) is None  # no camera_info at or before it
        models = [pairing.at(stamp * MS) for stamp in (10, 15, 20, 30, 40)]
    finally:
        streams.close()
    first, same_frame, restamped, renamed, zoomed = (m[0] for m in models)  # type: ignore[index]
    assert first is same_frame is restamped and first.frame_id == "cam"
    assert renamed is not first and renamed.frame_id == "other_optical_frame"
    assert renamed.K[0, 0] == 60.0 and zoomed.K[0, 0] == 70.0 and zoomed is not renamed
    assert [m[1].header.stamp.nanosec for m in models] == [  # type: ignore[index]
        10 * MS, 10 * MS, 20 * MS, 30 * MS, 40 * MS]
