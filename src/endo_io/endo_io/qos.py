"""QoS presets following REP 2003 (sensor data and map QoS).

* Subscriptions to sensor streams (images, camera_info, tracker poses) use
  the sensor-data profile: best effort, keep last 5, volatile. A best-effort
  subscription matches both reliable and best-effort publishers, so a node
  never silently misses a driver that publishes either way.
* Publishers are reliable, keep last ``depth``, and accept QoS overrides from
  parameters (``qos_overrides./topic.publisher.reliability`` and friends), as
  image_pipeline's nodes do. A user who wants best effort for a wireless link
  sets it at launch without code changes.
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

#: Subscription profile for sensor streams (REP 2003).
SENSOR_DATA_QOS: QoSProfile = qos_profile_sensor_data


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


def publisher_overrides() -> QoSOverridingOptions:
    """Allow history, depth, reliability and durability to be overridden by parameters."""
    return QoSOverridingOptions.with_default_policies()


def create_reliable_publisher(node: Node, msg_type: type, topic: str, depth: int = 10) -> Publisher:
    """Create a reliable publisher whose QoS can be overridden through parameters."""
    return node.create_publisher(
        msg_type, topic, reliable_qos(depth), qos_overriding_options=publisher_overrides()
    )
