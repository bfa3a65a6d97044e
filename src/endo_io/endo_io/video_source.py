"""Frames from a V4L2 device or a video file through OpenCV, ROS-free.

:class:`VideoSource` opens ``/dev/videoN``, a device number or a video file
(anything OpenCV's FFmpeg backend decodes), says at once when it cannot
(:class:`VideoSourceError`, one line naming the device or file), and gives
frames as numpy arrays in the encoding asked for: ``mono8`` (H, W) uint8 or
``rgb8`` / ``bgr8`` (H, W, 3) uint8. A file can be rewound (``--loop``). The
node around it is :mod:`endo_io.camera_node`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from endo_io.errors import Endo3dError

#: Encodings a source can give, and OpenCV's conversion from its BGR frames.
ENCODINGS: dict[str, int | None] = {
    "rgb8": cv2.COLOR_BGR2RGB,
    "bgr8": None,
    "mono8": cv2.COLOR_BGR2GRAY,
}
_DEVICE = re.compile(r"(?:/dev/video)?(\d+)")


class VideoSourceError(Endo3dError):
    """A video device or file that cannot be opened or read."""


@dataclass(frozen=True)
class SourceInfo:
    """What a source is: a device or a file, its frame size and its frame rate (Hz, 0 unknown)."""

    name: str
    is_file: bool
    width: int
    height: int
    fps: float


class VideoSource:
    """An opened device or file.

    Args:
        spec: ``/dev/videoN``, ``N`` or a file path.
        encoding: one of :data:`ENCODINGS`.

    Raises:
        VideoSourceError: no such device or file, or nothing decodable in it.
    """

    def __init__(self, spec: str, *, encoding: str = "rgb8") -> None:
        if encoding not in ENCODINGS:
            raise VideoSourceError(f"encoding {encoding!r} is not one of {', '.join(ENCODINGS)}")
        self._conversion = ENCODINGS[encoding]
        device = _DEVICE.fullmatch(spec)
        if device is not None and not Path(spec).is_file():
            path = f"/dev/video{device.group(1)}"
            if not Path(path).exists():
                raise VideoSourceError(f"no video device {path}")
            capture = cv2.VideoCapture(int(device.group(1)), cv2.CAP_V4L2)
            if not capture.isOpened():
                raise VideoSourceError(f"cannot open video device {path} (busy, or not a camera)")
            name, is_file = path, False
        else:
            if not Path(spec).is_file():
                raise VideoSourceError(f"no video file {spec}")
            # FFmpeg's own complaint about a bad file would come before our one line.
            os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
            capture = cv2.VideoCapture(spec)
            if not capture.isOpened():
                raise VideoSourceError(f"cannot decode video file {spec}")
            name, is_file = spec, True
        self._capture = capture
        first = self._read_raw()
        if first is None:
            capture.release()
            raise VideoSourceError(f"no frame could be read from {name}")
        self._pending: np.ndarray | None = first
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        self.info = SourceInfo(
            name=name,
            is_file=is_file,
            width=int(first.shape[1]),
            height=int(first.shape[0]),
            fps=fps if math.isfinite(fps) and 0.0 < fps < 10_000.0 else 0.0,
        )

    def _read_raw(self) -> np.ndarray | None:
        ok, frame = self._capture.read()
        return frame if ok and frame is not None else None

    def read(self) -> np.ndarray | None:
        """The next frame, converted; None at the end of a file (or a device that stopped)."""
        frame, self._pending = (self._pending, None) if self._pending is not None else (
            self._read_raw(), None
        )
        if frame is None:
            return None
        if frame.ndim == 2:  # a grey source
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        return frame if self._conversion is None else cv2.cvtColor(frame, self._conversion)

    def rewind(self) -> bool:
        """Go back to a file's first frame; False for a device or when seeking fails."""
        if not self.info.is_file:
            return False
        return bool(self._capture.set(cv2.CAP_PROP_POS_FRAMES, 0))

    def close(self) -> None:
        """Release the device or file."""
        self._capture.release()
