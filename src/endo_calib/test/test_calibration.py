import numpy as np
import pytest
import yaml

from endo_calib.calibration import PhotometricCalibration
from endo_calib.errors import CalibrationFileError, CalibrationMismatchError
from endo_calib.synthetic import synthetic_calibration


def _calibration(width=64, height=48, bits=8, colour=False, source="pixels"):
    return synthetic_calibration(
        width,
        height,
        bits=bits,
        colour=colour,
        gamma=2.0,
        gamma_step=0.2,
        light_model_degree=6,
        light_source=source,
    )


def test_correct_is_lut_over_light_map_with_nan_for_saturation_and_outside():
    cal = _calibration()
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    out = cal.correct(raw)
    assert out.dtype == np.float32 and out.shape == (48, 64)
    light = cal.light_map
    expected = cal.inverse_response[raw] / np.where(light > 0, light, np.nan)
    expected[raw == 255] = np.nan
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    assert np.isnan(out[raw == 255]).all()
    assert np.isnan(out[~cal.fov_mask]).all()


def test_correct_colour_and_luminance():
    cal = _calibration(colour=True)
    raw = np.full((48, 64, 3), 128, np.uint8)
    raw[..., 2] = 64
    out = cal.correct(raw)
    assert out.shape == (48, 64, 3)
    lut = cal.inverse_response
    light = cal.light_map
    c = (24, 32)
    np.testing.assert_allclose(
        out[c],
        [lut[128, 0] / light[c][0], lut[128, 1] / light[c][1], lut[64, 2] / light[c][2]],
        rtol=1e-6,
    )
    lum = cal.luminance(out)
    np.testing.assert_allclose(
        lum[c], 0.2126 * out[c][0] + 0.7152 * out[c][1] + 0.0722 * out[c][2], rtol=1e-6
    )


def test_twelve_bit_values_above_the_bit_depth_are_nan():
    cal = _calibration(bits=12)
    raw = np.full((48, 64), 2000, np.uint16)
    raw[0, 0] = 5000
    raw[24, 32] = 4095  # saturated
    out = cal.correct(raw)
    assert np.isnan(out[0, 0]) and np.isnan(out[24, 32])
    assert out[24, 31] == pytest.approx(
        cal.inverse_response[2000] / cal.light_map[24, 31], rel=1e-6
    )
    with pytest.raises(CalibrationMismatchError):
        cal.correct(raw.astype(np.uint8))


def test_binned_frames_use_the_area_mean_of_the_light_map():
    cal = _calibration()
    raw = np.full((24, 32), 100, np.uint8)
    out = cal.correct(raw)
    light = np.where(cal.fov_mask, cal.light_map, np.nan).reshape(24, 2, 32, 2).mean(axis=(1, 3))
    inside = np.isfinite(light)
    np.testing.assert_allclose(out[inside], cal.inverse_response[100] / light[inside], rtol=1e-5)
    with pytest.raises(CalibrationMismatchError, match="aspect ratio"):
        cal.correct(np.zeros((48, 48), np.uint8))
    with pytest.raises(CalibrationMismatchError):
        cal.correct(np.zeros((48, 64, 3), np.uint8))


def test_a_stream_of_other_channels_than_the_calibration_says_how_to_calibrate_it():
    # A colour camera's stream against a mono calibration was refused with its shape only;
    # the user's way out is a calibration from that camera's own colour gray-card images.
    with pytest.raises(CalibrationMismatchError) as mono_calibration:
        _calibration().correct(np.zeros((48, 64, 3), np.uint8))
    assert str(mono_calibration.value) == (
        "frame of shape (48, 64, 3) does not fit a mono calibration; the stream is colour and"
        " the calibration mono: fit one on this camera's colour gray-card images"
        " (endo-calibrate keeps their red, green and blue)"
    )
    with pytest.raises(CalibrationMismatchError, match="the stream is mono and the calibration"
                       " colour: fit one on this camera's mono gray-card images"):  # fmt: skip
        _calibration(colour=True).correct(np.zeros((48, 64), np.uint8))
    four_channels = r"\(48, 64, 4\) does not fit a red/green/blue calibration$"
    with pytest.raises(CalibrationMismatchError, match=four_channels):
        _calibration(colour=True).correct(np.zeros((48, 64, 4), np.uint8))


@pytest.mark.parametrize("colour", [False, True])
def test_save_load_round_trip(tmp_path, colour):
    cal = _calibration(colour=colour, source="model")
    path = cal.save(tmp_path / "photometric.yaml")
    assert (tmp_path / "photometric.light_map.png").is_file()
    document = yaml.safe_load(path.read_text())
    assert (
        document["bit_depth"] == 8
        and len(document["inverse_response"][cal.channel_names[0]]) == 256
    )
    back = PhotometricCalibration.load(path)
    assert back.channel_names == cal.channel_names and back.light_source == "model"
    np.testing.assert_allclose(back.inverse_response, cal.inverse_response, atol=1e-7)
    np.testing.assert_array_equal(back.fov_mask, cal.fov_mask)
    for a, b in zip(back.channels, cal.channels, strict=True):
        np.testing.assert_allclose(a.light_pixels, b.light_pixels, atol=1.0 / 65535)
        np.testing.assert_allclose(
            a.light_model.coefficients, b.light_model.coefficients, rtol=1e-9
        )
    raw = np.full((48, 64, 3) if colour else (48, 64), 77, np.uint8)
    np.testing.assert_allclose(back.correct(raw), cal.correct(raw), rtol=1e-6)


def test_missing_and_corrupt_files_are_named_errors(tmp_path):
    with pytest.raises(CalibrationFileError, match="not found"):
        PhotometricCalibration.load(tmp_path / "nope.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("format: [unclosed\n  - : :")
    with pytest.raises(CalibrationFileError, match="not valid YAML"):
        PhotometricCalibration.load(broken)
    path = _calibration().save(tmp_path / "cal.yaml")
    good = path.read_text()
    path.write_text(good.replace("bit_depth: 8", "bit_depth: 12"))
    with pytest.raises(CalibrationFileError, match="corrupt"):
        PhotometricCalibration.load(path)
    document = yaml.safe_load(good)
    document["inverse_response"]["mono"][100] = 2.0  # no longer monotone
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(CalibrationFileError, match="monotone"):
        PhotometricCalibration.load(path)
    path.write_text(good)
    (tmp_path / "cal.light_map.png").unlink()
    with pytest.raises(CalibrationFileError, match="light map"):
        PhotometricCalibration.load(path)
    other = tmp_path / "other.yaml"
    other.write_text("image_width: 640\n")
    with pytest.raises(CalibrationFileError, match="not an endo3d"):
        PhotometricCalibration.load(other)


def test_a_zero_light_model_is_refused_at_load_with_one_line(tmp_path):
    # issue 16: a zero light model was accepted; every output was NaN, counted "processed"
    path = _calibration(source="model").save(tmp_path / "cal.yaml")
    document = yaml.safe_load(path.read_text())
    coefficients = document["light_map"]["model"]["coefficients"]["mono"]
    document["light_map"]["model"]["coefficients"]["mono"] = [0.0] * len(coefficients)
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(CalibrationFileError, match="all coefficients 0") as refused:
        PhotometricCalibration.load(path)
    assert "\n" not in str(refused.value) and "cal.yaml" in str(refused.value)
    # a negated model (positive nowhere) is refused the same way
    document["light_map"]["model"]["coefficients"]["mono"] = [-c for c in coefficients]
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(CalibrationFileError, match="positive on 0 %"):
        PhotometricCalibration.load(path)
