"""Every package root exports its public API, and importing a root stays cheap."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from endo_io.lazy_exports import type_checking_imports

ROOTS = ("endo_io", "endo_calib", "endo_sfs", "endo_sim", "endo_tracker_bridge")


@pytest.mark.parametrize("name", ROOTS)
def test_every_export_resolves_and_all_lists_exactly_the_exports(name):
    root = importlib.import_module(name)
    declared = type_checking_imports(Path(root.__file__).read_text(encoding="utf-8"))
    assert sorted(root.__all__) == sorted(declared)
    for export, target in declared.items():
        module_name, attribute = target.split(":")
        value = getattr(root, export)
        source = importlib.import_module(module_name)
        expected = getattr(source, attribute)
        assert value is expected, f"{name}.{export} is not {target}"
        assert export in dir(root)
    with pytest.raises(AttributeError, match="no attribute 'not_exported'"):
        _ = root.not_exported


def test_the_documented_imports_work():
    import endo_calib.calibration
    import endo_calib.fit
    from endo_calib import PhotometricCalibration, fit_gray_card

    assert PhotometricCalibration is endo_calib.calibration.PhotometricCalibration
    assert fit_gray_card is endo_calib.fit.fit_gray_card


def test_importing_the_roots_loads_no_ros_and_no_heavy_library():
    """A ROS-free user of one module pays for that module only."""
    code = (
        "import sys\n"
        f"import {', '.join(ROOTS)}\n"
        "heavy = ('rclpy', 'cv2', 'scipy', 'numba', 'numpy', 'matplotlib')\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & set(heavy)))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.strip() == "[]", result.stdout


def test_a_ros_free_module_does_not_load_rclpy():
    code = "import sys\nimport endo_io.camera, endo_calib.fit\nprint('rclpy' in sys.modules)\n"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.strip() == "False"


def test_the_voxel_map_loads_no_ros_message_package():
    """An algorithm module: it writes the map's point records without sensor_msgs."""
    code = ("import sys\nimport endo_flow.voxel_map\n"
            "print(sorted(m for m in ('rclpy', 'sensor_msgs') if m in sys.modules))\n")
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert result.stdout.strip() == "[]", result.stdout
