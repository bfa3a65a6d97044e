"""QoS presets following REP 2003 (sensor data and map QoS).

* Subscriptions to sensor streams (images, camera_info) use the sensor-data
  profile: best effort, keep last 5, volatile. A best-effort subscription
  matches both reliable and best-effort publishers, so a node never silently
  misses a driver that publishes either way. Pose streams (the tracker's, the
  camera's) are the same but keep the last :data:`POSE_STREAM_DEPTH`
  (:data:`POSE_STREAM_QOS`): every sample counts there.
* Publishers are reliable, keep last ``depth``, and accept QoS overrides from
  parameters (``qos_overrides./topic.publisher.reliability`` and friends), as
  image_pipeline's nodes do. A user who wants best effort for a wireless link
  sets it at launch without code changes.
* The frame a node processes (the raw image of the correction, the corrected
  image of SFS, the relative depth of flow) comes through
  :data:`NEWEST_FRAME_QOS`: best effort, keep last :data:`NEWEST_FRAME_DEPTH`.
  A frame that has waited there longer than ``frame_backlog_s`` is stale:
  the node then takes the frames behind it, processes the newest and counts
  the others as skipped (:meth:`endo_io.diagnostics.InputHealth.subscribe`
  with ``newest=True``; for a second after a skip every frame with a newer
  one behind it is stale), so a stage slower than the camera works on the
  present, never on a backlog, while a stall shorter than the limit skips
  nothing. Why not keep-last-1: DDS
  would then overwrite the stale frames where the node cannot see them, and
  a skip would be indistinguishable from a frame lost in transport.
* The inputs a node takes by stamp when its frame arrives (flow's corrected
  image and camera_info, taken when the relative depth of their stamp comes:
  :meth:`endo_io.diagnostics.InputHealth.subscribe_passive`) wait in DDS
  until then: :data:`BY_STAMP_QOS`, best effort, keep last
  :data:`BY_STAMP_DEPTH`. A pose stream taken that way (flow's poses, taken
  when a depth arrives and every :data:`PASSIVE_POSE_TAKE_PERIOD_S`) waits in
  :data:`PASSIVE_POSE_QOS`: keep last :data:`PASSIVE_POSE_DEPTH`, 2 s of a
  250 Hz tracker.
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import QoSOverridingOptions


def best_effort_qos(depth: int) -> QoSProfile:
    """Best-effort, volatile, keep-last ``depth`` subscription profile."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


#: Subscription profile for sensor streams (REP 2003).
SENSOR_DATA_QOS: QoSProfile = qos_profile_sensor_data

#: Samples a pose-stream subscription holds while its node is busy: every
#: tracker sample counts (a pose buffer interpolates between them), and a pose
#: is ~100 bytes, so the queue covers 0.4 s at 250 Hz, 1.7 s at 60 Hz: a node
#: stalled by a slow frame or a loaded machine takes them all afterwards
#: instead of losing all but the last five.
POSE_STREAM_DEPTH = 100

#: Subscription profile of tracker and camera pose streams: best effort (it
#: matches reliable and best-effort publishers), keep last POSE_STREAM_DEPTH.
POSE_STREAM_QOS = best_effort_qos(POSE_STREAM_DEPTH)

#: Frames a newest-frame subscription holds while its node is busy: 8 frames
#: cover 0.27 s at 30 fps, longer than any stage takes per frame here, so the
#: node itself sees (and counts) every frame it skips.
NEWEST_FRAME_DEPTH = 8

#: Subscription profile of the frame a node processes (see the module docstring).
NEWEST_FRAME_QOS = best_effort_qos(NEWEST_FRAME_DEPTH)


def reliable_qos(depth: int = 10, *, latched: bool = False) -> QoSProfile:
    """Reliable keep-last profile for publishers.

    ``latched=True`` gives transient-local durability, for topics such as a
    calibration or a static transform that late subscribers must still get.
    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


#: Publisher profile of endo_flow's fused map (``/endoscope/map``): reliable,
#: keep last 1, transient local, so that a viewer started after the last map
#: still gets it. A recording of the map must offer the same (endo-process
#: writes it as its ``offered_qos_profiles``): a replay publishes with the
#: recorded offer, and a transient-local subscriber (endo-foxglove, the RViz
#: config) matches no volatile publisher.
MAP_QOS: QoSProfile = reliable_qos(1, latched=True)


def publisher_overrides() -> QoSOverridingOptions:
    """Allow history, depth, reliability and durability to be overridden by parameters."""
    return QoSOverridingOptions.with_default_policies()


def create_reliable_publisher(node: Node, msg_type: type, topic: str, depth: int = 10) -> Publisher:
    """Create a reliable publisher whose QoS can be overridden through parameters."""
    return node.create_publisher(
        msg_type, topic, reliable_qos(depth), qos_overriding_options=publisher_overrides()
    )

#: Messages a by-stamp input holds until they are taken: 1 s at 30 fps, longer
#: than the slowest stage's latency here (SFS's p99 at full resolution, 0.4 s),
#: so the image of a depth that comes late is still there.
BY_STAMP_DEPTH = 30

#: Subscription profile of an input taken by stamp (see the module docstring).
BY_STAMP_QOS = best_effort_qos(BY_STAMP_DEPTH)

#: Poses a pose stream taken by its node (not one callback each) holds until
#: they are taken: 2 s at 250 Hz (a pose is ~100 bytes: 50 kB). The node takes
#: them at least every :data:`PASSIVE_POSE_TAKE_PERIOD_S` while its executor
#: runs; the depth covers a stall (a slow frame, a loaded machine) of up to
#: 2 s less that period. With :data:`POSE_STREAM_DEPTH` (0.4 s at 250 Hz) a
#: depth gap longer than 0.4 s overwrote poses in DDS, where nobody counted
#: them (review of issue 15's changes).
PASSIVE_POSE_DEPTH = 500

#: Subscription profile of a pose stream taken by its node (flow's).
PASSIVE_POSE_QOS = best_effort_qos(PASSIVE_POSE_DEPTH)

#: Longest interval between two takes of a passive pose stream, seconds, even
#: when no frame comes (a node idle 10 times a second costs ~10 executor
#: wake-ups, against 250 for a callback per pose).
PASSIVE_POSE_TAKE_PERIOD_S = 0.1
