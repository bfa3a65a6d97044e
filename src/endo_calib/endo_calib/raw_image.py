"""Raw frames as the calibration expects them, from ROS image encodings.

The calibration works on (H, W) mono or (H, W, 3) RGB-ordered integer frames.
Camera drivers publish mono8/mono16/16UC1 or rgb8/bgr8/rgba8/bgra8; this
turns an array decoded by ``endo_io.image.image_to_array`` into that layout.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from endo_calib.errors import CalibrationMismatchError

#: Encodings whose raw values the calibration can take.
RAW_ENCODINGS = frozenset({"mono8", "mono16", "16UC1", "rgb8", "bgr8", "rgba8", "bgra8"})


def to_raw_frame(array: NDArray[np.integer], encoding: str) -> NDArray[np.integer]:
    """Reorder a decoded image into the calibration's layout.

    array: (H, W) or (H, W, C) as decoded for ``encoding``.
    Returns (H, W) uint8/uint16 for mono encodings, (H, W, 3) RGB uint8 for
    colour ones (a view where possible). Raises CalibrationMismatchError for
    encodings without raw values (e.g. 32FC1).
    """
    if encoding not in RAW_ENCODINGS:
        raise CalibrationMismatchError(
            f"encoding {encoding!r} carries no raw camera values; "
            f"expected one of {sorted(RAW_ENCODINGS)}"
        )
    if encoding in ("mono8", "mono16", "16UC1"):
        return array
    if encoding == "rgb8":
        return array
    if encoding == "rgba8":
        return array[:, :, :3]
    # bgr8 / bgra8: reverse the first three channels.
    return array[:, :, 2::-1]
