"""Who else is on this ROS domain: another graph's nodes and publishers, before we start ours.

Two ``endo-launch`` runs in one ROS domain see each other's topics: each
graph's nodes take the other's frames, and a recorder keeps both graphs'
outputs mixed. :func:`graph_conflicts` looks at the domain through rclpy's
graph introspection (after a short discovery wait) for nodes with our nodes'
names in our namespace and for publishers on the topics our graph will
publish, and names them, so that the launcher can refuse to start.
"""

from __future__ import annotations

import os
import time
from collections.abc import Collection

#: What rcl names a publisher's node before discovery has told it the node's name.
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"


def _qualified(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def graph_conflicts(
    topics: Collection[str],
    node_names: Collection[str],
    *,
    discovery_s: float = 3.0,
) -> list[str]:
    """What already runs on this process's ROS domain that would mix with our graph.

    Args:
        topics: fully qualified topics our graph will publish.
        node_names: fully qualified names of the nodes it will start
            (``/rig1/sfs``).
        discovery_s: how long to let discovery find the others (on loopback
            0.3-1.8 s was measured at load 15; the wait ends early once
            something was found and did not change for half a second).

    Returns:
        One entry per conflict, ``/sfs (node)`` or ``/endoscope/points
        (published by /sfs)``, sorted; empty when the domain is free.
    """
    import rclpy
    from rclpy.context import Context

    context = Context()
    # not the launcher's own command line (rclpy's default): its `--remap FROM:=TO`
    # reads to rcl as the deprecated remap syntax, applied here with a warning each
    rclpy.init(args=["endo-launch"], context=context)
    try:
        probe = rclpy.create_node(f"endo_launch_probe_{os.getpid()}", context=context)
        found: list[str] = []
        deadline = time.monotonic() + discovery_s
        while True:
            now = time.monotonic()
            current = _conflicts(probe, topics, node_names)
            if current != found:
                found, changed = current, now
            # a publisher seen before its node's name (rcl's _NODE_NAME_UNKNOWN_) is
            # not settled: under load the name came later than half a second
            settled = found and not any(UNKNOWN_NODE in entry for entry in found)
            if now >= deadline or (settled and now - changed > 0.5):
                return found
            time.sleep(0.1)
    finally:
        rclpy.shutdown(context=context)


def _conflicts(probe: object, topics: Collection[str], node_names: Collection[str]) -> list[str]:
    from rclpy.node import Node

    assert isinstance(probe, Node)
    present = {
        _qualified(namespace, name)
        for name, namespace in probe.get_node_names_and_namespaces()
    }
    found = {f"{name} (node)" for name in node_names if name in present}
    for topic in topics:
        for info in probe.get_publishers_info_by_topic(topic):
            owner = _qualified(info.node_namespace, info.node_name)
            found.add(f"{topic} (published by {owner})")
    return sorted(found)
