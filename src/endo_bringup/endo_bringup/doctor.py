"""``endo-doctor``: start a real node and print the DDS settings it got.

Run it the way you run the other nodes (``make doctor`` does so with the
Makefile's environment) to see which DDS domain, discovery range and Fast DDS
transport a node would use before pointing it at a live endoscope.

* ``--write-profile PATH`` writes the large-frame Fast DDS profile that endo3d
  nodes give themselves (:mod:`endo_io.dds_transport`), for your own
  non-endo3d nodes: ``export FASTRTPS_DEFAULT_PROFILES_FILE=PATH`` before
  starting them.
* ``--check-frames`` sends 60 640×480 float frames at 30 Hz from one node
  process to another over a best-effort subscription, with this environment,
  and says how many arrived.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import rclpy
from rclpy.node import Node

from endo_io.dds_transport import write_profile
from endo_io.process import dds_environment, prepare_transport, split_ros_args


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="endo-doctor",
        description="Print the DDS settings an endo3d node gets in this environment "
        "(exit 1 when discovery may leave the host).",
    )
    parser.add_argument("--write-profile", type=Path, metavar="PATH",
                        help="write the large-frame Fast DDS profile to PATH and exit")
    parser.add_argument("--check-frames", action="store_true",
                        help="also send 60 640x480 32FC1 frames at 30 Hz between two node "
                        "processes and report how many arrived")  # fmt: skip
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Print the node's DDS environment as JSON; exit 1 when discovery may leave the host."""
    args = list(sys.argv if argv is None else argv)
    ours, ros = split_ros_args(args)
    options = _parser().parse_args(ours)
    if options.write_profile is not None:
        path = write_profile(options.write_profile)
        print(f"wrote {path}; for your own nodes: export FASTRTPS_DEFAULT_PROFILES_FILE={path}")
        return 0
    transport = prepare_transport()
    rclpy.init(args=ros)
    try:
        node = Node("endo_doctor")
        env = dds_environment(node)
        node.destroy_node()
    finally:
        rclpy.shutdown()
    report: dict[str, object] = {
        "domain_id": env.domain_id,
        "discovery_range": env.discovery_range,
        "static_peers": env.static_peers,
        "rmw_implementation": env.rmw_implementation,
        "loopback_only": env.loopback_only,
        "transport": transport.description,
        "transport_source": transport.source,
        "transport_variables": dict(transport.variables),
    }
    if options.check_frames:
        from endo_bringup.frame_probe import ProbeError, run_probe

        try:
            result = run_probe(dict(os.environ))
            report["large_frames"] = {
                "received": result.received,
                "sent": result.expected,
                "latency_median_ms": round(result.latency_median_ms, 2),
            }
        except ProbeError as error:
            report["large_frames"] = {"error": str(error)}
    print(json.dumps(report, indent=2))
    return 0 if env.loopback_only else 1


if __name__ == "__main__":
    sys.exit(main())
