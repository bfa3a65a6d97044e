"""Named exception classes shared by every endo3d package.

Nodes catch :class:`Endo3dError` around each message: the message is dropped,
the one-line reason is logged and counted in ``/diagnostics``, and the node
keeps running. Each package derives its own errors from these so that a
caller can tell *what* was wrong from the class alone.
"""

from __future__ import annotations


class Endo3dError(Exception):
    """Base class of every error raised on bad input anywhere in endo3d."""


class MessageConversionError(Endo3dError, ValueError):
    """A ROS message cannot be converted to or from numpy as asked."""


class ImageEncodingError(MessageConversionError):
    """An image encoding is unknown, unsupported, or not the one required."""


class ImageLayoutError(MessageConversionError):
    """An image's step, size or buffer length do not agree."""


class UndecodableMessageError(MessageConversionError):
    """A message's serialized (CDR) bytes do not decode as the topic's type."""


class CameraModelError(MessageConversionError):
    """A CameraInfo or calibration YAML is inconsistent or unsupported."""


class PoseError(MessageConversionError):
    """A pose is not finite or its rotation is not a unit quaternion."""


class PointCloudError(MessageConversionError):
    """A PointCloud2 lacks the expected fields or its layout is inconsistent."""


class BagError(Endo3dError):
    """A bag cannot be opened, read or written."""


class BagCorruptError(BagError):
    """A bag is truncated or damaged; everything before the damage was read."""


class PoseLookupError(Endo3dError):
    """No pose can be given at the asked stamp (see the subclasses for why)."""


class PoseTooOldError(PoseLookupError):
    """The stamp is older than every pose still held: it will never be answered."""


class PoseBeforeStreamError(PoseTooOldError):
    """The stamp is before the first pose of the pose stream (which started or restarted later).

    No pose will come for it. A normal start: the camera's first frame often
    precedes the tracker's first pose, at every start and every loop of a
    replay; a caller reports it as an expected condition, not as an error.
    """


class PoseNotYetError(PoseLookupError):
    """The stamp is newer than the newest pose: the answer may still arrive."""


class PoseGapError(PoseLookupError):
    """The two poses around the stamp are further apart than the allowed gap."""


class PoseOrderError(PoseError):
    """A pose arrived with a stamp at or before the newest one held."""


class ClockJumpError(Endo3dError):
    """Time jumped (a bag loop, a driver restart): state kept over time was reset."""


class StampOrderError(Endo3dError):
    """A stamp is at or shortly before its stream's newest: the sample is out of order."""


class FutureStampError(StampOrderError):
    """A stamp is far ahead of its stream's newest and no later sample confirms a jump yet."""


class OutputExistsError(Endo3dError):
    """A tool's output file exists and the user did not ask to replace it (``--overwrite``)."""


class ParameterValidationError(Endo3dError, ValueError):
    """A node parameter has the wrong type, is out of its range or not one of its choices.

    Raised while a node starts (``endo_io.process.run_node`` turns it into one
    line on stderr and exit code 2) and given as the reason when a run-time
    change is refused.
    """


class RosArgumentsError(Endo3dError):
    """rcl refuses a node's ROS arguments: a parameter file that does not parse, a bad remap."""


def yaml_error_line(error: Exception) -> str:
    """One line naming where and why PyYAML refused a document.

    ``str()`` of a ``yaml.YAMLError`` spans several lines (the context, the
    offending line, a caret); error messages here are one line.

    Args:
        error: a ``yaml.YAMLError`` (a ``MarkedYAMLError`` gives its position);
            any other exception gives the first line of its text.

    Returns:
        e.g. ``line 2, column 1: expected ',' or ']', but got '<stream end>'
        (while parsing a flow sequence)``.
    """
    problem = getattr(error, "problem", None)
    if problem is None:
        lines = str(error).splitlines()
        return lines[0] if lines else type(error).__name__
    mark = getattr(error, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    context = getattr(error, "context", None)
    return f"{where}{problem}" + (f" ({context})" if context else "")
