"""Named errors of the photometric calibration.

Each class names one cause, so that a caller (the CLI, the correction node's
``InputHealth``) can tell what went wrong from the class alone; the message is
one line that says which file, level or image was at fault.
"""

from __future__ import annotations

from endo_io.errors import Endo3dError


class CalibrationError(Endo3dError):
    """Base class of every endo_calib error."""


class InsufficientLevelsError(CalibrationError, ValueError):
    """Fewer than two usable gray levels, or a level without any frame."""


class SaturatedCardError(CalibrationError, ValueError):
    """A gray level is saturated (or black) over most of the field of view."""


class ImageSizeMismatchError(CalibrationError, ValueError):
    """Gray-card frames differ in size, channels or dtype from each other or the camera."""


class FitError(CalibrationError, RuntimeError):
    """The joint fit of response and light map has no usable data or diverged."""


class CalibrationFileError(CalibrationError, OSError):
    """A calibration file is missing, unreadable, or its content is corrupt."""


class CalibrationMismatchError(CalibrationError, ValueError):
    """An image does not match the calibration (size, aspect ratio, bit depth, channels)."""


class ManifestError(CalibrationError, ValueError):
    """A gray-card manifest YAML is missing, malformed, or names unreadable images."""


class DsoFormatError(CalibrationError, ValueError):
    """A TUM/DSO ``pcalib.txt`` or ``vignette.png`` is missing or malformed."""
