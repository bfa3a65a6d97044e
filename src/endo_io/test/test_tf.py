"""/tf and /tf_static written without tf2 read back through rosbags and mcap-ros2-support.

Both readers decode with their own CDR parser from the schema text stored in
the file (rosbags is given an empty type store, so it can only use the bag's
definition), so the values they return check our schema and our bytes.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from endo_io.bag import BagReader, BagWriter, qos_profiles_from_yaml
from endo_io.pose import invert_transform, rigid_transform
from endo_io.tf import (
    TF_MESSAGE_TYPE,
    StampedTransform,
    TransformError,
    camera_transform,
    serialize_tf_message,
    static_transforms,
    tf_message_definition,
    write_tf,
)
from endo_io.topics import (
    MARKER_FRAME,
    OPTICAL_FRAME,
    TF,
    TF_STATIC,
    TRACKER_FRAME,
    WORLD_FRAME,
)

T0 = 1_700_000_000_123_456_789


def camera_poses(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rigid_transform(rng.normal(size=3), rng.normal(size=3) * 0.1) for _ in range(n)]


@pytest.fixture
def calibration() -> dict[str, np.ndarray]:
    return {
        "T_world_tracker": rigid_transform([0.1, -0.2, 3.0], [0.5, -1.25, 0.75]),
        "T_marker_camera": rigid_transform([1.0, 0.5, -0.25], [0.01, -0.02, 0.15]),
    }


def write_bag(path, poses, calibration) -> None:
    with BagWriter(path) as bag:
        edges = static_transforms(**calibration, stamp_ns=T0)
        write_tf(bag, TF_STATIC, edges, T0)
        for i, T in enumerate(poses):
            stamp = T0 + i * 33_333_333
            write_tf(bag, TF, [camera_transform(T, stamp)], stamp)


def as_matrix(translation, rotation) -> np.ndarray:
    return StampedTransform(
        0, "a", "b", np.array(translation, dtype=float), np.array(rotation, dtype=float)
    ).matrix()


def expected_edges(poses, calibration):
    static = [
        (WORLD_FRAME, TRACKER_FRAME, T0, calibration["T_world_tracker"]),
        (OPTICAL_FRAME, MARKER_FRAME, T0, invert_transform(calibration["T_marker_camera"])),
    ]
    dynamic = [
        (WORLD_FRAME, OPTICAL_FRAME, T0 + i * 33_333_333, T) for i, T in enumerate(poses)
    ]
    return static, dynamic


def test_rosbags_reads_tf_and_tf_static_from_the_schema_in_the_file(tmp_path, calibration):
    poses = camera_poses(5, seed=1)
    path = tmp_path / "tf.mcap"
    write_bag(path, poses, calibration)
    static, dynamic = expected_edges(poses, calibration)

    got: dict[str, list] = {TF: [], TF_STATIC: []}
    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            TF: TF_MESSAGE_TYPE, TF_STATIC: TF_MESSAGE_TYPE
        }
        for connection, log_time, raw in reader.messages():
            assert log_time >= T0
            msg = reader.deserialize(raw, connection.msgtype)
            for t in msg.transforms:
                stamp = t.header.stamp.sec * 10**9 + t.header.stamp.nanosec
                tr, q = t.transform.translation, t.transform.rotation
                got[connection.topic].append(
                    (t.header.frame_id, t.child_frame_id, stamp,
                     as_matrix([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]))
                )
    for want, have in ((static, got[TF_STATIC]), (dynamic, got[TF])):
        assert [h[:3] for h in have] == [w[:3] for w in want]
        for (*_, T_have), (*_, T_want) in zip(have, want, strict=True):
            np.testing.assert_allclose(T_have, T_want, atol=1e-12)


def test_mcap_ros2_decoder_reads_the_same_values(tmp_path, calibration):
    poses = camera_poses(3, seed=2)
    path = tmp_path / "tf.mcap"
    write_bag(path, poses, calibration)
    static, dynamic = expected_edges(poses, calibration)

    got: dict[str, list] = {TF: [], TF_STATIC: []}
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema.name == TF_MESSAGE_TYPE and schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            for t in decoded.transforms:
                stamp = t.header.stamp.sec * 10**9 + t.header.stamp.nanosec
                tr, q = t.transform.translation, t.transform.rotation
                got[channel.topic].append(
                    (t.header.frame_id, t.child_frame_id, stamp,
                     as_matrix([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]))
                )
            assert message.log_time >= T0
    for want, have in ((static, got[TF_STATIC]), (dynamic, got[TF])):
        assert [h[:3] for h in have] == [w[:3] for w in want]
        for (*_, T_have), (*_, T_want) in zip(have, want, strict=True):
            np.testing.assert_allclose(T_have, T_want, atol=1e-12)


def test_tf_static_is_recorded_latched_and_tf_volatile(tmp_path, calibration):
    path = tmp_path / "tf.mcap"
    write_bag(path, camera_poses(1, seed=3), calibration)
    with BagReader(path) as bag:
        topics = dict(bag.topics)
    static_qos = qos_profiles_from_yaml(topics[TF_STATIC].offered_qos_profiles)[0]
    tf_qos = qos_profiles_from_yaml(topics[TF].offered_qos_profiles)[0]
    assert static_qos.durability.name == "TRANSIENT_LOCAL" and static_qos.depth == 1
    assert tf_qos.durability.name == "VOLATILE" and tf_qos.reliability.name == "RELIABLE"


def test_bytes_are_canonical_cdr_and_schema_matches_rosbags_own():
    store = get_typestore(Stores.ROS2_JAZZY)
    edges = [
        camera_transform(T, T0 + k)
        for k, T in enumerate(camera_poses(4, seed=4))
    ] + [StampedTransform.from_matrix(np.eye(4), 7, "a", "frame_with_odd_len")]
    ours = serialize_tf_message(edges)
    assert len(ours) % 4 == 0
    decoded = store.deserialize_cdr(ours, TF_MESSAGE_TYPE)
    assert [t.child_frame_id for t in decoded.transforms] == [e.child_frame for e in edges]
    # rosbags re-encodes with zero padding: equal bytes mean ours are canonical.
    theirs = bytes(store.serialize_cdr(decoded, TF_MESSAGE_TYPE))
    assert ours == theirs + bytes(-len(theirs) % 4)
    # The same types and field names as the definition rosbags generates
    # (which spells every type in full and drops the comments).
    text, _ = store.generate_msgdef(TF_MESSAGE_TYPE, ros_version=2)

    def fields_per_type(definition: str) -> dict[str, list[str]]:
        sections = definition.split("=" * 80 + "\n")
        result = {}
        for index, section in enumerate(sections):
            lines = [line.split("#")[0].strip() for line in section.splitlines()]
            lines = [line for line in lines if line]
            name = TF_MESSAGE_TYPE if index == 0 else lines.pop(0).removeprefix("MSG: ")
            result[name] = [line.split()[1] for line in lines]
        return result

    assert fields_per_type(tf_message_definition().text) == fields_per_type(text)


def test_an_empty_message_is_valid_cdr():
    store = get_typestore(Stores.ROS2_JAZZY)
    assert store.deserialize_cdr(serialize_tf_message([]), TF_MESSAGE_TYPE).transforms == []


@pytest.mark.parametrize(
    ("matrix", "parent", "child", "stamp", "cause"),
    [
        (np.full((4, 4), np.nan), "world", "cam", 0, "finite"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "world", "cam", 0, "rotation"),
        (np.eye(4), "", "cam", 0, "empty"),
        (np.eye(4), "cam", "cam", 0, "own parent"),
        (np.eye(4), "world", "cam", -1, "out of range"),
        (np.eye(4), "world", "cam", 2**31 * 10**9, "out of range"),
    ],
)
def test_bad_transforms_are_refused_with_the_cause(matrix, parent, child, stamp, cause):
    with pytest.raises(TransformError, match=cause):
        StampedTransform.from_matrix(matrix, stamp, parent, child)


def test_static_transforms_skip_what_is_unknown(calibration):
    assert static_transforms(T_world_tracker=None, T_marker_camera=None) == []
    only = static_transforms(T_world_tracker=None, T_marker_camera=calibration["T_marker_camera"])
    assert [(e.parent_frame, e.child_frame) for e in only] == [(OPTICAL_FRAME, MARKER_FRAME)]
    # The recorded edge composes with the hand-eye transform to the identity.
    np.testing.assert_allclose(
        calibration["T_marker_camera"] @ only[0].matrix(), np.eye(4), atol=1e-12
    )


def test_write_tf_refuses_an_empty_message(tmp_path):
    with BagWriter(tmp_path / "x.mcap") as bag, pytest.raises(TransformError, match="at least"):
        write_tf(bag, TF, [], T0)


def test_importing_the_module_loads_no_rclpy():
    code = "import sys\nimport endo_io.tf\nprint('rclpy' in sys.modules)\n"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.strip() == "False"
