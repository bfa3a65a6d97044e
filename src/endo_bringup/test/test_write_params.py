"""endo-launch --write-params never replaces a file unless asked."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from endo_bringup.launcher import main


def test_write_params_refuses_an_existing_file_without_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "handeye.yaml"  # the user's file, misnamed on the command line
    path.write_text("T_camera_marker: [1, 2, 3]\n")
    assert main(["--write-params", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path} exists; --overwrite replaces it" in err[0], err
    assert path.read_text() == "T_camera_marker: [1, 2, 3]\n"
    assert main(["--write-params", str(path), "--overwrite"]) == 0
    written = yaml.safe_load(path.read_text())
    assert {"/**/sfs", "/**/flow"} <= set(written)  # every node's section
    fresh = tmp_path / "new.yaml"
    assert main(["--write-params", str(fresh)]) == 0 and fresh.exists()
