"""The correction node's parameters in endo-process: mask_extrapolated, output_encoding, all."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from endo_calib.calibration import PhotometricCalibration
from endo_calib.node import PARAMETERS as CORRECTION_PARAMETERS
from endo_calib.raw_image import to_raw_frame
from endo_io import topics
from endo_io.bag import BagReader, deserialize
from endo_io.camera import CameraModel
from endo_io.image import decode_irradiance, encode_irradiance, image_to_array
from endo_process.errors import ParameterFileError
from endo_process.settings import load_settings
from endo_process.shading import RawFrame, ShadingStage

from .conftest import PHANTOM


def test_every_parameter_of_the_correction_node_is_accepted(tmp_path: Path) -> None:
    # A launch's parameter file carries the node's whole table (health settings too).
    names = {spec.name for spec in CORRECTION_PARAMETERS}
    assert {"channel", "mask_extrapolated", "calibration_file"} <= names
    path = tmp_path / "params.yaml"
    path.write_text(
        "photometric_correction:\n  ros__parameters:\n"
        "    mask_extrapolated: true\n    channel: luminance\n"
        + "".join(
            f"    {spec.name}: {spec.default!r}\n"
            for spec in CORRECTION_PARAMETERS
            if spec.name not in ("mask_extrapolated", "channel", "calibration_file")
            and isinstance(spec.default, int | float) and not isinstance(spec.default, bool)
        )
    )  # fmt: skip
    settings = load_settings(path)
    assert settings.mask_extrapolated is True and settings.channel == "luminance"
    assert load_settings(None).mask_extrapolated is False  # the node's default
    assert load_settings(None).output_encoding == "16UC1"
    path.write_text("photometric_correction:\n  ros__parameters: {output_encoding: 32FC1}\n")
    assert load_settings(path).output_encoding == "32FC1"
    path.write_text("photometric_correction:\n  ros__parameters: {no_such_name: 1}\n")
    with pytest.raises(ParameterFileError, match="no_such_name"):
        load_settings(path)


def test_sections_apply_as_rcl_applies_them_and_a_section_for_no_node_is_named(
    tmp_path: Path,
) -> None:
    # `sfss:` (a misspelt node) and `/rig1/sfs:` (a namespaced launch's) were ignored
    # without a word: the run went on with the defaults
    path = tmp_path / "params.yaml"
    path.write_text("/**:\n  ros__parameters: {roughness: 0.2, max_tracks: 300}\n"
                    "/sfs:\n  ros__parameters: {solve_scale: 0.5}\n"
                    "/*/sfs:\n  ros__parameters: {solve_scale: 0.25}\n"
                    "v4l2_camera:\n  ros__parameters: {video_device: /dev/video0}\n")  # fmt: skip
    settings = load_settings(path)
    assert settings.sfs["roughness"] == 0.2 and settings.flow["max_tracks"] == 300
    assert settings.sfs["solve_scale"] == 0.5  # /*/sfs is a namespaced node's
    assert settings.ignored_sections == ("/*/sfs", "v4l2_camera")
    path.write_text("sfss:\n  ros__parameters: {solve_scale: 0.5}\n")
    with pytest.raises(ParameterFileError, match=r"section sfss .* \(did you mean sfs\?\)$"):
        load_settings(path)
    # a typo in a section for every node is refused as the live node refuses it
    path.write_text("/**:\n  ros__parameters: {solve_scal: 0.5}\n")
    with pytest.raises(ParameterFileError,
                       match=r"no parameter 'solve_scal' \(did you mean solve_scale\?\)$"):
        load_settings(path)


def _phantom_frame() -> tuple[np.ndarray, RawFrame]:
    with BagReader(PHANTOM) as reader:
        image = deserialize(next(reader.messages([topics.IMAGE_RAW])))
        info = deserialize(next(reader.messages([topics.CAMERA_INFO])))
    raw = image_to_array(image)
    return raw, RawFrame(0, 0, "optical", raw, image.encoding, CameraModel.from_camera_info(info))


def test_the_corrected_image_is_solved_as_the_live_nodes_receive_it(
    calibrations: tuple[Path, Path],
) -> None:
    """16UC1 (default): SFS and the output get the fixed point's values; 32FC1: the floats."""
    calibration = PhotometricCalibration.load(calibrations[0])
    raw, frame = _phantom_frame()
    parameters = load_settings(None, solve_scale=0.5).sfs
    expected = calibration.correct(to_raw_frame(raw, frame.encoding))
    shaded = {}
    for encoding in ("16UC1", "32FC1"):
        stage = ShadingStage(calibration, "luminance", parameters, output_encoding=encoding)
        shaded[encoding] = stage.process(frame)
        assert shaded[encoding].encoding == encoding and shaded[encoding].saturated == 0
    fixed = shaded["16UC1"].irradiance
    assert fixed is not None
    np.testing.assert_array_equal(
        fixed, decode_irradiance(encode_irradiance(expected).pixels, "16UC1"))
    np.testing.assert_array_equal(shaded["32FC1"].irradiance, expected)
    # the same pixels solved, and the depth moves by a few 1e-5 (median 1.7e-5 measured on
    # this frame at solve_scale 0.5; p99 1.7e-4)
    a, b = shaded["16UC1"].depth_relative, shaded["32FC1"].depth_relative
    assert a is not None and b is not None
    both = np.isfinite(a) & np.isfinite(b)
    assert np.array_equal(np.isfinite(a), np.isfinite(b))
    assert float(np.median(np.abs(a[both] / b[both] - 1.0))) < 2e-4


def test_mask_extrapolated_is_the_calibrations_own(calibrations: tuple[Path, Path]) -> None:
    calibration = PhotometricCalibration.load(calibrations[0])
    raw, frame = _phantom_frame()
    image_encoding = frame.encoding
    parameters = load_settings(None, solve_scale=0.5).sfs
    invalid = {}
    for mask in (False, True):
        stage = ShadingStage(calibration, "luminance", parameters, mask_extrapolated=mask,
                             output_encoding="32FC1")  # fmt: skip
        shaded = stage.process(frame)
        expected = calibration.correct(to_raw_frame(raw, image_encoding), mask_extrapolated=mask)
        assert shaded.irradiance is not None
        np.testing.assert_array_equal(shaded.irradiance, expected)
        invalid[mask] = int(np.isnan(shaded.irradiance).sum())
    # The phantom's highlights reach 255, above what the gray card showed unsaturated.
    assert invalid[True] > invalid[False]
