"""/tf and /tf_static in an endo-process output, read back by rosbags and the mcap library.

Both readers decode ``tf2_msgs/msg/TFMessage`` from the schema stored in the
file (rosbags with an empty type store), so no tf2 package is involved
anywhere. The per-frame edge must be the camera pose at the image stamp (the
written /endoscope/pose interpolated there, and within the tracker's error of
the simulator's truth); the static edges the parameters' ``T_world_tracker``
and the inverse of the hand–eye ``T_marker_camera``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from endo_io import topics
from endo_io.bag import BagReader, deserialize
from endo_io.pose import pose_to_matrix
from endo_io.pose_buffer import PoseBuffer
from endo_io.tf import StampedTransform
from endo_tracker_bridge.handeye_file import HandEyeCalibration

from .conftest import process_first_frames

FRAMES = 12


@pytest.fixture(scope="module")
def short_run(
    calibrations: tuple[Path, Path], phantom_params: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    output = tmp_path_factory.mktemp("tf") / "phantom_tf.mcap"
    return process_first_frames(output, calibrations, phantom_params, FRAMES)


def _edge(t) -> tuple[str, str, int, np.ndarray]:
    tr, q = t.transform.translation, t.transform.rotation
    edge = StampedTransform(
        0, "a", "b", np.array([tr.x, tr.y, tr.z]), np.array([q.x, q.y, q.z, q.w])
    )
    stamp = t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec
    return t.header.frame_id, t.child_frame_id, stamp, edge.matrix()


def _with_rosbags(path: Path) -> dict[str, list]:
    got: dict[str, list] = {topics.TF: [], topics.TF_STATIC: []}
    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        wanted = [c for c in reader.connections if c.topic in got]
        for connection, _, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, connection.msgtype)
            got[connection.topic] += [_edge(t) for t in msg.transforms]
    return got


def _with_mcap(path: Path) -> dict[str, list]:
    got: dict[str, list] = {topics.TF: [], topics.TF_STATIC: []}
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(topics=list(got)):
            got[channel.topic] += [_edge(t) for t in msg.transforms]
    return got


@pytest.mark.parametrize("read", [_with_rosbags, _with_mcap])
def test_tf_is_the_camera_pose_at_each_image_stamp(short_run, read):
    got = read(short_run)
    with BagReader(short_run) as bag:
        images = [deserialize(m) for m in bag.messages(topics=[topics.IMAGE_CORRECTED])]
        poses = sorted(
            (pose_to_matrix(deserialize(m))[::-1]
             for m in bag.messages(topics=[topics.CAMERA_POSE])
             if deserialize(m).header.frame_id == topics.WORLD_FRAME),
            key=lambda p: p[0],
        )
        truth = {}
        for m in bag.messages(topics=[topics.TRUE_CAMERA_POSE]):
            T, stamp = pose_to_matrix(deserialize(m))
            truth[stamp] = T
    buffer = PoseBuffer()
    for stamp, T in poses:
        buffer.insert(stamp, T)
    image_stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in images]
    # The first image is older than the first tracker sample: no pose, no /tf.
    assert [e[2] for e in got[topics.TF]] == image_stamps[1:]
    interpolated = 0
    for parent, child, stamp, T in got[topics.TF]:
        assert (parent, child) == (topics.WORLD_FRAME, images[0].header.frame_id)
        assert np.linalg.norm(T[:3, 3] - truth[stamp][:3, 3]) < 2e-3  # tracker noise, lever arm
        if stamp < buffer.newest_ns:  # a partial run writes poses up to its last frame only
            np.testing.assert_allclose(T, buffer.query(stamp), atol=1e-9)
            interpolated += 1
    assert interpolated >= FRAMES - 2


@pytest.mark.parametrize("read", [_with_rosbags, _with_mcap])
def test_tf_static_holds_the_registration_and_the_hand_eye(
    short_run, read, calibrations, phantom_params
):
    static = read(short_run)[topics.TF_STATIC]
    assert [(p, c) for p, c, _, _ in static] == [
        (topics.WORLD_FRAME, topics.TRACKER_FRAME), (topics.OPTICAL_FRAME, topics.MARKER_FRAME)
    ]
    params = yaml.safe_load(phantom_params.read_text())
    rows = next(v["ros__parameters"]["T_world_tracker"] for v in params.values()
                if "T_world_tracker" in v.get("ros__parameters", {}))
    np.testing.assert_allclose(static[0][3], np.reshape(rows, (4, 4)), atol=1e-9)
    T_marker_camera = HandEyeCalibration.load(calibrations[1]).T_marker_camera
    np.testing.assert_allclose(T_marker_camera @ static[1][3], np.eye(4), atol=1e-9)
    with BagReader(short_run) as bag:
        first = next(iter(bag.messages()))
    assert first.topic == topics.TF_STATIC  # written first: a viewer has it from the start
