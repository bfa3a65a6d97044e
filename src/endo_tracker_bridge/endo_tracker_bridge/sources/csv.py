"""Source ``csv``: a comma- or tab-separated tracker log, replayed with its own stamps.

The first line that is not a ``#`` comment is a header; columns are found by
name (case-insensitive), so NDI Track exports and hand-made logs both work:

=============  ==========================================================
time           ``stamp_ns`` / ``time_ns`` / ``timestamp_ns`` (integer ns), or
               ``timestamp`` / ``time`` / ``stamp`` / ``time_s`` /
               ``timestamp_s`` (decimal seconds, parsed exactly)
translation    ``x, y, z`` or ``tx, ty, tz`` (in the log's unit)
rotation       ``qx, qy, qz, qw`` (or ``q0`` for w, NDI's name), or a
               matrix ``m00 … m23`` (row-major 3x4, translation in m03,
               m13, m23; ``m30 … m33`` may follow and are ignored)
tool           optional ``tool`` / ``tool_id`` / ``port`` / ``device``
status         optional ``status`` / ``state``: ok, visible, valid, enabled,
               1, true are visible; missing, occluded, out of volume, 0,
               false are missing; disabled is disabled
frame          optional ``frame`` / ``frame_number`` / ``frame#``
quality        optional ``error`` / ``rms_error`` / ``quality``
=============  ==========================================================

Empty cells and ``nan`` are NaN. A row whose rotation and translation are
all NaN is a missing tool (as NDI Track writes them).
"""

from __future__ import annotations

import csv
import decimal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endo_tracker_bridge.conventions import (
    LengthUnit,
    transform_from_matrix,
    transform_from_quaternion,
)
from endo_tracker_bridge.errors import TrackerLogError, TrackerSampleError
from endo_tracker_bridge.sample import ToolStatus, TrackerSample
from endo_tracker_bridge.sources.background import BackgroundSource
from endo_tracker_bridge.validation import DEFAULT_ROTATION_TOLERANCE

_NS_COLUMNS = ("stamp_ns", "time_ns", "timestamp_ns")
_SECONDS_COLUMNS = ("timestamp", "time", "stamp", "time_s", "timestamp_s")
_TRANSLATION_COLUMNS = (("x", "y", "z"), ("tx", "ty", "tz"))
_QUATERNION_COLUMNS = (("qx", "qy", "qz", "qw"), ("qx", "qy", "qz", "q0"))
_MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(3) for j in range(4))
_TOOL_COLUMNS = ("tool", "tool_id", "port", "device")
_STATUS_COLUMNS = ("status", "state")
_FRAME_COLUMNS = ("frame", "frame_number", "frame#", "framenumber")
_QUALITY_COLUMNS = ("error", "rms_error", "quality")
_VISIBLE = {"ok", "visible", "valid", "enabled", "1", "true"}
_MISSING = {
    "missing",
    "occluded",
    "out of volume",
    "partially out of volume",
    "0",
    "false",
    "invalid",
}
_DISABLED = {"disabled"}


class TrackerLogRowError(TrackerSampleError):
    """One row of a tracker log cannot be read (bad number, wrong column count)."""


@dataclass(frozen=True)
class TrackerLog:
    """A parsed log: header, raw rows and their stamps (None where unreadable).

    ``rows`` are (line number, cells) pairs; ``stamps_ns`` are integer ns.
    """

    path: str
    columns: tuple[str, ...]
    delimiter: str
    rows: tuple[tuple[int, tuple[str, ...]], ...]
    stamps_ns: tuple[int | None, ...]

    def column(self, names: Sequence[str]) -> int | None:
        """Index of the first of ``names`` present in the header, else None."""
        for name in names:
            if name in self.columns:
                return self.columns.index(name)
        return None


def _sniff_delimiter(header_line: str) -> str:
    if "\t" in header_line:
        return "\t"
    if ";" in header_line and "," not in header_line:
        return ";"
    return ","


