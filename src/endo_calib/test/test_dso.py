import cv2
import numpy as np
import pytest

from endo_calib.calibration import PhotometricCalibration
from endo_calib.dso import export_dso, import_dso, read_pcalib
from endo_calib.errors import DsoFormatError


def test_dso_files_follow_the_tum_conventions(gamma_fit, tmp_path):
    cal, _, _ = gamma_fit
    pcalib, vignette = export_dso(cal, tmp_path)
    lines = pcalib.read_text().splitlines()
    values = np.array([float(x) for x in lines[0].split()])
    assert len(lines) == 1 and values.size == 256
    assert np.all(np.diff(values) > 0)  # DSO rejects anything not strictly increasing
    assert values[0] == pytest.approx(0.0, abs=1e-3) and values[-1] == pytest.approx(
        255.0, abs=1e-3
    )
    image = cv2.imread(str(vignette), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint16 and image.shape == (cal.height, cal.width)
    assert image.max() == 65535 and image.min() >= 1  # DSO divides by it


def test_dso_round_trip(gamma_fit, tmp_path):
    cal, _, _ = gamma_fit
    export_dso(cal, tmp_path)
    back = import_dso(tmp_path)
    assert back.channel_names == ("mono",) and back.light_source == "pixels"
    np.testing.assert_allclose(back.inverse_response, cal.inverse_response, atol=2e-6)
    np.testing.assert_array_equal(back.fov_mask, cal.fov_mask)
    inside = cal.fov_mask
    np.testing.assert_allclose(
        back.light_map[inside], cal.light_map[inside] / cal.light_map.max(), atol=2.0 / 65535
    )
    # the imported calibration corrects frames like the original
    frame = np.full((cal.height, cal.width), 120, np.uint8)
    ratio = back.correct(frame)[inside] / cal.correct(frame)[inside]
    np.testing.assert_allclose(ratio, ratio.mean(), rtol=1e-4)
    # and survives our own file format
    again = PhotometricCalibration.load(back.save(tmp_path / "from_dso.yaml"))
    np.testing.assert_allclose(again.inverse_response, back.inverse_response, atol=1e-7)


def test_eight_bit_vignette_and_twelve_bit_response_import(tmp_path):
    h, w = 30, 40
    yy, xx = np.mgrid[:h, :w]
    vignette = np.clip(255 - ((xx - 20) ** 2 + (yy - 15) ** 2) // 4, 0, 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "vignette.png"), vignette)
    g = np.linspace(0, 1, 4096) ** 2 * 4000 + 5
    (tmp_path / "pcalib.txt").write_text(" ".join(map(str, g)) + "\n")
    cal = import_dso(tmp_path)
    assert cal.bit_depth == 12
    assert cal.inverse_response[0] == 0 and cal.inverse_response[-1] == 1
    np.testing.assert_array_equal(cal.fov_mask, vignette > 0)
    assert cal.light_map[15, 20] == 1.0


def test_bad_dso_files_are_named_errors(tmp_path):
    with pytest.raises(DsoFormatError, match="not found"):
        import_dso(tmp_path)
    bad = tmp_path / "pcalib.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(DsoFormatError, match="2\\^bits"):
        read_pcalib(bad)
    bad.write_text(" ".join(["1"] * 256))
    with pytest.raises(DsoFormatError, match="strictly increasing"):
        read_pcalib(bad)
