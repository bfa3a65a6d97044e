"""endo-sim render: the size estimate it warns with, and the warning itself."""

from __future__ import annotations

from pathlib import Path

import pytest

from endo_sim.bagout import estimated_size, write_bag
from endo_sim.cli import LARGE_BAG_BYTES, _warn_if_large
from endo_sim.sequences import SimulationConfig, build_sequence


def test_the_estimate_is_near_the_written_size(tmp_path: Path) -> None:
    sequence = build_sequence(SimulationConfig(scene="abdomen", width=320, height=240,
                                               duration_s=0.5, depth_every=2, seed=3))
    done: list[int] = []
    summary = write_bag(sequence, tmp_path / "small.mcap", progress=done.append)
    assert done == list(range(1, 16))  # one call per image, in order
    estimate = estimated_size(sequence.config, len(sequence.frame_times_ns))
    assert estimate.depth_frames == 8
    assert 0.6 < estimate.total_bytes / summary.bag_bytes < 1.5


def test_a_large_bag_is_announced_with_how_to_keep_depth_sparse(
    capsys: pytest.CaptureFixture[str],
) -> None:
    estimate = estimated_size(SimulationConfig(scene="colon", depth_every=1), 300)
    assert estimate.total_bytes > LARGE_BAG_BYTES
    _warn_if_large(estimate, 1, 30.0)
    line = capsys.readouterr().err.strip()
    assert len(line.splitlines()) == 1 and "--depth-every 30" in line and "MB" in line
    _warn_if_large(estimated_size(SimulationConfig(scene="colon", depth_every=30), 300), 30, 30.0)
    assert capsys.readouterr().err == ""
