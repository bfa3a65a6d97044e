"""``endo-doctor``: start a real node and print the DDS settings it got.

Run it the way you run the other nodes (``make doctor`` does so with the
Makefile's environment) to see which DDS domain and discovery range a node
would use before pointing it at a live endoscope.
"""

from __future__ import annotations

import json
import sys

import rclpy
from rclpy.node import Node

from endo_io.process import dds_environment


def main(argv: list[str] | None = None) -> int:
    """Print the node's DDS environment as JSON; exit 1 when discovery may leave the host."""
    rclpy.init(args=sys.argv if argv is None else argv)
    try:
        node = Node("endo_doctor")
        env = dds_environment(node)
        node.destroy_node()
    finally:
        rclpy.shutdown()
    report = {
        "domain_id": env.domain_id,
        "discovery_range": env.discovery_range,
        "static_peers": env.static_peers,
        "rmw_implementation": env.rmw_implementation,
        "loopback_only": env.loopback_only,
    }
    print(json.dumps(report, indent=2))
    return 0 if env.loopback_only else 1


if __name__ == "__main__":
    sys.exit(main())
