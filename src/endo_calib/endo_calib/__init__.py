"""Gray-card photometric calibration (camera response, light map) and the correction node.

>>> report = fit_gray_card(levels, camera)  # levels: GrayLevel or a GrayCardAccumulator
>>> calibration = PhotometricCalibration.from_fit(report)
>>> calibration.save("photometric.yaml")
>>> irradiance = PhotometricCalibration.load("photometric.yaml").correct(raw)

Names are imported on first use, so ``import endo_calib`` loads nothing else.
"""

from typing import TYPE_CHECKING

from endo_io.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from endo_calib.calibration import (
        OUTPUT_CHANNELS,
        ChannelCalibration,
        PhotometricCalibration,
        select_channel,
    )
    from endo_calib.dso import export_dso, import_dso
    from endo_calib.errors import (
        CalibrationError,
        CalibrationFileError,
        CalibrationMismatchError,
        FitError,
    )
    from endo_calib.fit import ChannelFit, FitReport, fit_gray_card
    from endo_calib.geometry import CardPose, geometry_term
    from endo_calib.gray_levels import GrayCardAccumulator, GrayLevel
    from endo_calib.light_map import LightModel
    from endo_calib.node import PhotometricCorrectionNode
    from endo_calib.raw_image import to_raw_frame
    from endo_calib.report import write_report
    from endo_calib.response import InverseResponse

__all__ = [
    "OUTPUT_CHANNELS",
    "CalibrationError",
    "CalibrationFileError",
    "CalibrationMismatchError",
    "CardPose",
    "ChannelCalibration",
    "ChannelFit",
    "FitError",
    "FitReport",
    "GrayCardAccumulator",
    "GrayLevel",
    "InverseResponse",
    "LightModel",
    "PhotometricCalibration",
    "PhotometricCorrectionNode",
    "export_dso",
    "fit_gray_card",
    "geometry_term",
    "import_dso",
    "select_channel",
    "to_raw_frame",
    "write_report",
]
__getattr__, __dir__ = lazy_exports(__name__)
