"""handeye.yaml: what is saved is what is loaded, and bad files are refused."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from endo_io.pose import rigid_transform
from endo_tracker_bridge.errors import HandEyeFileError
from endo_tracker_bridge.handeye_file import HandEyeCalibration


def test_round_trip(tmp_path):
    T = rigid_transform([0.1, -2.0, 0.5], [0.012, -0.003, 0.151])
    calibration = HandEyeCalibration(
        T_marker_camera=T,
        time_offset_ns=-21_437_000,
        residuals={"reprojection_rms_px": 0.31, "translation_rms_mm": 0.4, "rotation_rms_deg": 0.1},
        method="park + least-squares",
        date="2026-11-22T10:00:00+00:00",
        views_used=80,
        views_total=84,
        T_tracker_target=np.eye(4),
        details={"closed_form": {"tsai": {"translation_rms_mm": np.float64(0.9)}}},
    )
    path = tmp_path / "handeye.yaml"
    calibration.save(path)
    document = yaml.safe_load(path.read_text())
    assert document["time_offset_s"] == pytest.approx(-0.021437)
    assert "tracker_stamp = camera_time + time_offset_s" in document["time_offset_convention"]
    loaded = HandEyeCalibration.load(path)
    np.testing.assert_allclose(loaded.T_marker_camera, T, atol=1e-15)
    assert loaded.time_offset_ns == -21_437_000
    assert loaded.residuals == calibration.residuals
    assert (loaded.views_used, loaded.views_total, loaded.method) == (80, 84, calibration.method)
    assert loaded.details["closed_form"]["tsai"]["translation_rms_mm"] == 0.9


def test_bad_files_are_refused(tmp_path):
    path = tmp_path / "handeye.yaml"
    with pytest.raises(HandEyeFileError, match="cannot read"):
        HandEyeCalibration.load(path)
    path.write_text("time_offset_s: 0.1\n")
    with pytest.raises(HandEyeFileError, match="no T_marker_camera"):
        HandEyeCalibration.load(path)
    path.write_text("T_marker_camera: [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n")
    with pytest.raises(HandEyeFileError, match="orthonormal"):
        HandEyeCalibration.load(path)
    path.write_text("T_marker_camera: [1, 2, 3]\n")
    with pytest.raises(HandEyeFileError, match="4x4"):
        HandEyeCalibration.load(path)
    eye = "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]"
    path.write_text(f"T_marker_camera: {eye}\ntime_offset_s: .nan\n")
    with pytest.raises(HandEyeFileError, match="finite"):
        HandEyeCalibration.load(path)
