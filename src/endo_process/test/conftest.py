"""Session fixtures: the calibrations endo-demo fits from the sample bags, and a params file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from endo_process.runner import ProcessOptions, process_bag
from endo_process.simulated import write_simulated_parameters

BAGS = Path(__file__).resolve().parents[3] / "bags"
PHANTOM = BAGS / "phantom_colon.mcap"


@pytest.fixture(scope="session")
def calibrations(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(photometric.yaml, handeye.yaml) from endo-calibrate and endo-handeye on the sample bags."""
    out = tmp_path_factory.mktemp("calibrations")
    photometric, handeye = out / "photometric.yaml", out / "handeye.yaml"
    bin_dir = Path(sys.executable).parent
    # The commands docs/process.md gives, with the sample bags' card distance and board.
    for argv in (
        [bin_dir / "endo-calibrate", "--bag", BAGS / "graycard.mcap", "--card-distance", "0.0265",
         "-o", photometric],
        [bin_dir / "endo-handeye", BAGS / "handeye.mcap", "-o", handeye, "--board", "8x5",
         "--square-mm", "4", "--pose-unit", "m"],
    ):
        done = subprocess.run([str(a) for a in argv], capture_output=True, text=True, check=False,
                              timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
    return photometric, handeye


@pytest.fixture(scope="session")
def phantom_params(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The nodes' parameters for the phantom: simulated roughness and registration."""
    return write_simulated_parameters(
        PHANTOM, tmp_path_factory.mktemp("params") / "endo3d.yaml"
    )


def process_first_frames(
    output: Path, calibrations: tuple[Path, Path], params: Path, frames: int
) -> Path:
    """endo-process on the phantom's first ``frames`` frames, --jobs 1 at solve_scale 0.5."""
    report = process_bag(ProcessOptions(
        bag=PHANTOM, output=output, calibration=calibrations[0], handeye=calibrations[1],
        params=params, solve_scale=0.5, jobs=1, max_frames=frames, progress=False,
    ))  # fmt: skip
    assert report.frames_shaded == frames
    return output
