"""The flow node's warm-up: the first-frame work done on synthetic frames before it subscribes."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

from endo_flow.pipeline import FlowOptions
from endo_flow.tracking import TrackingOptions
from endo_flow.warm_up import warm_up_pipeline
from endo_io.camera import CameraModel


def test_the_warm_up_loads_the_cloud_and_map_kernels_in_this_process() -> None:
    # a fresh process: nothing of the map's numba kernels is loaded before the warm-up
    code = (
        "from endo_flow.cloud import _grid_normals, _in_range\n"
        "from endo_flow.triangulation import _triangulate\n"
        "from endo_flow.voxel_map import _insert\n"
        "from endo_flow.pipeline import FlowOptions\n"
        "from endo_flow.warm_up import warm_up_pipeline\n"
        "from endo_io.camera import CameraModel\n"
        "kernels = (_triangulate, _in_range, _grid_normals, _insert)\n"
        "print(*(len(k.signatures) for k in kernels))\n"
        "camera = CameraModel.pinhole(160, 120, 140.0, 140.0, 79.5, 59.5)\n"
        "warm_up_pipeline(FlowOptions(), camera)\n"
        "print(*(len(k.signatures) for k in kernels))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=300, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    before, after = (line.split() for line in result.stdout.splitlines())
    # triangulation's, the world cloud's and the map's kernels: none loaded before, each after
    assert before == ["0"] * 4 and after == ["1"] * 4


def test_the_warm_up_runs_at_odd_sizes_and_tracking_resolutions() -> None:
    camera = CameraModel.pinhole(201, 151, 170.0, 170.0, 100.0, 75.0)
    for downsample in (1, 2, 3):
        options = replace(FlowOptions(), tracking=replace(TrackingOptions(), downsample=downsample))
        assert warm_up_pipeline(options, camera) > 0.0
