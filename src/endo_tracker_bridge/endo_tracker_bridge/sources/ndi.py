"""Source ``ndi``: NDI Polaris, Vega or Aurora through scikit-surgerynditracker.

``NDITracker.get_frame()`` (scikit-surgerynditracker 1.0.x, via
sksurgerycore's ``SKSBaseTracker.get_smooth_frame``) returns a 5-tuple of
lists, one entry per tool, in the order of the tool descriptors (the ROM
files' order for Polaris/Vega, the wired ports for Aurora):

``(port_handles, time_stamps, frame_numbers, tracking, tracking_quality)``

* ``port_handles``: int port handle of each tool;
* ``time_stamps``: host ``time.time()`` float seconds when the frame was
  requested (the same for every tool of a frame);
* ``frame_numbers``: the tracker's 60 Hz frame counter, as a float;
* ``tracking``: by default a (4, 4) float64 matrix, rotation and translation
  in **millimetres**; with ``"use quaternions": True`` a (1, 7) array
  ``[qw, qx, qy, qz, x, y, z]`` (**w first**, millimetres). A tool reported
  MISSING or DISABLED comes back with NaN in the rotation and translation
  (the (4, 4) keeps its last row ``[0, 0, 0, 1]``);
* ``tracking_quality``: the tool's RMS marker fit error (mm), NaN when the
  tool is missing.

:func:`readings_from_ndi_frame` splits such a tuple per tool and
:func:`sample_from_ndi_reading` converts one tool to a sample.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from endo_tracker_bridge.conventions import (
    LengthUnit,
    quaternion_wxyz_to_xyzw,
    transform_from_matrix,
    transform_from_quaternion,
)
from endo_tracker_bridge.errors import NdiFrameError, ToolNotVisibleError, TrackerSourceError
from endo_tracker_bridge.sample import ToolStatus, TrackerSample
from endo_tracker_bridge.sources.background import BackgroundSource
from endo_tracker_bridge.validation import DEFAULT_ROTATION_TOLERANCE

TRACKER_TYPES = ("polaris", "vega", "aurora")


@dataclass(frozen=True)
class NdiToolReading:
    """One tool's entry of an NDI frame, as scikit-surgerynditracker gave it.

    ``port_handle`` is None for the library's "dummy" tracker, which assigns
    no handles; ``index`` is the tool's position in the frame.
    """

    port_handle: int | None
    time_stamp_s: float
    frame_number: float
    tracking: np.ndarray = field(repr=False)
    quality: float
    index: int = 0


def readings_from_ndi_frame(frame: Sequence[Any]) -> list[NdiToolReading]:
    """Split a ``get_frame()`` 5-tuple into per-tool readings.

    Raises :class:`NdiFrameError` when the tuple does not have five lists of
    equal length.
    """
    if len(frame) != 5:
        raise NdiFrameError(f"NDI frame has {len(frame)} parts, expected 5")
    handles, stamps, numbers, tracking, quality = (list(part) for part in frame)
    if not len(handles) == len(stamps) == len(numbers) == len(tracking) == len(quality):
        lengths = [len(handles), len(stamps), len(numbers), len(tracking), len(quality)]
        raise NdiFrameError(f"NDI frame lists have different lengths {lengths}")
    return [
        NdiToolReading(
            None if h is None else int(h),
            float(s),
            float(n),
            np.asarray(t, dtype=np.float64),
            float(q),
            index,
        )
        for index, (h, s, n, t, q) in enumerate(
            zip(handles, stamps, numbers, tracking, quality, strict=True)
        )
    ]


def sample_from_ndi_reading(
    reading: NdiToolReading,
    max_rms_error_mm: float = math.inf,
    tolerance: float = DEFAULT_ROTATION_TOLERANCE,
) -> TrackerSample:
    """Convert one tool's reading to a sample (metres, x,y,z,w internally).

    A reading whose pose is entirely NaN is the tool reported MISSING or
    DISABLED: it becomes a sample with status MISSING (and a NaN pose), which
    the :class:`~endo_tracker_bridge.validation.SampleGate` rejects as
    ToolNotVisibleError. A fit error above ``max_rms_error_mm`` raises
    ToolNotVisibleError (NDI's own "partially out of volume" readings have
    large errors). A partly NaN pose raises NonFinitePoseError; a bad layout
    NdiFrameError.
    """
    tracking = reading.tracking
    if tracking.shape == (4, 4):
        pose_values = tracking[:3, :]
    elif tracking.size == 7:
        pose_values = tracking.reshape(7)
    else:
        raise NdiFrameError(
            f"NDI tracking entry has shape {tracking.shape}, expected (4, 4) or (1, 7)"
        )
    stamp_ns = round(reading.time_stamp_s * 1e9)
    tool_id = f"tool{reading.index}" if reading.port_handle is None else str(reading.port_handle)
    frame_number = int(reading.frame_number) if math.isfinite(reading.frame_number) else None
    if np.all(np.isnan(pose_values)):
        return TrackerSample(
            stamp_ns=stamp_ns,
            T_tracker_marker=np.full((4, 4), np.nan),
            tool_id=tool_id,
            status=ToolStatus.MISSING,
            frame_number=frame_number,
        )
    if tracking.shape == (4, 4):
        T = transform_from_matrix(tracking, LengthUnit.MILLIMETRE, tolerance)
    else:
        values = tracking.reshape(7)
        T = transform_from_quaternion(
            quaternion_wxyz_to_xyzw(values[0:4]), values[4:7], LengthUnit.MILLIMETRE, tolerance
        )
    quality = reading.quality if math.isfinite(reading.quality) else None
    if quality is not None and quality > max_rms_error_mm:
        raise ToolNotVisibleError(
            f"tool {tool_id} fit error {quality:.3f} mm exceeds {max_rms_error_mm:g} mm"
        )
    return TrackerSample(
        stamp_ns=stamp_ns,
        T_tracker_marker=T,
        tool_id=tool_id,
        status=ToolStatus.VISIBLE,
        frame_number=frame_number,
        quality=quality,
    )


@dataclass(frozen=True)
class NdiOptions:
    """How to reach the tracker.

    ``tracker_type`` is polaris, vega or aurora; ``serial_port`` ("" probes
    the serial ports) is for Polaris/Aurora, ``ip_address``/``tcp_port`` for
    Vega; ``romfiles`` are the tool definition files (Polaris/Vega);
    ``tool_index`` picks the tool to follow in the frame's order;
    ``rate_hz`` is the polling rate (the tracker measures at 60 Hz).
    """

    tracker_type: str = "polaris"
    serial_port: str = ""
    ip_address: str = ""
    tcp_port: int = 8765
    romfiles: tuple[str, ...] = ()
    tool_index: int = 0
    rate_hz: float = 60.0
    max_rms_error_mm: float = math.inf

    def configuration(self) -> dict[str, Any]:
        """The configuration dict ``NDITracker(...)`` takes."""
        if self.tracker_type not in TRACKER_TYPES:
            raise TrackerSourceError(
                f"unknown NDI tracker type '{self.tracker_type}' "
                f"(expected {', '.join(TRACKER_TYPES)})"
            )
        config: dict[str, Any] = {"tracker type": self.tracker_type, "use quaternions": False}
        if self.tracker_type == "vega":
            if not self.ip_address:
                raise TrackerSourceError("NDI Vega needs an IP address")
            config.update({"ip address": self.ip_address, "port": int(self.tcp_port)})
        elif self.serial_port:
            config["serial port"] = self.serial_port
        if self.tracker_type in ("polaris", "vega"):
            if not self.romfiles:
                raise TrackerSourceError(
                    f"NDI {self.tracker_type} needs at least one tool ROM file"
                )
            config["romfiles"] = list(self.romfiles)
        return config


def _open_nditracker(configuration: dict[str, Any]) -> Any:
    from sksurgerynditracker.nditracker import NDITracker

    return NDITracker(configuration)


class NdiSource(BackgroundSource):
    """Polls an NDI tracker on a thread; reconnects after an I/O error.

    ``open_tracker`` builds the tracker object from the configuration dict
    (``NDITracker`` by default; tests pass a stand-in with the same
    ``start_tracking``/``get_frame``/``stop_tracking``/``close`` methods).
    """

    def __init__(
        self,
        options: NdiOptions,
        tolerance: float = DEFAULT_ROTATION_TOLERANCE,
        open_tracker: Callable[[dict[str, Any]], Any] = _open_nditracker,
        log: Callable[[str], None] | None = None,
    ) -> None:
        super().__init__(log)
        self.options = options
        self.tolerance = tolerance
        self._configuration = options.configuration()
        self._open_tracker = open_tracker
        self._set_status(connected=False, tracker_type=options.tracker_type)

    def to_sample(self, item: NdiToolReading) -> TrackerSample:
        """Convert one queued tool reading (see :func:`sample_from_ndi_reading`)."""
        return sample_from_ndi_reading(item, self.options.max_rms_error_mm, self.tolerance)

    def _run(self, stop: threading.Event) -> None:
        period_s = 1.0 / self.options.rate_hz
        while not stop.is_set():
            try:
                tracker = self._open_tracker(dict(self._configuration))
                tracker.start_tracking()
            except (OSError, ValueError, KeyError) as error:
                self._log(f"NDI tracker not available ({error}); retrying")
                stop.wait(2.0)
                continue
            self._set_status(connected=True)
            try:
                next_time = time.monotonic()
                while not stop.is_set():
                    readings = readings_from_ndi_frame(tracker.get_frame())
                    if self.options.tool_index < len(readings):
                        self._emit(readings[self.options.tool_index])
                    next_time += period_s
                    stop.wait(max(0.0, next_time - time.monotonic()))
            except (OSError, ValueError) as error:
                self._log(f"NDI tracker lost ({error}); reconnecting")
            finally:
                self._set_status(connected=False)
                with contextlib.suppress(OSError, ValueError):
                    tracker.close()
