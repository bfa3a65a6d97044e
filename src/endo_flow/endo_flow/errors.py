"""Named errors of endo_flow: why one frame could not be used."""

from __future__ import annotations

from endo_io.errors import Endo3dError


class FlowError(Endo3dError):
    """Base class of every endo_flow error on bad input."""


class FlowInputError(FlowError, ValueError):
    """A frame's arrays have the wrong shape or dtype, or disagree with the camera."""


class NoFeaturesError(FlowError):
    """No trackable feature in the frame (textureless, black or all saturated)."""


class MapExportError(FlowError):
    """The voxel map cannot be written (empty map, unwritable path)."""
