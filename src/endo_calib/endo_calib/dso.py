"""Import and export of the TUM/DSO photometric calibration format.

DSO (Engel et al., "Direct Sparse Odometry") and the TUM monoVO dataset tools
(mono_dataset_code) describe a camera by two files:

* ``pcalib.txt``: one line of 2^bits (at least 256) whitespace-separated
  numbers, the inverse response G(v) for raw values v = 0..2^bits−1. DSO
  requires it strictly increasing and rescales it to [0, 255] itself
  (``255·(G − G[0])/(G[-1] − G[0])``), so only its shape matters; the TUM
  files use the raw-value scale, G(255) ≈ 255, and so do we on export.
* ``vignette.png``: the attenuation V(x) at the camera resolution, a 16-bit
  (or 8-bit) single-channel PNG that DSO divides by its maximum. V is our
  light map L: light distribution times lens vignetting.

DSO divides by V everywhere, so a vignette may not be 0. On export, pixels
outside the field of view get the value 1 (of 65535); on import, pixels at or
below 1 count (16-bit) or 0 (8-bit) are taken as outside the field of view.
DSO handles one channel; an RGB calibration exports one chosen channel.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from endo_calib.calibration import ChannelCalibration, PhotometricCalibration
from endo_calib.errors import CalibrationError, DsoFormatError
from endo_calib.light_map import fit_light_model
from endo_calib.response import InverseResponse

PCALIB_NAME = "pcalib.txt"
VIGNETTE_NAME = "vignette.png"
#: Vignette value written outside the field of view (DSO divides by it).
OUTSIDE_FOV_VALUE = 1


def export_dso(
    calibration: PhotometricCalibration, directory: str | Path, channel: str | None = None
) -> tuple[Path, Path]:
    """Write ``pcalib.txt`` and ``vignette.png`` of one channel into ``directory``.

    channel: "mono", "red", "green" or "blue"; by default the only channel of a
        mono calibration, or green.
    Returns (pcalib path, vignette path).
    """
    names = calibration.channel_names
    name = channel or ("mono" if names == ("mono",) else "green")
    if name not in names:
        raise DsoFormatError(f"channel {name!r} not in the calibration's channels {names}")
    index = names.index(name)
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    lut = calibration.channels[index].inverse_response.lut
    top = lut.size - 1
    table = lut * top
    # DSO rejects a response that is not strictly increasing: lift flat runs
    # by far less than one raw value's worth of irradiance.
    ramp = np.arange(lut.size) * 1e-6
    table = np.maximum.accumulate(table + ramp)
    pcalib = out / PCALIB_NAME
    pcalib.write_text(" ".join(f"{x:.9g}" for x in table) + "\n", encoding="ascii")
    light = calibration.light_map
    if light.ndim == 3:
        light = light[:, :, index]
    peak = float(light.max())
    if not np.isfinite(peak) or peak <= 0.0:
        raise CalibrationError("calibration has an empty light map")
    vignette = np.clip(np.rint(light / peak * 65535.0), OUTSIDE_FOV_VALUE + 1, 65535).astype(
        np.uint16
    )
    vignette[light <= 0.0] = OUTSIDE_FOV_VALUE
    path = out / VIGNETTE_NAME
    if not cv2.imwrite(str(path), vignette):
        raise DsoFormatError(f"cannot write {path}")
    return pcalib, path


def read_pcalib(path: str | Path) -> InverseResponse:
    """Read a DSO ``pcalib.txt``: the normalised inverse response (g(0)=0, g(max)=1).

    Raises DsoFormatError when the file is missing, its first line is not
    2^bits ≥ 256 numbers, or they do not increase.
    """
    file = Path(path)
    if not file.is_file():
        raise DsoFormatError(f"DSO response file {file} not found")
    try:
        first = file.read_text(encoding="ascii").splitlines()[0]
        values = np.array([float(x) for x in first.split()], dtype=np.float64)
    except (IndexError, ValueError, UnicodeDecodeError) as error:
        raise DsoFormatError(f"{file}: first line is not a list of numbers ({error})") from error
    n = values.size
    if n < 256 or n & (n - 1) or n > 1 << 16:
        raise DsoFormatError(f"{file}: {n} response values, expected 2^bits with 8 <= bits <= 16")
    if not np.all(np.isfinite(values)) or np.any(np.diff(values) <= 0.0):
        raise DsoFormatError(f"{file}: response values are not strictly increasing")
    try:
        return InverseResponse.from_values(values)
    except CalibrationError as error:
        raise DsoFormatError(f"{file}: {error}") from error


def read_vignette(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Read a DSO ``vignette.png``: ((H, W) float64 map with max 1, (H, W) bool field of view)."""
    file = Path(path)
    if not file.is_file():
        raise DsoFormatError(f"DSO vignette {file} not found")
    image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DsoFormatError(f"{file} is not a readable image")
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise DsoFormatError(f"{file} must be a single-channel 8- or 16-bit image")
    threshold = OUTSIDE_FOV_VALUE if image.dtype == np.uint16 else 0
    fov = image > threshold
    if not fov.any():
        raise DsoFormatError(f"{file} is black everywhere")
    values = image.astype(np.float64)
    light = np.where(fov, values / values[fov].max(), 0.0)
    return light, fov


def import_dso(
    directory: str | Path,
    pcalib: str | Path | None = None,
    vignette: str | Path | None = None,
    light_model_degree: int = 8,
) -> PhotometricCalibration:
    """Build a mono calibration from DSO files.

    directory: folder holding ``pcalib.txt`` and ``vignette.png``; ``pcalib`` and
        ``vignette`` override either path.
    light_model_degree: degree of the smooth light model fitted to the vignette
        (kept for resampling; the correction uses the per-pixel vignette).
    Returns a :class:`PhotometricCalibration` with light source "pixels".
    """
    folder = Path(directory)
    response = read_pcalib(pcalib or folder / PCALIB_NAME)
    light, fov = read_vignette(vignette or folder / VIGNETTE_NAME)
    model = fit_light_model(light, fov.astype(np.float64), light_model_degree)
    channel = ChannelCalibration("mono", response, light, model)
    summary = {"imported_from": "TUM/DSO", "directory": str(folder)}
    return PhotometricCalibration([channel], fov, None, "pixels", summary)
