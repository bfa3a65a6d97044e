"""The flow node's warm-up: the first-frame work done on synthetic frames before it subscribes."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np

from endo_flow.pipeline import FlowOptions
from endo_flow.tracking import TrackingOptions
from endo_flow.warm_up import warm_up_pipeline
from endo_io.camera import CameraModel


def test_the_warm_up_loads_the_cloud_and_map_kernels_in_this_process() -> None:
    # a fresh process: nothing of the map's numba kernels is loaded before the warm-up
    code = (
        "from endo_flow.cloud import _kept_normals\n"
        "from endo_flow.triangulation import _triangulate\n"
        "from endo_flow.voxel_map import _insert, _published\n"
        "from endo_flow.pipeline import FlowOptions\n"
        "from endo_flow.warm_up import warm_up_pipeline\n"
        "from endo_io.camera import CameraModel\n"
        "kernels = (_triangulate, _kept_normals, _insert, _published)\n"
        "print(*(len(k.signatures) for k in kernels))\n"
        "camera = CameraModel.pinhole(160, 120, 140.0, 140.0, 79.5, 59.5)\n"
        "warm_up_pipeline(FlowOptions(), camera)\n"
        "print(*(len(k.signatures) for k in kernels))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=300, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    before, after = (line.split() for line in result.stdout.splitlines())
    # triangulation's, the world cloud's and the map's kernels (insert, message): none loaded
    # before, each after
    assert before == ["0"] * 4 and after == ["1"] * 4


def test_the_warm_up_runs_at_odd_sizes_and_tracking_resolutions() -> None:
    camera = CameraModel.pinhole(201, 151, 170.0, 170.0, 100.0, 75.0)
    for downsample in (1, 2, 3):
        options = replace(FlowOptions(), tracking=replace(TrackingOptions(), downsample=downsample))
        assert warm_up_pipeline(options, camera) > 0.0


#: Run in a fresh process on frames saved by the test: after the node's warm-up, the
#: real frames load no numba kernel (or variant) of their own. Before the warm-up
#: reseeded with live tracks, the tracker's highlight detection compiled a variant at
#: the first reseed of a fresh clone (~0.9 s, while SFS skipped frames).
_FRESH_PROCESS_CHECK = """
import importlib, pkgutil, sys
import numba, numpy as np
import endo_flow, endo_sfs
from endo_flow.node import PARAMETERS, pipeline_options
from endo_flow.pipeline import FlowFrame, FlowPipeline
from endo_flow.warm_up import warm_up_pipeline
from endo_io.camera import CameraModel

saved = np.load(sys.argv[1])
camera = CameraModel.load_yaml(sys.argv[2])
kernels = {}
for package in (endo_flow, endo_sfs):
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        kernels.update({f"{module.__name__}.{n}": f for n, f in vars(module).items()
                        if isinstance(f, numba.core.registry.CPUDispatcher)})
values = {p.name: p.default for p in PARAMETERS}
values["tracking_downsample"] = 1
options = pipeline_options(values)
warm_up_pipeline(options, camera)
before = {k: len(f.signatures) for k, f in kernels.items()}
pipeline = FlowPipeline(options)
clouds = 0
for stamp, image, depth, pose in zip(saved["stamps"], saved["images"], saved["depths"],
                                     saved["poses"], strict=True):
    clouds += len(pipeline.process(FlowFrame(int(stamp), image, depth, camera, pose)).points) > 0
print(clouds)
print(sorted(k for k, f in kernels.items() if len(f.signatures) > before[k]))
"""


def test_after_the_warm_up_real_frames_load_no_kernel_of_their_own(moving, kit, tmp_path) -> None:
    frames = 40  # past the first reseed with live tracks (reseed_every 10) and the first cloud
    poses = kit.tracked_poses(moving.poses[:frames])
    saved = tmp_path / "frames.npz"
    np.savez(saved, stamps=moving.stamps[:frames], images=np.stack(moving.images[:frames]),
             depths=np.stack([d / kit.S_TRUE for d in moving.depths[:frames]]).astype(np.float32),
             poses=poses)  # fmt: skip
    camera = tmp_path / "camera.yaml"
    moving.camera.save_yaml(camera)
    result = subprocess.run([sys.executable, "-c", _FRESH_PROCESS_CHECK, str(saved), str(camera)],
                            capture_output=True, text=True, timeout=600, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    clouds, loaded = result.stdout.strip().splitlines()[-2:]
    assert int(clouds) > 0  # the cloud and map path ran
    assert loaded == "[]"
