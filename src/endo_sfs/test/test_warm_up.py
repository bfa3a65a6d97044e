"""numba start-up: the kernel cache, --help, and the compile notice.

Kernels are cached outside the source tree, --help never compiles, and a
warm-up that must compile says so first.
"""

import os
import subprocess
import sys
from pathlib import Path

from endo_sfs.warm_up import COMPILE_NOTICE, kernels_cached, warm_up_kernels

BIN = Path(sys.executable).parent
SOURCES = Path(__file__).resolve().parents[1] / "endo_sfs"


def test_kernels_are_cached_under_the_cache_home_even_if_numba_came_first(tmp_path):
    code = (
        "import numba\n"  # numba read its configuration before endo_sfs set the folder
        "from endo_sfs import kernels\n"
        "print(numba.config.CACHE_DIR)\n"
        "print(kernels.near_light_sweep._cache._cache_path)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    result = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    config_dir, kernel_dir = result.stdout.split()
    assert Path(config_dir) == tmp_path / "endo3d" / "numba"
    assert Path(kernel_dir).parent == tmp_path / "endo3d" / "numba"
    assert SOURCES not in Path(kernel_dir).parents


def test_help_lists_parameters_without_compiling(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    result = subprocess.run(
        [str(BIN / "endo-sfs"), "--help"], env=env, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "solve_scale" in result.stdout and "compiling" not in result.stdout + result.stderr
    assert list(tmp_path.rglob("*.nbi")) == [] and list(tmp_path.rglob("*.nbc")) == []


def test_a_warm_up_that_must_compile_says_so_first(monkeypatch, tmp_path):
    # An empty cache folder for the stamp; the kernels of this process were
    # decorated already and load from where they are (no compile of minutes here).
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not kernels_cached()
    said: list[str] = []
    warm_up_kernels(announce=said.append)
    assert said == [COMPILE_NOTICE.format(folder=tmp_path)]
    assert kernels_cached()
    # another checkout's stamp in the shared folder is its own, not this tree's
    (ours,) = tmp_path.glob("endo_sfs.kernels.*")
    (tmp_path / "endo_sfs.kernels.0123456789abcdef").write_text("kernels of other sources\n")
    assert kernels_cached()
    ours.write_text("kernels of other sources\n")  # this tree's sources changed
    assert not kernels_cached()
