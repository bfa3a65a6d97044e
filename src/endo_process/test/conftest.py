"""Session fixtures: the calibrations endo-demo fits from the sample bags, and a params file."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from endo_bringup.graph import run_offline_calibrations
from endo_process.simulated import write_simulated_parameters

BAGS = Path(__file__).resolve().parents[3] / "bags"
PHANTOM = BAGS / "phantom_colon.mcap"


@pytest.fixture(scope="session")
def calibrations(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(photometric.yaml, handeye.yaml) from endo-calibrate and endo-handeye on the sample bags."""
    out = tmp_path_factory.mktemp("calibrations")
    photometric, handeye = run_offline_calibrations(
        BAGS / "graycard.mcap", BAGS / "handeye.mcap", out, dict(os.environ)
    )
    assert photometric.return_code == 0, photometric.output
    assert handeye.return_code == 0, handeye.output
    return photometric.result, handeye.result


@pytest.fixture(scope="session")
def phantom_params(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The nodes' parameters for the phantom: simulated roughness and registration."""
    return write_simulated_parameters(
        PHANTOM, tmp_path_factory.mktemp("params") / "endo3d.yaml"
    )
