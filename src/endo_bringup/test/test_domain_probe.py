"""endo_bringup.domain_probe: the launcher's look at its ROS domain keeps to itself."""

from __future__ import annotations

import sys

import pytest

from endo_bringup.domain_probe import graph_conflicts


def test_the_launchers_own_remap_arguments_are_not_read_by_rcl(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture
) -> None:
    # `endo-launch live --remap /tracker/pose:=/ndi/scope/pose` printed rcl's
    # "Found remap rule '/tracker/pose:=/ndi/scope/pose'. This syntax is deprecated. Use
    # '--ros-args --remap ...' instead." once per rule: rclpy.init read the launcher's argv
    monkeypatch.setattr(sys, "argv", ["endo-launch", "live", "--remap",
                                      "/tracker/pose:=/ndi/scope/pose"])  # fmt: skip
    assert graph_conflicts(["/probe_test/endoscope/points"], ["/probe_test/sfs"],
                           discovery_s=0.3) == []  # fmt: skip
    err = capfd.readouterr().err
    assert "remap rule" not in err and "deprecated" not in err, err
