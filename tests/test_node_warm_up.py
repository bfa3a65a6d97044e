"""Nodes warm up on a frame of the stream's camera before they subscribe.

``endo-sfs`` and ``endo-flow`` take ``warm_up_camera_file`` (a camera_calibration
YAML): they say in a log line that they warmed up on a frame of that size, and
they do it before they are up (the DDS line :func:`endo_io.process.run_node`
logs once the constructor returned: what endo-launch and the demo wait for).
The correction node warms up on its calibration's size. A file that is not a
camera stops the node with one line naming the parameter and exit code 2.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from endo_calib.synthetic import synthetic_calibration
from endo_io.camera import CameraModel

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
ENV = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1",
           RCUTILS_LOGGING_BUFFERED_STREAM="0")  # fmt: skip
UP = re.compile(r"DDS: domain \d+")


def _start_and_stop(executable: str, *parameters: str, timeout_s: float = 120.0) -> str:
    """The node's log from its start until it is up, then SIGINT."""
    args = [str(BIN / executable), "--ros-args"]
    for parameter in parameters:
        args += ["-p", parameter]
    process = subprocess.Popen(args, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)  # fmt: skip
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    assert process.stdout is not None
    try:
        for line in process.stdout:
            lines.append(line.rstrip("\n"))
            if UP.search(line) or time.monotonic() > deadline:
                break
    finally:
        process.send_signal(signal.SIGINT)
        process.wait(30)
    return "\n".join(lines)


@pytest.fixture(scope="module")
def camera_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("camera") / "camera.yaml"
    CameraModel.pinhole(96, 72, 80.0, 80.0, 47.5, 35.5).save_yaml(path)
    return path


@pytest.mark.parametrize("executable", ["endo-sfs", "endo-flow"])
def test_a_node_warms_up_on_the_cameras_size_before_it_is_up(executable, camera_file):
    log = _start_and_stop(executable, f"warm_up_camera_file:={camera_file}")
    warmed = re.search(rf"warmed up on a 96x72 frame of {re.escape(str(camera_file))} in "
                       r"\d+\.\d+ s", log)  # fmt: skip
    up = UP.search(log)
    assert warmed is not None and up is not None, log
    assert warmed.start() < up.start()


def test_the_correction_node_warms_up_on_its_calibrations_size(tmp_path):
    path = tmp_path / "mono.yaml"
    synthetic_calibration(32, 24).save(path)
    log = _start_and_stop("endo-photometric-correction", f"calibration_file:={path}")
    warmed = re.search(r"warmed up on a 32x24 mono8 frame", log)
    up = UP.search(log)
    assert warmed is not None and up is not None, log
    assert warmed.start() < up.start()


@pytest.mark.parametrize("executable", ["endo-sfs", "endo-flow"])
def test_a_warm_up_file_that_is_not_a_camera_says_so_in_one_line(executable, tmp_path):
    missing = tmp_path / "missing.yaml"
    result = subprocess.run(
        [str(BIN / executable), "--ros-args", "-p", f"warm_up_camera_file:={missing}"],
        env=ENV, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"{executable}: parameter warm_up_camera_file: {missing} is not "
                               "a camera_calibration YAML")  # fmt: skip
