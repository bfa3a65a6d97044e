"""Every package is a proper ament_python package that colcon builds.

Users drop `src/` into a normal ROS 2 workspace and run `colcon build`; this
test does exactly that in a temporary folder and checks what `ros2 run` and
the ament index need: the package marker, package.xml, and each console
script under lib/<package>/.
"""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from catkin_pkg.package import parse_package

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in (ROOT / "src").glob("*/package.xml"))
EXPECTED = {
    "endo_io", "endo_calib", "endo_sfs", "endo_flow", "endo_tracker_bridge", "endo_sim",
    "endo_bringup", "endo_process", "endo_foxglove",
}


#: Executable names: ``endo-<name>`` in lowercase words joined by "-" (a node's
#: executable is its ROS node name with "-": endo-photometric-correction,
#: endo-sfs, endo-tracker-bridge; a CLI's names its task: endo-calibrate).
EXECUTABLE_NAME = re.compile(r"endo(-[a-z0-9]+)+")
#: Old executable names kept working for one release: old name → its new name.
ALIASES = {"photometric_correction": "endo-photometric-correction"}


def _console_script_targets(setup_py: Path) -> dict[str, str]:
    """Console scripts a setup.py declares (name → module:function), read without running it."""
    tree = ast.parse(setup_py.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    assert isinstance(value, ast.List)
                    pairs = [ast.literal_eval(e).split("=") for e in value.elts]
                    return {name.strip(): target.strip() for name, target in pairs}
    return {}


def _console_scripts(setup_py: Path) -> list[str]:
    """Names of the console scripts a setup.py declares."""
    return list(_console_script_targets(setup_py))


def test_workspace_has_every_package():
    assert set(PACKAGES) == EXPECTED


def test_executables_follow_one_naming_scheme():
    scripts: dict[str, str] = {}
    for name in PACKAGES:
        scripts.update(_console_script_targets(ROOT / "src" / name / "setup.py"))
    assert {"endo-sfs", "endo-photometric-correction", "endo-tracker-bridge"} <= set(scripts)
    for script, target in scripts.items():
        if script in ALIASES:
            assert scripts[ALIASES[script]] == target, f"{script} must run what replaced it"
        else:
            assert EXECUTABLE_NAME.fullmatch(script), f"{script} does not follow endo-<name>"


@pytest.mark.parametrize("name", PACKAGES)
def test_package_xml_is_valid_format_3_ament_python(name):
    package = parse_package(str(ROOT / "src" / name / "package.xml"))
    package.validate()
    assert package.package_format == 3
    assert package.name == name
    assert package.get_build_type() == "ament_python"
    assert (ROOT / "src" / name / "resource" / name).is_file()
    assert (ROOT / "src" / name / "setup.cfg").is_file()


def test_colcon_builds_every_package_with_its_console_scripts(tmp_path):
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        colcon = Path(shutil.which("colcon") or "colcon")
    result = subprocess.run(
        [
            str(colcon), "--log-base", str(tmp_path / "log"), "build",
            "--base-paths", str(ROOT / "src"),
            "--build-base", str(tmp_path / "build"),
            "--install-base", str(tmp_path / "install"),
            "--event-handlers", "console_direct-",
        ],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert f"{len(PACKAGES)} packages finished" in result.stdout + result.stderr
    for name in PACKAGES:
        prefix = tmp_path / "install" / name
        assert (prefix / "share/ament_index/resource_index/packages" / name).is_file()
        assert (prefix / "share" / name / "package.xml").is_file()
        for script in _console_scripts(ROOT / "src" / name / "setup.py"):
            assert (prefix / "lib" / name / script).is_file(), f"{name}: ros2 run needs {script}"
    # `ros2 launch endo_bringup endo3d.launch.py` and its default parameter file
    share = tmp_path / "install" / "endo_bringup" / "share" / "endo_bringup"
    assert (share / "launch" / "endo3d.launch.py").is_file()
    assert (share / "config" / "endo3d.yaml").is_file()