def _parse_seconds_ns(text: str) -> int:
    try:
        value = decimal.Decimal(text.strip())
    except decimal.InvalidOperation:
        raise ValueError(f"'{text}' is not a number of seconds") from None
    if not value.is_finite():
        raise ValueError(f"'{text}' is not a finite time")
    return int((value * 1_000_000_000).to_integral_value(rounding=decimal.ROUND_HALF_EVEN))


def read_tracker_log(path: str | Path, delimiter: str = "") -> TrackerLog:
    """Read a tracker log; ``delimiter`` "" detects tab, semicolon or comma from the header.

    Raises :class:`TrackerLogError` when the file cannot be read or lacks a
    time, translation or rotation column.
    """
    try:
        lines = Path(path).read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise TrackerLogError(f"cannot read tracker log {path}: {error}") from None
    numbered = [
        (n + 1, line)
        for n, line in enumerate(lines)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not numbered:
        raise TrackerLogError(f"tracker log {path} has no header line")
    separator = delimiter or _sniff_delimiter(numbered[0][1])
    parsed = list(csv.reader([line for _, line in numbered], delimiter=separator))
    columns = tuple(cell.strip().lower() for cell in parsed[0])
    rows = tuple((n, tuple(cells)) for (n, _), cells in zip(numbered[1:], parsed[1:], strict=True))
    log = TrackerLog(str(path), columns, separator, rows, ())
    ns_column, s_column = log.column(_NS_COLUMNS), log.column(_SECONDS_COLUMNS)
    if ns_column is None and s_column is None:
        raise TrackerLogError(
            f"tracker log {path} has no time column ({', '.join(_NS_COLUMNS + _SECONDS_COLUMNS)})"
        )
    has_translation = any(all(c in columns for c in names) for names in _TRANSLATION_COLUMNS)
    has_quaternion = any(all(c in columns for c in names) for names in _QUATERNION_COLUMNS)
    has_matrix = all(c in columns for c in _MATRIX_COLUMNS)
    if not has_matrix and not (has_translation and has_quaternion):
        raise TrackerLogError(
            f"tracker log {path} needs x,y,z with qx,qy,qz,qw, or m00..m23 columns"
        )
    stamps: list[int | None] = []
    for _, cells in rows:
        try:
            if ns_column is not None:
                stamps.append(int(cells[ns_column].strip()))
            else:
                stamps.append(_parse_seconds_ns(cells[s_column]))  # type: ignore[index]
        except (ValueError, IndexError):
            stamps.append(None)
    return TrackerLog(str(path), columns, separator, rows, tuple(stamps))


def _float(cell: str) -> float:
    text = cell.strip()
    return float("nan") if text == "" else float(text)


def sample_from_log_row(
    log: TrackerLog,
    index: int,
    unit: LengthUnit = LengthUnit.MILLIMETRE,
    tolerance: float = DEFAULT_ROTATION_TOLERANCE,
) -> TrackerSample:
    """Convert row ``index`` of ``log`` to a sample in metres.

    Raises TrackerLogRowError (unreadable time or number, short row),
    NonFinitePoseError, NonUnitQuaternionError or NonOrthonormalRotationError.
    A row reported missing (status column, or an all-NaN pose) becomes a
    sample with status MISSING, rejected later by the gate.
    """
    line, cells = log.rows[index]
    stamp_ns = log.stamps_ns[index]
    if stamp_ns is None:
        raise TrackerLogRowError(f"{log.path}:{line}: unreadable time")
    if len(cells) < len(log.columns):
        raise TrackerLogRowError(
            f"{log.path}:{line}: {len(cells)} cells, header has {len(log.columns)}"
        )

    def cell(names: Sequence[str]) -> str | None:
        column = log.column(names)
        return None if column is None else cells[column].strip()

    tool = cell(_TOOL_COLUMNS) or ""
    frame_text, quality_text = cell(_FRAME_COLUMNS), cell(_QUALITY_COLUMNS)
    status_text = (cell(_STATUS_COLUMNS) or "ok").lower()
    if status_text in _DISABLED:
        status = ToolStatus.DISABLED
    elif status_text in _MISSING:
        status = ToolStatus.MISSING
    elif status_text in _VISIBLE:
        status = ToolStatus.VISIBLE
    else:
        raise TrackerLogRowError(f"{log.path}:{line}: unknown tool status '{status_text}'")
    try:
        frame_number = int(float(frame_text)) if frame_text else None
        quality = _float(quality_text) if quality_text else None
        if all(c in log.columns for c in _MATRIX_COLUMNS):
            values = np.array([_float(cells[log.columns.index(c)]) for c in _MATRIX_COLUMNS])
            pose_values = values
        else:
            names_t = next(n for n in _TRANSLATION_COLUMNS if all(c in log.columns for c in n))
            names_q = next(n for n in _QUATERNION_COLUMNS if all(c in log.columns for c in n))
            translation = np.array([_float(cells[log.columns.index(c)]) for c in names_t])
            quaternion = np.array([_float(cells[log.columns.index(c)]) for c in names_q])
            pose_values = np.concatenate([translation, quaternion])
    except ValueError as error:
        raise TrackerLogRowError(f"{log.path}:{line}: {error}") from None
    if quality is not None and not np.isfinite(quality):
        quality = None
    if status is not ToolStatus.VISIBLE or np.all(np.isnan(pose_values)):
        return TrackerSample(
            stamp_ns=stamp_ns,
            T_tracker_marker=np.full((4, 4), np.nan),
            tool_id=tool,
            status=ToolStatus.MISSING if status is ToolStatus.VISIBLE else status,
            frame_number=frame_number,
        )
    if pose_values.size == 12:
        T = transform_from_matrix(pose_values.reshape(3, 4), unit, tolerance)
    else:
        T = transform_from_quaternion(pose_values[3:7], pose_values[0:3], unit, tolerance)
    return TrackerSample(
        stamp_ns=stamp_ns,
        T_tracker_marker=T,
        tool_id=tool,
        frame_number=frame_number,
        quality=quality,
    )


class CsvReplaySource(BackgroundSource):
    """Replays a tracker log in real time (× ``rate``), keeping the log's stamps.

    Rows are released when ``(stamp − first stamp) / rate`` has elapsed since
    the start; ``rate = 0`` releases them as fast as they are taken. Only rows
    of ``tool`` are replayed when it is non-empty. A row with an unreadable
    time is released right after the row before it (and rejected then).
    """

    def __init__(
        self,
        path: str | Path,
        unit: LengthUnit = LengthUnit.MILLIMETRE,
        delimiter: str = "",
        tool: str = "",
        rate: float = 1.0,
        tolerance: float = DEFAULT_ROTATION_TOLERANCE,
        log: Callable[[str], None] | None = None,
    ) -> None:
        super().__init__(log, queue_length=1 << 16)
        self.log_file = read_tracker_log(path, delimiter)
        self.unit, self.tool, self.rate, self.tolerance = unit, tool, rate, tolerance
        self._set_status(path=str(path), rows=len(self.log_file.rows), replayed=0, finished=False)

    def to_sample(self, item: int) -> TrackerSample:
        """Convert row ``item`` of the log (see :func:`sample_from_log_row`)."""
        return sample_from_log_row(self.log_file, item, self.unit, self.tolerance)

    def _selected(self, index: int) -> bool:
        if not self.tool:
            return True
        column = self.log_file.column(_TOOL_COLUMNS)
        return column is not None and self.log_file.rows[index][1][column].strip() == self.tool

    def _run(self, stop: threading.Event) -> None:
        stamps = self.log_file.stamps_ns
        known = [s for s in stamps if s is not None]
        origin_ns = known[0] if known else 0
        start = time.monotonic()
        replayed = 0
        for index, stamp in enumerate(stamps):
            if stop.is_set():
                return
            if not self._selected(index):
                continue
            if stamp is not None and self.rate > 0:
                delay_s = (stamp - origin_ns) * 1e-9 / self.rate - (time.monotonic() - start)
                if delay_s > 0 and stop.wait(delay_s):
                    return
            self._emit(index)
            replayed += 1
            self._set_status(replayed=replayed)
        self._set_status(finished=True)
        self._log(f"tracker log {self.log_file.path}: replay finished ({replayed} rows)")
