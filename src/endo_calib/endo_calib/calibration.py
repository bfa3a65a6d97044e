"""The photometric calibration of a camera and the per-frame correction.

``PhotometricCalibration.correct(raw)`` turns a raw frame into linear
irradiance with the light map divided out,

    I(x) = g(v(x)) / L(x),

which for a Lambertian scene is ρ(x)·cos θ/r² times one global constant: what
shape from shading needs. Saturated raw values and pixels outside the field of
view give NaN.

On disk a calibration is ``photometric.yaml`` (human-readable: bit depth,
channels, the inverse-response table, the smooth light model's coefficients,
fit diagnostics) and, beside it, ``<stem>.light_map.png``: the per-pixel light
map as a 16-bit PNG (value = round(L·65535), 0 outside the field of view; RGB
calibrations store a 3-channel PNG).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from endo_calib.errors import CalibrationError, CalibrationFileError, CalibrationMismatchError
from endo_calib.light_map import LightModel, resample_map
from endo_calib.response import InverseResponse
from endo_io.provenance import provenance_summary

if TYPE_CHECKING:
    from endo_calib.fit import FitReport

_LOG = logging.getLogger(__name__)
FILE_FORMAT = "endo3d.photometric_calibration"
FILE_VERSION = 1
#: Scale of the 16-bit light-map PNG: stored value = round(L · PNG_SCALE).
PNG_SCALE = 65535.0
#: How a light map is turned into the one the correction divides by.
LIGHT_SOURCES = ("model", "pixels")
#: Rec. 709 luminance weights of linear R, G, B.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
#: What :func:`select_channel` picks from a corrected frame.
OUTPUT_CHANNELS = ("luminance", "red", "green", "blue", "rgb")


@dataclass(frozen=True, eq=False)
class ChannelCalibration:
    """Calibration of one colour channel.

    name: "mono", "red", "green" or "blue".
    inverse_response: g of this channel.
    light_pixels: (H, W) float64 per-pixel light map, 0 outside the field of view.
    light_model: the smooth light model (None when only a per-pixel map is known,
        e.g. after a DSO import).
    """

    name: str
    inverse_response: InverseResponse
    light_pixels: NDArray[np.float64]
    light_model: LightModel | None


@dataclass(frozen=True, eq=False)
class _Corrector:
    """Precomputed tables of one image size: float32 LUT(s) and 1/L."""

    luts: NDArray[np.float32]  # (C, n) float32, NaN at saturated/out-of-range values
    inv_light: NDArray[np.float32]  # (H, W) or (H, W, C) float32, NaN outside the FOV
    lut_cv: NDArray[np.float32] | None  # (1, 256, C) or (256,) table for cv2.LUT (8-bit only)


class PhotometricCalibration:
    """Inverse response and light map of one camera (all channels), ready to correct frames.

    channels: one :class:`ChannelCalibration` per channel, ("mono",) or
        ("red", "green", "blue"), all the same bit depth and size.
    fov_mask: (H, W) bool field of view.
    saturation_value: raw values ≥ this are saturated (NaN after correction).
    light_source: "model" (divide by the smooth light model inside the field of
        view) or "pixels" (divide by the per-pixel map).
    fit_summary: diagnostics of the fit, stored in the YAML (free-form mapping).
    response_ranges: per channel name, which raw values the fit observed and
        which are extrapolated (``ResponseExtent.as_dict``; empty for files
        written before it was recorded, and for DSO imports).
    provenance: the input and run that produced the calibration
        (:mod:`endo_io.provenance`; empty when unknown).
    """

    def __init__(
        self,
        channels: list[ChannelCalibration],
        fov_mask: NDArray[np.bool_],
        saturation_value: int | None = None,
        light_source: str = "model",
        fit_summary: dict[str, Any] | None = None,
        *,
        response_ranges: dict[str, dict[str, Any]] | None = None,
        provenance: dict[str, Any] | None = None,
    ) -> None:
        if not channels:
            raise CalibrationError("a calibration needs at least one channel")
        names = tuple(ch.name for ch in channels)
        if names not in (("mono",), ("red", "green", "blue")):
            raise CalibrationError(f"channels must be (mono) or (red, green, blue), got {names}")
        bits = {ch.inverse_response.bit_depth for ch in channels}
        shapes = {ch.light_pixels.shape for ch in channels}
        if len(bits) != 1 or len(shapes) != 1:
            raise CalibrationError("channels differ in bit depth or light-map size")
        if light_source not in LIGHT_SOURCES:
            raise CalibrationError(
                f"light source must be one of {LIGHT_SOURCES}, got {light_source!r}"
            )
        if light_source == "model" and any(ch.light_model is None for ch in channels):
            raise CalibrationError("light source 'model' needs a light model for every channel")
        self.channels = channels
        self.fov_mask = np.asarray(fov_mask, dtype=bool)
        if self.fov_mask.shape != channels[0].light_pixels.shape:
            raise CalibrationError("field-of-view mask and light map differ in size")
        self.bit_depth = bits.pop()
        top = (1 << self.bit_depth) - 1
        self.saturation_value = top if saturation_value is None else int(saturation_value)
        self.light_source = light_source
        self.fit_summary = dict(fit_summary or {})
        self.response_ranges = {str(k): dict(v) for k, v in (response_ranges or {}).items()}
        self.provenance = dict(provenance or {})
        self._correctors: dict[tuple[int, int, bool], _Corrector] = {}
        self._check_light_maps()

    def _check_light_maps(self) -> None:
        """Refuse a light map the correction cannot divide by (zero, negative, non-finite).

        A light map that is not positive over most of the field of view makes
        every corrected pixel NaN: a zero light model (all coefficients 0), a
        light-map PNG of zeros, a corrupt model.

        Raises:
            CalibrationError: one line naming the channel and what is wrong.
        """
        inside = self.fov_mask
        if not inside.any():
            raise CalibrationError("the light map is 0 everywhere: there is no field of view")
        for ch in self.channels:
            if self.light_source == "model" and ch.light_model is not None:
                what = f"light model of channel {ch.name}"
                coefficients = ch.light_model.coefficients
                if not np.all(np.isfinite(coefficients)):
                    raise CalibrationError(f"{what} has coefficients that are not finite")
                if not np.any(coefficients):
                    raise CalibrationError(
                        f"{what} has all coefficients 0: every corrected pixel would be NaN"
                    )
                values = ch.light_model.evaluate(self.width, self.height)[inside]
            else:
                what = f"light map of channel {ch.name}"
                values = ch.light_pixels[inside]
            usable = float(np.mean(np.isfinite(values) & (values > 0.0)))
            if usable < 0.5:
                raise CalibrationError(
                    f"{what} is positive on {100 * usable:.0f} % of the field of view: most "
                    "corrected pixels would be NaN"
                )

    # ----------------------------------------------------------------- views
    @property
    def channel_names(self) -> tuple[str, ...]:
        """("mono",) or ("red", "green", "blue")."""
        return tuple(ch.name for ch in self.channels)

    @property
    def width(self) -> int:
        """Width of the calibrated images in pixels."""
        return int(self.fov_mask.shape[1])

    @property
    def height(self) -> int:
        """Height of the calibrated images in pixels."""
        return int(self.fov_mask.shape[0])

    @property
    def inverse_response(self) -> NDArray[np.float64]:
        """The inverse response table(s): (2^bits,) float64 for mono, (2^bits, 3) for RGB.

        ``inverse_response[v]`` is g(v), 0 at v = 0 and 1 at v = 2^bits − 1.
        """
        tables = [ch.inverse_response.lut for ch in self.channels]
        return tables[0].copy() if len(tables) == 1 else np.stack(tables, axis=-1)

    @property
    def light_map(self) -> NDArray[np.float64]:
        """The light map the correction divides by: (H, W) or (H, W, 3) float64, 0 off the FOV."""
        return self.light_map_at(self.width, self.height)

    def light_map_at(self, width: int, height: int) -> NDArray[np.float64]:
        """The light map resampled to another resolution of the same sensor.

        Returns (height, width) or (height, width, 3) float64, 0 outside the FOV.
        Raises CalibrationMismatchError for another aspect ratio.
        """
        maps = []
        for ch in self.channels:
            if self.light_source == "model" and ch.light_model is not None:
                _, inside = resample_map(ch.light_pixels, self.fov_mask, width, height)
                maps.append(np.where(inside, ch.light_model.evaluate(width, height), 0.0))
            else:
                maps.append(resample_map(ch.light_pixels, self.fov_mask, width, height)[0])
        return maps[0] if len(maps) == 1 else np.stack(maps, axis=-1)

    def observed_top(self, channel: str) -> int | None:
        """The highest raw value of ``channel`` the fit observed unsaturated (None: unknown).

        Values above it have an extrapolated inverse response.
        """
        extent = self.response_ranges.get(channel) or {}
        observed = extent.get("observed")
        return int(observed[1]) if observed else None

    # ------------------------------------------------------------ correction
    def _corrector(self, width: int, height: int, mask_extrapolated: bool = False) -> _Corrector:
        key = (width, height, mask_extrapolated)
        cached = self._correctors.get(key)
        if cached is not None:
            return cached
        light = self.light_map_at(width, height)
        with np.errstate(divide="ignore"):
            inv = np.where(light > 0.0, 1.0 / np.where(light > 0.0, light, 1.0), np.nan)
        inv = inv.astype(np.float32)
        size = 1 << self.bit_depth
        # Tables cover every value the container may hold; values beyond the bit
        # depth or at saturation are NaN.
        length = 256 if self.bit_depth == 8 else 1 << 16
        luts = np.full((len(self.channels), length), np.nan, np.float32)
        for c, ch in enumerate(self.channels):
            luts[c, :size] = ch.inverse_response.lut.astype(np.float32)
        luts[:, min(self.saturation_value, length) :] = np.nan
        if mask_extrapolated:
            for c, ch in enumerate(self.channels):
                top = self.observed_top(ch.name)
                if top is not None:
                    luts[c, top + 1 :] = np.nan
        lut_cv: NDArray[np.float32] | None = None
        if self.bit_depth == 8:
            lut_cv = (
                luts[0].copy()
                if len(self.channels) == 1
                else np.ascontiguousarray(luts.T.reshape(1, 256, len(self.channels)))
            )
        corrector = _Corrector(luts, inv, lut_cv)
        if len(self._correctors) > 8:
            self._correctors.clear()
        self._correctors[key] = corrector
        return corrector

    def correct(
        self,
        raw: NDArray[np.integer],
        out: NDArray[np.float32] | None = None,
        *,
        mask_extrapolated: bool = False,
    ) -> NDArray[np.float32]:
        """Linear, light-corrected irradiance of a raw frame.

        raw: (H, W) for a mono calibration or (H, W, 3) RGB for a colour one;
            uint8 for 8-bit calibrations, uint8/uint16 otherwise (values in
            0..2^bits − 1). Any resolution with the calibration's aspect ratio
            (binned or scaled streams); the light map is resampled once per size.
        out: optional float32 output array of the result's shape.
        mask_extrapolated: NaN also where the raw value is above the highest
            value the calibration observed (its inverse response is
            extrapolated there; see ``response_ranges``).
        Returns (H, W) or (H, W, 3) float32: g(v)/L(x), NaN where v is saturated
        or out of range and outside the field of view.
        Raises CalibrationMismatchError when the frame does not fit the calibration.
        """
        image = np.asarray(raw)
        n_channels = len(self.channels)
        expected_ndim = 2 if n_channels == 1 else 3
        if image.ndim != expected_ndim or (n_channels == 3 and image.shape[2] != 3):
            raise CalibrationMismatchError(
                f"frame of shape {image.shape} does not fit a "
                f"{'/'.join(self.channel_names)} calibration{_channel_hint(image.ndim, n_channels)}"
            )
        if image.dtype == np.uint8:
            if self.bit_depth != 8:
                raise CalibrationMismatchError(
                    f"8-bit frame given to a {self.bit_depth}-bit calibration"
                )
        elif image.dtype == np.uint16:
            if self.bit_depth == 8:
                raise CalibrationMismatchError("16-bit frame given to an 8-bit calibration")
        else:
            raise CalibrationMismatchError(f"raw frame must be uint8 or uint16, got {image.dtype}")
        height, width = image.shape[:2]
        tables = self._corrector(width, height, mask_extrapolated)
        result: NDArray[np.float32]
        if tables.lut_cv is not None:
            result = np.asarray(cv2.LUT(image, tables.lut_cv, dst=out), dtype=np.float32)
        elif n_channels == 1:
            result = np.take(tables.luts[0], image, out=out)
        else:
            result = out if out is not None else np.empty(image.shape, np.float32)
            for c in range(n_channels):
                np.take(tables.luts[c], image[:, :, c], out=result[:, :, c])
        np.multiply(result, tables.inv_light, out=result)
        return result

    def luminance(self, corrected: NDArray[np.float32]) -> NDArray[np.float32]:
        """Rec. 709 luminance of a corrected RGB frame, (H, W, 3) -> (H, W) float32; mono passes."""
        if corrected.ndim == 2:
            return corrected
        w = np.asarray(LUMINANCE_WEIGHTS, np.float32)
        return (
            corrected[..., 0] * w[0] + corrected[..., 1] * w[1] + corrected[..., 2] * w[2]
        ).astype(np.float32, copy=False)

    # ------------------------------------------------------------ construction
    @classmethod
    def from_fit(cls, report: FitReport, light_source: str = "model") -> PhotometricCalibration:
        """The calibration of a gray-card fit.

        Args:
            report: what :func:`endo_calib.fit.fit_gray_card` returned.
            light_source: "model" (divide by the smooth light model) or
                "pixels" (by the per-pixel light map).

        Returns:
            The calibration; its ``fit_summary`` holds the fit's diagnostics
            as they are saved to the YAML.
        """
        channels = [
            ChannelCalibration(name, fit.inverse_response, fit.light_map, fit.light_model)
            for name, fit in report.channels.items()
        ]
        summary: dict[str, Any] = {
            "created": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "levels": [
                {k: (round(v, 6) if isinstance(v, float) else v) for k, v in lv.items()}
                for lv in report.levels
            ],
            "channels": {
                name: {
                    "residual_rms_dn": round(fit.residual_rms, 4),
                    "iterations": fit.iterations,
                    "converged": fit.converged,
                }
                for name, fit in report.channels.items()
            },
        }
        top = (1 << report.bit_depth) - 1
        ranges = {
            name: fit.extent.as_dict(top)
            for name, fit in report.channels.items()
            if fit.extent is not None
        }
        return cls(
            channels,
            report.fov_mask,
            report.saturation_value,
            light_source,
            summary,
            response_ranges=ranges,
        )

    # ----------------------------------------------------------------- files
    def save(self, path: str | Path) -> Path:
        """Write ``path`` (YAML) and ``<stem>.light_map.png`` beside it; returns the YAML path."""
        yaml_path = Path(path)
        png_path = yaml_path.with_name(yaml_path.stem + ".light_map.png")
        yaml_path.parent.mkdir(parents=True, exist_ok=True)
        stack = np.stack([ch.light_pixels for ch in self.channels], axis=-1)
        peak = float(stack.max()) if stack.size else 1.0
        scale = PNG_SCALE / max(peak, 1.0)  # maps may exceed 1 slightly where noisy
        png = np.clip(np.rint(stack * scale), 0, 65535).astype(np.uint16)
        png[~self.fov_mask] = 0
        png[self.fov_mask] = np.maximum(png[self.fov_mask], 1)  # keep the FOV visible in the PNG
        image = png[:, :, 0] if png.shape[2] == 1 else png[:, :, ::-1]  # OpenCV writes BGR
        if not cv2.imwrite(str(png_path), np.ascontiguousarray(image)):
            raise CalibrationFileError(f"cannot write light map {png_path}")
        document: dict[str, Any] = {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "model": "v = f(rho * L(x) * G(x)); corrected = g(v) / L(x), g = f^-1",
            "width": self.width,
            "height": self.height,
            "bit_depth": self.bit_depth,
            "saturation_value": self.saturation_value,
            "channels": list(self.channel_names),
            "light_map": {
                "file": png_path.name,
                "png_scale": float(scale),
                "note": "16-bit PNG, L = value / png_scale, 0 outside the field of view",
                "source": self.light_source,
                "model": _model_document(self.channels),
            },
            "inverse_response": {
                ch.name: [float(f"{x:.8g}") for x in ch.inverse_response.lut]
                for ch in self.channels
            },
            "fit": self.fit_summary,
        }
        if self.response_ranges:
            document["response_range"] = self.response_ranges
        if self.provenance:
            document["provenance"] = self.provenance
        text = yaml.safe_dump(document, sort_keys=False, default_flow_style=None, width=100)
        yaml_path.write_text(text, encoding="utf-8")
        return yaml_path

    @classmethod
    def load(cls, path: str | Path) -> PhotometricCalibration:
        """Read a calibration written by :meth:`save`.

        Raises CalibrationFileError naming the file and the cause when it is
        missing, not YAML, not a calibration, inconsistent, or its light map
        PNG is missing or of the wrong size.
        """
        yaml_path = Path(path)
        if not yaml_path.is_file():
            raise CalibrationFileError(f"calibration file {yaml_path} not found")
        try:
            document = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as error:
            first = str(error).splitlines()[0] if str(error) else type(error).__name__
            raise CalibrationFileError(
                f"calibration file {yaml_path} is not valid YAML: {first}"
            ) from error
        except OSError as error:
            raise CalibrationFileError(
                f"cannot read calibration file {yaml_path}: {error}"
            ) from error
        try:
            calibration = cls._from_document(document, yaml_path)
            _LOG.info(
                "photometric calibration %s: %s",
                yaml_path,
                provenance_summary(calibration.provenance),
            )
            return calibration
        except CalibrationFileError:
            raise
        except (CalibrationError, KeyError, TypeError, ValueError, AttributeError) as error:
            cause = f"missing key {error}" if isinstance(error, KeyError) else str(error)
            raise CalibrationFileError(
                f"calibration file {yaml_path} is corrupt: {cause}"
            ) from error

    @classmethod
    def _from_document(cls, document: Any, yaml_path: Path) -> PhotometricCalibration:
        if not isinstance(document, dict) or document.get("format") != FILE_FORMAT:
            raise CalibrationFileError(f"{yaml_path} is not an endo3d photometric calibration")
        if int(document["version"]) != FILE_VERSION:
            raise CalibrationFileError(
                f"{yaml_path} has format version {document['version']}, {FILE_VERSION} is supported"
            )
        width, height = int(document["width"]), int(document["height"])
        names = [str(n) for n in document["channels"]]
        light = document["light_map"]
        png_path = yaml_path.with_name(str(light["file"]))
        if not png_path.is_file():
            raise CalibrationFileError(f"light map {png_path} of {yaml_path.name} not found")
        image = cv2.imread(str(png_path), cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint16:
            raise CalibrationFileError(f"light map {png_path} is not a readable 16-bit PNG")
        stack = image[:, :, None] if image.ndim == 2 else image[:, :, ::-1]
        if stack.shape != (height, width, len(names)):
            raise CalibrationFileError(
                f"light map {png_path} is {stack.shape[1]}x{stack.shape[0]}x{stack.shape[2]}, "
                f"the YAML says {width}x{height}x{len(names)}"
            )
        scale = float(light["png_scale"])
        if not (math.isfinite(scale) and scale > 0.0):
            raise CalibrationFileError(f"{yaml_path}: light_map.png_scale must be > 0")
        fov = np.any(stack > 0, axis=-1)
        model_doc = light.get("model")
        bits = int(document["bit_depth"])
        channels = []
        for c, name in enumerate(names):
            lut = document["inverse_response"][name]
            response = InverseResponse(np.asarray(lut, dtype=np.float64), bits)
            model = None
            if model_doc:
                if model_doc.get("kind") != "legendre2d":
                    raise CalibrationFileError(
                        f"{yaml_path}: unknown light model {model_doc.get('kind')!r}"
                    )
                degree = int(model_doc["degree"])
                coefficients = np.asarray(model_doc["coefficients"][name], dtype=np.float64)
                if coefficients.shape != ((degree + 1) * (degree + 2) // 2,):
                    raise CalibrationFileError(
                        f"{yaml_path}: light model of channel {name} has {coefficients.size} "
                        f"coefficients, degree {degree} needs {(degree + 1) * (degree + 2) // 2}"
                    )
                model = LightModel(degree, coefficients)
            pixels = np.where(fov, stack[:, :, c].astype(np.float64) / scale, 0.0)
            channels.append(ChannelCalibration(name, response, pixels, model))
        return cls(
            channels,
            fov,
            int(document.get("saturation_value", (1 << bits) - 1)),
            str(light.get("source", "model" if model_doc else "pixels")),
            document.get("fit") or {},
            response_ranges=_mapping(document.get("response_range"), "response_range"),
            provenance=_mapping(document.get("provenance"), "provenance"),
        )


def select_channel(
    calibration: PhotometricCalibration, corrected: NDArray[np.float32], channel: str
) -> NDArray[np.float32]:
    """Pick one output channel from a corrected frame.

    Args:
        calibration: the calibration that corrected the frame.
        corrected: (H, W) or (H, W, 3) float32 from ``calibration.correct``.
        channel: one of ``OUTPUT_CHANNELS``; "luminance" of a mono calibration
            is its only channel.

    Returns:
        (H, W) float32, or (H, W, 3) for "rgb".

    Raises:
        CalibrationError: the calibration has no such channel.
    """
    names = calibration.channel_names
    if channel == "luminance":
        return calibration.luminance(corrected)
    if channel == "rgb":
        if corrected.ndim != 3:
            raise CalibrationError("channel 'rgb' needs a colour calibration")
        return corrected
    if channel not in names:
        raise CalibrationError(f"channel {channel!r} is not in the calibration's channels {names}")
    return np.ascontiguousarray(corrected[:, :, names.index(channel)])


def _mapping(value: Any, key: str) -> dict[str, Any]:
    """An optional mapping of the YAML ({} when absent); ValueError when it is not one."""
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ValueError(f"{key} must be a mapping, got {type(value).__name__}")
    return value


def _model_document(channels: list[ChannelCalibration]) -> dict[str, Any] | None:
    models = [ch.light_model for ch in channels]
    if any(m is None for m in models):
        return None
    first = models[0]
    assert first is not None
    return {
        "kind": "legendre2d",
        "coordinates": "x_n = 2(x + 0.5)/width - 1, y_n = 2(y + 0.5)/height - 1",
        "terms": "sum over i + j <= degree, i outer, j inner: c_ij P_i(x_n) P_j(y_n)",
        "degree": first.degree,
        "coefficients": {
            ch.name: [float(f"{x:.10g}") for x in ch.light_model.coefficients]  # type: ignore[union-attr]
            for ch in channels
        },
    }


def _channel_hint(frame_ndim: int, n_channels: int) -> str:
    """What to do when a stream's channels differ from the calibration's ("" when they agree).

    The inverse response and light map are per channel, so a colour stream needs a
    calibration fitted on that camera's colour gray-card images, not a mono one.
    """
    if frame_ndim == 3 and n_channels == 1:
        return (
            "; the stream is colour and the calibration mono: fit one on this camera's"
            " colour gray-card images (endo-calibrate keeps their red, green and blue)"
        )
    if frame_ndim == 2 and n_channels == 3:
        return (
            "; the stream is mono and the calibration colour: fit one on this camera's"
            " mono gray-card images, as the stream publishes them"
        )
    return ""

