"""Running one endo3d node as an OS process: init, spin, clean shutdown.

Every console script of a node calls :func:`run_node`. It logs the DDS
settings the process actually got (domain, discovery range, RMW), warns when
discovery is not restricted (the default Fast DDS discovery multicasts on
every interface), and turns SIGINT and SIGTERM into an orderly shutdown so
that nodes holding files (the recorder) can finalise them.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.utilities import get_rmw_implementation_identifier


@dataclass(frozen=True)
class DdsEnvironment:
    """The DDS settings of this process, as rclpy and the environment give them."""

    domain_id: int
    discovery_range: str
    static_peers: str
    rmw_implementation: str

    @property
    def loopback_only(self) -> bool:
        """True when discovery cannot leave this machine."""
        return self.discovery_range in ("LOCALHOST", "OFF")


def dds_environment(node: Node) -> DdsEnvironment:
    """Read the DDS settings that ``node``'s context was created with."""
    return DdsEnvironment(
        domain_id=int(node.context.get_domain_id()),
        discovery_range=os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "SYSTEM_DEFAULT"),
        static_peers=os.environ.get("ROS_STATIC_PEERS", ""),
        rmw_implementation=get_rmw_implementation_identifier(),
    )


def log_dds_environment(node: Node) -> DdsEnvironment:
    """Log the DDS settings once at start-up; warn when discovery may leave the host."""
    env = dds_environment(node)
    text = (
        f"DDS: domain {env.domain_id}, discovery range {env.discovery_range}, "
        f"rmw {env.rmw_implementation}"
    )
    if env.loopback_only:
        node.get_logger().info(text)
    else:
        node.get_logger().warning(
            text + " (discovery may multicast on every interface; set "
            "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST to keep traffic on this machine)"
        )
    return env


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Create a node with ``factory`` and spin it until SIGINT or SIGTERM.

    ``args`` are the ROS arguments (``--ros-args ...``); ``sys.argv`` by default.
    Returns the process exit code: the node's ``exit_code`` attribute when it
    has one (a replay that hit a damaged bag sets it), else 0.
    """
    # rclpy's default signal handlers cover SIGINT and SIGTERM: both shut the
    # context down, spin() returns, and the node's close() still runs below.
    rclpy.init(args=list(sys.argv if args is None else args))
    node: Node | None = None
    try:
        node = factory()
        log_dds_environment(node)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if callable(close):
                close()
            node.destroy_node()
        # try_shutdown: SIGINT or the node itself may have shut the context
        # down already, and a later rclpy.init() in this process must work.
        rclpy.try_shutdown()
    return int(getattr(node, "exit_code", 0) or 0)


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split a command line into (our arguments, ROS arguments).

    ROS arguments are the ``--ros-args ... [--]`` blocks; they go to
    ``rclpy.init`` (with the program name first), everything else to argparse.
    Unlike ``rclpy.utilities.remove_ros_args``, a ``FROM:=TO`` value of our own
    ``--remap`` option stays ours: rcl would otherwise take it for a
    (deprecated) bare remap rule.
    """
    ours: list[str] = []
    ros: list[str] = list(argv[:1])
    inside = False
    for arg in argv[1:]:
        if arg == "--ros-args":
            inside = True
            ros.append(arg)
        elif inside and arg == "--":
            inside = False
            ros.append(arg)
        elif inside:
            ros.append(arg)
        else:
            ours.append(arg)
    return ours, ros
