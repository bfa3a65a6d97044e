"""Nodes started with no Fast DDS variables move full-size float frames whole.

Two endo3d node processes (``endo_bringup.frame_probe``, both through
``endo_io.process.run_node``) with ``FASTRTPS_DEFAULT_PROFILES_FILE``,
``FASTDDS_DEFAULT_PROFILES_FILE`` and ``FASTDDS_BUILTIN_TRANSPORTS`` unset: 60
frames of 640×480 32FC1 (1.2 MB) at 30 Hz from a reliable publisher reach a
best-effort subscription, every one of them (from the first that arrives on:
before it, discovery is still going on). With Fast DDS's own defaults such a
frame crosses in UDP fragments and a best-effort reader loses most of them
(``docs/benchmarks.md``, "DDS transport for large frames").
"""

from __future__ import annotations

import os

import pytest

from endo_bringup.frame_probe import run_probe
from endo_io.dds_transport import BUILTIN_TRANSPORTS_VARIABLE, PROFILE_VARIABLES

pytestmark = pytest.mark.ros


def test_nodes_without_profile_variables_receive_every_large_frame():
    env = {k: v for k, v in os.environ.items()
           if k not in (*PROFILE_VARIABLES, BUILTIN_TRANSPORTS_VARIABLE)}  # fmt: skip
    result = run_probe(env, frames=60, rate_hz=30.0, width=640, height=480)
    assert result.first < 30, result  # most of the frames were sent after discovery
    assert result.lost == [], result
    assert result.received == result.expected
