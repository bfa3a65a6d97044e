"""Named errors of the endoscope simulator.

Every error derives from :class:`endo_io.errors.Endo3dError`, so a node or a
CLI can report the one-line cause and carry on (or exit) the same way as the
rest of endo3d.
"""

from __future__ import annotations

from endo_io.errors import Endo3dError


class SimulatorError(Endo3dError):
    """Base class of every error raised by ``endo_sim``."""


class SimulationParameterError(SimulatorError, ValueError):
    """A simulation parameter is out of its physical or supported range."""


class UnknownSceneError(SimulationParameterError):
    """A scene name is not one of the scenes the simulator knows."""


class GroundTruthError(SimulatorError):
    """A bag's ground-truth file is missing or unreadable."""
