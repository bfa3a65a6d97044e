"""``handeye.yaml``: the hand–eye and clock calibration the bridge loads.

Layout (YAML, every length in metres unless the key says otherwise)::

    T_marker_camera:            # 4x4 rows; camera optical frame → marker frame
      - [r11, r12, r13, tx]
      - ...
    time_offset_s: 0.0213       # tracker_stamp = camera_time + time_offset_s
    time_offset_convention: "tracker_stamp = camera_time + time_offset_s; ..."
    method: "park + least-squares"
    date: "2026-11-22T10:00:00+00:00"
    residuals:
      reprojection_rms_px: 0.21
      translation_rms_mm: 0.31  # spread of the target pose over the views
      rotation_rms_deg: 0.12
    views_used: 118
    views_total: 120
    T_tracker_target: [...]     # optional, the board in the tracker frame
    details: {...}              # optional, free-form (per-method results)
    provenance:                 # optional (endo_io.provenance): input bag (name, size,
      input: {...}              #   sha256), topics, camera_info, board, tool (program,
      ...                       #   endo3d version, date, command line)

Files written before ``provenance`` existed load as before; loading logs the
provenance (or its absence) at info level.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from endo_io.errors import yaml_error_line
from endo_io.provenance import provenance_summary
from endo_tracker_bridge.errors import HandEyeFileError
from endo_tracker_bridge.validation import check_rotation_matrix

_LOG = logging.getLogger(__name__)
TIME_OFFSET_CONVENTION = (
    "tracker_stamp = camera_time + time_offset_s; the bridge stamps /endoscope/pose "
    "at tracker_stamp - time_offset_s"
)
RESIDUAL_KEYS = ("reprojection_rms_px", "translation_rms_mm", "rotation_rms_deg")


@dataclass(frozen=True)
class HandEyeCalibration:
    """Result of a hand–eye and clock calibration.

    Attributes:
        T_marker_camera: (4,4) float64, metres: camera optical frame → marker frame.
        time_offset_ns: Integer ns, ``tracker_stamp = camera_time + time_offset_ns``.
        residuals: ``reprojection_rms_px`` (pixels), ``translation_rms_mm`` and
            ``rotation_rms_deg`` (spread of the per-view target pose).
        method: How it was computed (closed-form method chosen + refinement).
        date: ISO 8601 date-time of the calibration.
        views_used, views_total: Views kept after outlier rejection, and views
            with a detected board.
        T_tracker_target: (4,4) float64 board pose in the tracker frame, or None.
        details: Free-form extra results (per-method residuals, search range).
        provenance: Where it came from (:mod:`endo_io.provenance`); empty when unknown.
    """

    T_marker_camera: np.ndarray
    time_offset_ns: int = 0
    residuals: dict[str, float] = field(default_factory=dict)
    method: str = ""
    date: str = ""
    views_used: int = 0
    views_total: int = 0
    T_tracker_target: np.ndarray | None = None
    details: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def identity(cls) -> HandEyeCalibration:
        """No calibration: the camera is the marker, no clock offset."""
        return cls(T_marker_camera=np.eye(4), method="identity (uncalibrated)")

    def save(self, path: str | Path) -> None:
        """Write this calibration as YAML to ``path``."""
        document: dict[str, Any] = {
            "T_marker_camera": _matrix_to_rows(self.T_marker_camera),
            "time_offset_s": self.time_offset_ns * 1e-9,
            "time_offset_convention": TIME_OFFSET_CONVENTION,
            "method": self.method,
            "date": self.date,
            "residuals": {k: float(v) for k, v in self.residuals.items()},
            "views_used": int(self.views_used),
            "views_total": int(self.views_total),
        }
        if self.T_tracker_target is not None:
            document["T_tracker_target"] = _matrix_to_rows(self.T_tracker_target)
        if self.details:
            document["details"] = _plain(self.details)
        if self.provenance:
            document["provenance"] = _plain(self.provenance)
        text = "# endo3d hand-eye and clock calibration (endo-handeye)\n"
        text += yaml.safe_dump(document, sort_keys=False, default_flow_style=None)
        Path(path).write_text(text)

    @classmethod
    def load(cls, path: str | Path) -> HandEyeCalibration:
        """Read a calibration written by :meth:`save`; raise :class:`HandEyeFileError` if bad."""
        try:
            document = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError) as error:
            raise HandEyeFileError(
                f"cannot read hand-eye file {path}: {yaml_error_line(error)}"
            ) from error
        if not isinstance(document, dict) or "T_marker_camera" not in document:
            raise HandEyeFileError(f"{path}: no T_marker_camera")
        T = _rows_to_matrix(document["T_marker_camera"], path, "T_marker_camera")
        offset_s = document.get("time_offset_s", 0.0)
        if not isinstance(offset_s, int | float) or not math.isfinite(offset_s):
            raise HandEyeFileError(
                f"{path}: time_offset_s must be a finite number, got {offset_s!r}"
            )
        residuals = document.get("residuals") or {}
        if not isinstance(residuals, dict):
            raise HandEyeFileError(f"{path}: residuals must be a mapping")
        target = document.get("T_tracker_target")
        provenance = document.get("provenance") or {}
        if not isinstance(provenance, dict):
            raise HandEyeFileError(f"{path}: provenance must be a mapping")
        _LOG.info("hand-eye calibration %s: %s", path, provenance_summary(provenance))
        return cls(
            T_marker_camera=T,
            time_offset_ns=round(float(offset_s) * 1e9),
            residuals={str(k): float(v) for k, v in residuals.items()},
            method=str(document.get("method", "")),
            date=str(document.get("date", "")),
            views_used=int(document.get("views_used", 0)),
            views_total=int(document.get("views_total", 0)),
            T_tracker_target=None
            if target is None
            else _rows_to_matrix(target, path, "T_tracker_target"),
            details=dict(document.get("details") or {}),
            provenance=provenance,
        )


def _matrix_to_rows(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T, dtype=np.float64)]


def _rows_to_matrix(value: Any, path: str | Path, key: str) -> np.ndarray:
    try:
        T = np.asarray(value, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        raise HandEyeFileError(f"{path}: {key} must be 4x4 numbers") from None
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise HandEyeFileError(f"{path}: {key} is not a finite homogeneous transform")
    try:
        T[:3, :3] = check_rotation_matrix(T[:3, :3], tolerance=1e-6)
    except ValueError as error:
        raise HandEyeFileError(f"{path}: {key}: {error}") from None
    return T


def _plain(value: Any) -> Any:
    """Turn numpy scalars/arrays inside ``value`` into plain YAML types."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value
