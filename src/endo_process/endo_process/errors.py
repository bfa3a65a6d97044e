"""Why ``endo-process`` cannot start, or stopped early: one class per cause."""

from __future__ import annotations

from endo_io.errors import Endo3dError


class ProcessInputError(Endo3dError):
    """An input (bag, calibration, parameter file, option) is unusable; nothing was processed."""


class MissingTopicError(ProcessInputError):
    """The bag has no message on a topic the processing needs."""


class MissingCameraInfoError(ProcessInputError):
    """Neither the bag nor ``--camera-info`` gives the camera model."""


class ParameterFileError(ProcessInputError):
    """The ``--params`` file cannot be read or holds a value of the wrong kind."""


class ImageStampBackError(Endo3dError):
    """An image is stamped before an image already read (a clock jump back, frames out of order).

    Not an :class:`endo_io.errors.StampOrderError`: that one is the clock-jump
    guard's verdict on a sample at or *shortly* before its stream's newest (a
    late sample, dropped, while a far step back is a ClockJumpError that resets
    the stream); this one is any step back of the recording's image stamps, far
    or near, found by the frame loop when no camera_info pairs with the image.
    A handler of either would take the other wrongly, so neither derives from
    the other.
    """


class WorkerError(Endo3dError):
    """A shading worker process failed; the message carries its error."""
