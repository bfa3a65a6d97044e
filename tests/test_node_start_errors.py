"""Node executables started as a user starts them, with parameters that cannot work.

Each bad start must end with exactly one line on stderr naming the cause and
exit code 2, never a traceback; an integer given for a double parameter
(``-p solve_scale:=1``) must start the node normally.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from endo_calib.synthetic import synthetic_calibration

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
ENV = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")


def _run(executable: str, *parameters: str) -> subprocess.CompletedProcess[str]:
    args = [str(BIN / executable), "--ros-args"]
    for parameter in parameters:
        args += ["-p", parameter]
    return subprocess.run(args, env=ENV, capture_output=True, text=True, timeout=60)


def _one_line(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def mono_calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("calibration") / "mono.yaml"
    synthetic_calibration(32, 24).save(path)
    return path


@pytest.mark.parametrize(
    ("parameter", "message"),
    [
        ("solve_scale:=5.0", "endo-sfs: parameter solve_scale: 5.0 is out of range [0.1, 1]"),
        ("model:=foo", "endo-sfs: parameter model: 'foo' is not one of near_light, orthographic"),
        ("order:=2.5", "endo-sfs: parameter order: expected an integer, got 2.5"),
    ],
)
def test_sfs_with_a_bad_parameter_says_so_in_one_line(parameter, message):
    assert _one_line(_run("endo-sfs", parameter)) == message


def test_correction_with_a_colour_channel_of_a_mono_calibration_says_so_in_one_line(
    mono_calibration,
):
    line = _one_line(
        _run("photometric_correction", "channel:=red", f"calibration_file:={mono_calibration}")
    )
    assert line == (
        "photometric_correction: parameter channel: 'red' needs a colour calibration, but "
        f"{mono_calibration} has channels mono"
    )
    line = _one_line(_run("photometric_correction", "channel:=infrared"))
    assert "parameter channel: 'infrared' is not one of luminance, red, green, blue, rgb" in line


@pytest.mark.parametrize("output", ["/tracker/marker_pose", "/endoscope/pose"])
def test_bridge_listening_on_its_own_output_says_so_in_one_line(output):
    line = _one_line(_run("endo-tracker-bridge", f"ros_topic:={output}"))
    assert line == (
        f"endo-tracker-bridge: parameter ros_topic: {output!r} is the bridge's own output "
        f"{output}; set it to the tracker driver's topic (default /tracker/pose)"
    )


def test_bridge_with_an_unknown_source_or_unit_says_so_in_one_line():
    line = _one_line(_run("endo-tracker-bridge", "source:=serial"))
    assert line == (
        "endo-tracker-bridge: parameter source: 'serial' is not one of ros, igtl, ndi, csv"
    )
    line = _one_line(_run("endo-tracker-bridge", "ros_unit:=cm"))
    assert line == "endo-tracker-bridge: parameter ros_unit: 'cm' is not one of m, mm"


def _start_and_stop(args: list[str], ready: str, timeout: float = 60.0) -> tuple[int, str]:
    """Start a node, wait for ``ready`` in its log, stop it with SIGINT; (exit code, log)."""
    process = subprocess.Popen(args, env=ENV, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    assert process.stdout is not None
    lines = []
    deadline = time.monotonic() + timeout
    try:
        for line in process.stdout:
            lines.append(line)
            if ready in line or time.monotonic() > deadline:
                break
        time.sleep(0.5)  # spinning, as a user would see it before pressing Ctrl-C
        assert process.poll() is None, "".join(lines)
        process.send_signal(signal.SIGINT)
        rest, _ = process.communicate(timeout=15)
    except BaseException:
        process.kill()
        process.communicate()
        raise
    return process.returncode, "".join(lines) + rest


def test_sfs_takes_an_integer_for_a_double():
    code, log = _start_and_stop(
        [str(BIN / "endo-sfs"), "--ros-args", "-p", "solve_scale:=1", "-p", "roughness:=0"],
        ready="DDS: domain",
    )
    assert "kernels ready" in log and "Traceback" not in log, log
    assert code == 0, log
