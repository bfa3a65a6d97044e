"""The correction node's parameters in endo-process: its whole table, and mask_extrapolated."""

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
from endo_io.image import image_to_array
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
    path.write_text("photometric_correction:\n  ros__parameters: {no_such_name: 1}\n")
    with pytest.raises(ParameterFileError, match="no_such_name"):
        load_settings(path)


def test_mask_extrapolated_is_the_calibrations_own(calibrations: tuple[Path, Path]) -> None:
    calibration = PhotometricCalibration.load(calibrations[0])
    with BagReader(PHANTOM) as reader:
        image = deserialize(next(reader.messages([topics.IMAGE_RAW])))
        info = deserialize(next(reader.messages([topics.CAMERA_INFO])))
    raw = image_to_array(image)
    frame = RawFrame(0, 0, "optical", raw, image.encoding, CameraModel.from_camera_info(info))
    parameters = load_settings(None, solve_scale=0.5).sfs
    invalid = {}
    for mask in (False, True):
        stage = ShadingStage(calibration, "luminance", parameters, mask_extrapolated=mask)
        shaded = stage.process(frame)
        expected = calibration.correct(to_raw_frame(raw, image.encoding), mask_extrapolated=mask)
        assert shaded.irradiance is not None
        np.testing.assert_array_equal(shaded.irradiance, expected)
        invalid[mask] = int(np.isnan(shaded.irradiance).sum())
    # The phantom's highlights reach 255, above what the gray card showed unsaturated.
    assert invalid[True] > invalid[False]
