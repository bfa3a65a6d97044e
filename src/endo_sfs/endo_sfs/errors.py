"""Named errors of shape from shading: what about an input frame was unusable."""

from __future__ import annotations

from endo_io.errors import Endo3dError


class SfsError(Endo3dError):
    """Base class of every endo_sfs error on bad input."""


class SfsInputError(SfsError, ValueError):
    """An irradiance image, mask or warm start has the wrong shape, dtype or values."""


class CameraMismatchError(SfsInputError):
    """The camera model's image size differs from the irradiance image's size."""


class InvalidOptionError(SfsInputError):
    """A solver setting (:class:`endo_sfs.SfsOptions`) is out of its range."""


class NoValidPixelsError(SfsInputError):
    """No pixel is usable: the frame is all dark, all saturated, NaN or masked."""


class NoCommonPixelsError(SfsInputError):
    """Scoring: no pixel has both an estimate and a ground-truth depth."""


class IrradianceRangeError(SfsInputError):
    """A frame holds irradiance above ``max_irradiance``: it cannot be linear irradiance."""


class SolutionRangeError(SfsError):
    """The solve gave depth that is not a finite positive number (an overflow)."""


class UnknownModelError(SfsError, ValueError):
    """The requested reflectance or camera model is not one endo_sfs implements."""
