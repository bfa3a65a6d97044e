"""Workspace-wide pytest settings.

DDS stays on loopback in every test, however pytest was started: `make test`
exports these already; a bare `pytest` run gets the same defaults here, before
any test imports rclpy.
"""

from __future__ import annotations

import os

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", "42")
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
