"""Source ``igtl``: an OpenIGTLink client for TRANSFORM messages (PLUS, 3D Slicer).

Protocol (OpenIGTLink v1/v2 header, big-endian, 58 bytes): version (u16),
type (12 chars), device name (20 chars), timestamp (u32 seconds + u32
fraction of a second in units of 2⁻³²), body size (u64), CRC-64 of the body
(u64). A TRANSFORM body holds the upper 3x4 of a homogeneous matrix, column by
column, as float32; PLUS and Slicer send millimetres.

Message decoding is pyigtl's (``MessageBase.parse_header``,
``TransformMessage.unpack``, its CRC-64). The connection is managed here
rather than with ``pyigtl.OpenIGTLinkClient``: pyigtl 0.3.4's client treats a
closed socket (``recv`` returning no bytes) like "no data yet" and never
reconnects, while the bridge must survive the server going away and coming
back (a PLUS restart) without restarting the node. This client reconnects
when the peer closes, on any socket error, and when TCP keep-alive finds the
peer gone without closing (a crashed host, a pulled cable: about 5 s).
``stale_timeout_s`` > 0 also reconnects after that long without data; it is
off by default because 3D Slicer sends a TRANSFORM only when it changes.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pyigtl.messages import CRC64, MessageBase, TransformMessage

from endo_tracker_bridge.conventions import LengthUnit, transform_from_matrix
from endo_tracker_bridge.errors import IgtlMessageError, TrackerSourceError
from endo_tracker_bridge.sample import TrackerSample
from endo_tracker_bridge.sources.background import BackgroundSource
from endo_tracker_bridge.validation import DEFAULT_ROTATION_TOLERANCE

HEADER_SIZE = MessageBase.IGTL_HEADER_SIZE
_HEADER = struct.Struct("> H 12s 20s I I Q Q")
#: Largest body accepted; a TRANSFORM body is 48 bytes (+ v2 extended header
#: and metadata), so anything near this is a corrupt stream, not a message.
MAX_BODY_BYTES = 64 << 20


class ConnectionLostError(OSError):
    """The OpenIGTLink peer closed the connection or stopped sending."""


@dataclass(frozen=True)
class IgtlFrame:
    """One received OpenIGTLink message, not yet decoded.

    ``header`` is pyigtl's parsed header dict (``message_type``,
    ``device_name``, ``header_version``, ``timestamp``, ``body_size``);
    ``stamp_ns`` is the header timestamp as exact integer nanoseconds;
    ``crc`` is the CRC-64 the sender wrote; ``receive_ns`` is this host's
    ``time.time_ns()`` when the body had fully arrived.
    """

    header: dict[str, Any]
    body: bytes
    stamp_ns: int
    crc: int
    receive_ns: int


def parse_header(raw: bytes) -> tuple[dict[str, Any], int, int]:
    """Parse a 58-byte header → (pyigtl header fields, stamp in ns, CRC-64)."""
    if len(raw) != HEADER_SIZE:
        raise IgtlMessageError(f"header has {len(raw)} bytes, expected {HEADER_SIZE}")
    try:
        fields = MessageBase.parse_header(raw)
    except (struct.error, UnicodeDecodeError) as error:
        raise IgtlMessageError(f"header cannot be decoded: {error}") from None
    _, _, _, seconds, fraction, _, crc = _HEADER.unpack(raw)
    stamp_ns = seconds * 1_000_000_000 + round(fraction * 1e9 / 2**32)
    return fields, stamp_ns, crc


def sample_from_igtl_frame(
    frame: IgtlFrame,
    unit: LengthUnit = LengthUnit.MILLIMETRE,
    stamp_from: str = "message",
    tolerance: float = DEFAULT_ROTATION_TOLERANCE,
) -> TrackerSample:
    """Decode a TRANSFORM frame into a sample in metres.

    ``stamp_from`` is ``"message"`` (the sender's header timestamp, what PLUS
    sets to the acquisition time) or ``"receive"`` (this host's clock on
    arrival, for senders that leave the timestamp at zero).
    Raises IgtlMessageError (wrong type, CRC mismatch, bad body),
    NonFinitePoseError or NonOrthonormalRotationError.
    """
    message_type = frame.header.get("message_type", "")
    device = frame.header.get("device_name", "")
    if message_type != "TRANSFORM":
        raise IgtlMessageError(f"message '{device}' is {message_type}, not TRANSFORM")
    if CRC64(frame.body) != frame.crc:
        raise IgtlMessageError(f"CRC-64 mismatch in TRANSFORM '{device}'")
    message = TransformMessage()
    try:
        message.unpack(frame.header, frame.body)
    except (struct.error, ValueError, UnicodeDecodeError) as error:
        raise IgtlMessageError(f"TRANSFORM '{device}' body cannot be decoded: {error}") from None
    T = transform_from_matrix(message.matrix, unit, tolerance)
    if stamp_from == "message":
        stamp_ns = frame.stamp_ns
    elif stamp_from == "receive":
        stamp_ns = frame.receive_ns
    else:
        raise TrackerSourceError(f"unknown OpenIGTLink stamp source '{stamp_from}'")
    return TrackerSample(stamp_ns=stamp_ns, T_tracker_marker=T, tool_id=device)


class IgtlSource(BackgroundSource):
    """OpenIGTLink client that queues the TRANSFORM frames of one device.

    Frames of other devices and other message types are skipped (a PLUS
    server streams every tool it tracks); they are counted in
    :meth:`status` as ``ignored_messages``.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 18944,
        device_name: str = "",
        unit: LengthUnit = LengthUnit.MILLIMETRE,
        stamp_from: str = "message",
        tolerance: float = DEFAULT_ROTATION_TOLERANCE,
        reconnect_interval_s: float = 0.5,
        stale_timeout_s: float = 0.0,
        log: Callable[[str], None] | None = None,
    ) -> None:
        super().__init__(log)
        if stamp_from not in ("message", "receive"):
            raise TrackerSourceError(f"unknown OpenIGTLink stamp source '{stamp_from}'")
        self.host, self.port, self.device_name = host, int(port), device_name
        self.unit, self.stamp_from, self.tolerance = unit, stamp_from, tolerance
        self.reconnect_interval_s = reconnect_interval_s
        self.stale_timeout_s = stale_timeout_s
        self.connections = 0
        self.ignored = 0
        self._junk = False
        self._set_status(connected=False, connections=0, server=f"{host}:{port}")

    def to_sample(self, item: IgtlFrame) -> TrackerSample:
        """Decode one queued frame (see :func:`sample_from_igtl_frame`)."""
        return sample_from_igtl_frame(item, self.unit, self.stamp_from, self.tolerance)

    def _run(self, stop: threading.Event) -> None:
        waiting_logged = False
        while not stop.is_set():
            try:
                connection = socket.create_connection((self.host, self.port), timeout=1.0)
            except OSError as error:
                if not waiting_logged:
                    self._log(
                        f"OpenIGTLink server {self.host}:{self.port} not reachable "
                        f"({error}); retrying"
                    )
                    waiting_logged = True
                stop.wait(self.reconnect_interval_s)
                continue
            waiting_logged = False
            self.connections += 1
            self._set_status(connected=True, connections=self.connections)
            # After a junk stream the next connection is likely junk too: its
            # lines are throttled until a good TRANSFORM arrives.
            text = f"connected to OpenIGTLink server {self.host}:{self.port}"
            if self._junk:
                self._log_throttled("connected", text)
            else:
                self._log(text)
            try:
                connection.settimeout(0.1)
                _enable_keepalive(connection)
                self._receive(connection, stop)
            except IgtlMessageError as error:
                self._junk = True
                self._log_throttled(
                    "junk",
                    f"OpenIGTLink stream from {self.host}:{self.port} is not OpenIGTLink "
                    f"({error}); reconnecting",
                )
            except OSError as error:
                self._junk = False
                self._log(
                    f"OpenIGTLink connection to {self.host}:{self.port} lost: {error}; reconnecting"
                )
            finally:
                connection.close()
                self._set_status(connected=False)
            stop.wait(self.reconnect_interval_s)

    def _receive(self, connection: socket.socket, stop: threading.Event) -> None:
        while not stop.is_set():
            raw = self._read_exactly(connection, HEADER_SIZE, stop)
            if raw is None:
                return
            header, stamp_ns, crc = parse_header(raw)
            if header["body_size"] > MAX_BODY_BYTES:
                raise IgtlMessageError(f"body size {header['body_size']} bytes: corrupt stream")
            body = self._read_exactly(connection, header["body_size"], stop)
            if body is None:
                return
            wanted_device = not self.device_name or header["device_name"] == self.device_name
            if header["message_type"] != "TRANSFORM" or not wanted_device:
                self.ignored += 1
                self._set_status(ignored_messages=self.ignored)
                continue
            self._junk = False
            self._emit(IgtlFrame(header, body, stamp_ns, crc, time.time_ns()))

    def _read_exactly(
        self, connection: socket.socket, size: int, stop: threading.Event
    ) -> bytes | None:
        """Read ``size`` bytes; None if ``stop`` was set; ConnectionLostError on EOF/silence."""
        chunks: list[bytes] = []
        remaining = size
        last_data = time.monotonic()
        while remaining > 0:
            if stop.is_set():
                return None
            try:
                chunk = connection.recv(min(remaining, 1 << 16))
            except TimeoutError:
                if time.monotonic() - last_data > self.stale_timeout_s > 0:
                    raise ConnectionLostError(f"no data for {self.stale_timeout_s:g} s") from None
                continue
            if not chunk:
                raise ConnectionLostError("server closed the connection")
            chunks.append(chunk)
            remaining -= len(chunk)
            last_data = time.monotonic()
        return b"".join(chunks)


def _enable_keepalive(connection: socket.socket) -> None:
    """Probe an idle connection after 2 s, every 1 s, give up after 3 misses."""
    connection.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for name, value in (("TCP_KEEPIDLE", 2), ("TCP_KEEPINTVL", 1), ("TCP_KEEPCNT", 3)):
        if hasattr(socket, name):  # Linux names; other systems keep their defaults
            connection.setsockopt(socket.IPPROTO_TCP, getattr(socket, name), value)
