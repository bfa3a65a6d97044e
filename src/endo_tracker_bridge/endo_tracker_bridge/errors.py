"""Named errors of the tracker bridge.

Every rejected tracker sample raises one of the :class:`TrackerSampleError`
subclasses; the node counts them by class name on ``/diagnostics``. Problems
with a whole source (a malformed log file, an unknown option) and with the
hand–eye calibration have their own branches so that a caller can tell what
went wrong from the class alone. The three rejections of a bad pose value
are also :class:`endo_io.errors.PoseError` subclasses: the bridge's checks are
endo_io's (:mod:`endo_io.pose`), re-raised under the bridge's names.
"""

from __future__ import annotations

from endo_io.errors import Endo3dError, PoseError


class TrackerSampleError(Endo3dError, ValueError):
    """One tracker sample was rejected; the stream goes on."""


class NonFinitePoseError(TrackerSampleError, PoseError):
    """A pose holds NaN or infinity."""


class NonUnitQuaternionError(TrackerSampleError, PoseError):
    """A quaternion's norm differs from 1 by more than the tolerance."""


class NonOrthonormalRotationError(TrackerSampleError, PoseError):
    """A rotation matrix is not orthonormal with determinant +1 within the tolerance."""


class ToolNotVisibleError(TrackerSampleError):
    """The tracker reports the tool missing, occluded or disabled."""


class TimeWentBackwardsError(TrackerSampleError):
    """A sample's stamp is not after the previous accepted stamp of its tool.

    With the default gate only a repeat of the newest stamp: a step back is
    a restart of the tool's stream (a clock jump), not a rejected sample.
    """


class SpeedLimitError(TrackerSampleError):
    """A sample moved faster than the configured linear or angular speed limit."""


class UnexpectedFrameError(TrackerSampleError):
    """A pose arrived in another frame than the one the bridge was told to expect."""


class StampCorrectionError(TrackerSampleError):
    """Correcting a stamp by the calibrated time offset gives a negative time."""


class IgtlMessageError(TrackerSampleError):
    """An OpenIGTLink message is not a usable TRANSFORM of the configured device."""


class NdiFrameError(TrackerSampleError):
    """A frame from scikit-surgerynditracker does not have the documented layout."""


class TrackerSourceError(Endo3dError):
    """A tracker source cannot be set up or read (bad option, unreadable log)."""


class TrackerLogError(TrackerSourceError):
    """A tracker log file (CSV/TSV) is malformed."""


class HandEyeError(Endo3dError):
    """A hand–eye calibration cannot be computed from the given data."""


class HandEyeFileError(HandEyeError):
    """A handeye.yaml file is missing fields or holds inconsistent values."""
