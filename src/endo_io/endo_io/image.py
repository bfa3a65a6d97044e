"""Conversions between ``sensor_msgs/Image`` and numpy arrays.

Supported encodings and the arrays they map to:

============  ==========  =========  ========================
encoding      dtype       channels   array shape
============  ==========  =========  ========================
``mono8``     uint8       1          (H, W)
``mono16``    uint16      1          (H, W)
``16UC1``     uint16      1          (H, W)
``32FC1``     float32     1          (H, W)  REP 118 depth, metres
``32FC3``     float32     3          (H, W, 3)  colour irradiance, normals
``rgb8``      uint8       3          (H, W, 3)
``bgr8``      uint8       3          (H, W, 3)
``rgba8``     uint8       4          (H, W, 4)
``bgra8``     uint8       4          (H, W, 4)
============  ==========  =========  ========================

Channel order is kept as the encoding names it (a ``bgr8`` image gives a
B,G,R array, as OpenCV expects); nothing is reordered here.

Rows may be padded (``step > width * bytes_per_pixel``); multi-byte data may
be big-endian (``is_bigendian = 1``). The returned array is always C-contiguous
in native byte order. When the message is already packed and native it is a
zero-copy view of ``msg.data`` (as cv_bridge does), otherwise a copy.

A node that takes its images raw (serialized CDR bytes, as
:meth:`endo_io.diagnostics.InputHealth.subscribe` does) decodes them with
:func:`image_from_cdr` into an :class:`ImageView`: the message's fields, its
``data`` a view of the received bytes. rclpy's own deserialisation copies the
1.2 MB of a 640x480 32FC1 frame into an ``array.array`` on top of the bytes
it was given; at 30 images/s those copies, of differing lifetimes, fragment
the main thread's heap (the live flow node's RSS sawtooth in the soak,
docs/benchmarks.md). :func:`image_to_array` takes either.

The corrected image (``/endoscope/image_corrected``, linear irradiance) travels
as ``16UC1`` fixed point by default, half the bytes of ``32FC1`` (one 640x480
hop: 6.5-7.4 ms p50 against 12-22 ms, docs/benchmarks.md) and no measurable
change of the SFS result: count ``u`` means irradiance
``u * IRRADIANCE_PER_COUNT`` (1e-4 per count, 0 ... 6.5534), ``65535`` is NaN.
:func:`encode_irradiance` and :func:`image_to_irradiance` are the codec; every
reader of the corrected image takes either encoding by the message's
``encoding`` field.
"""

from __future__ import annotations

import struct
import sys
from array import array as byte_array
from dataclasses import dataclass
from typing import Final, TypeAlias

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from endo_io.cdr import CdrReader, cdr_string, decode_plain_cdr, header_cdr
from endo_io.errors import ImageEncodingError, ImageLayoutError
from endo_io.stamp import ns_to_stamp


@dataclass(frozen=True)
class PixelFormat:
    """Element type and channel count of one image encoding."""

    dtype: np.dtype
    channels: int

    @property
    def bytes_per_pixel(self) -> int:
        """Bytes one pixel occupies in ``Image.data``."""
        return self.dtype.itemsize * self.channels


PIXEL_FORMATS: dict[str, PixelFormat] = {
    "mono8": PixelFormat(np.dtype(np.uint8), 1),
    "mono16": PixelFormat(np.dtype(np.uint16), 1),
    "16UC1": PixelFormat(np.dtype(np.uint16), 1),
    "32FC1": PixelFormat(np.dtype(np.float32), 1),
    "32FC3": PixelFormat(np.dtype(np.float32), 3),
    "rgb8": PixelFormat(np.dtype(np.uint8), 3),
    "bgr8": PixelFormat(np.dtype(np.uint8), 3),
    "rgba8": PixelFormat(np.dtype(np.uint8), 4),
    "bgra8": PixelFormat(np.dtype(np.uint8), 4),
}

#: Encodings that :func:`image_to_array` and :func:`array_to_image` handle.
SUPPORTED_ENCODINGS: frozenset[str] = frozenset(PIXEL_FORMATS)

_NATIVE_IS_BIGENDIAN = sys.byteorder == "big"


def pixel_format(encoding: str) -> PixelFormat:
    """Return the element dtype and channel count of ``encoding``.

    Raises :class:`ImageEncodingError` if the encoding is not supported.
    """
    try:
        return PIXEL_FORMATS[encoding]
    except KeyError:
        raise ImageEncodingError(
            f"unsupported image encoding {encoding!r}; supported: "
            f"{', '.join(sorted(SUPPORTED_ENCODINGS))}"
        ) from None


@dataclass(frozen=True)
class ImageView:
    """A ``sensor_msgs/Image`` decoded from its CDR bytes, ``data`` a view of them.

    The fields are the message's, with the same names and meanings, so a
    node reads ``header.stamp``, ``encoding``, ... as from an ``Image``;
    :func:`image_to_array` takes it. ``data`` is read-only (a view of the
    immutable bytes rclpy delivers); :func:`image_to_array` returns a
    writeable copy of its pixels. It keeps the whole serialized message
    alive.
    """

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview


#: What a node receives as an image: decoded by :func:`image_from_cdr`, or a message
#: (a test's, an offline driver's).
ImageMessage: TypeAlias = Image | ImageView


def image_from_cdr(data: bytes) -> ImageMessage:
    """Decode a serialized ``sensor_msgs/Image`` without copying its pixels.

    Reads the fields as rclpy's ``deserialize_message(data, Image)`` does
    (the same values, strings cut at a NUL and invalid UTF-8 replaced as
    rclpy does; tested against it), but ``data`` of the result is a view of
    ``data``: no copy of the pixels. Bytes after the pixel data (CDR
    padding) are ignored, as rclpy ignores them. The image's layout (encoding,
    step, size) is not checked here but by :func:`image_to_array`, as for a
    deserialized message. A message in another encapsulation than plain CDR
    (XCDR2, parameter lists: no endo3d or ROS 2 publisher sends them for
    Image) is given to rclpy, which returns an ``Image``.

    Args:
        data: the serialized message, its 4-byte encapsulation header first.

    Returns:
        An :class:`ImageView` (an ``Image`` in the rare case above).

    Raises:
        UndecodableMessageError: the bytes end before a field does (a
            declared string or data length longer than what is left
            included: refused before anything is allocated), or they do not
            decode as an Image (other encapsulations, through rclpy).
    """
    return decode_plain_cdr(data, Image, _read_image)


def _read_image(cdr: CdrReader) -> ImageView:
    header = cdr.header()
    height = cdr.uint32("height")
    width = cdr.uint32("width")
    encoding = cdr.string("encoding")
    is_bigendian = cdr.uint8("is_bigendian")
    step = cdr.uint32("step")
    return ImageView(header, height, width, encoding, is_bigendian, step, cdr.octets("data"))


def image_to_array(msg: ImageMessage) -> np.ndarray:
    """Return the pixels of a ``sensor_msgs/Image`` as a numpy array.

    Returns an array of shape (H, W) for single-channel encodings or
    (H, W, C) for colour ones, with dtype uint8, uint16 or float32 (see the
    module table), C-contiguous and in native byte order. Units are those of
    the encoding (``32FC1`` depth is metres by REP 118). The array may share
    memory with ``msg.data`` when no copy is needed and ``msg.data`` is
    writeable; it is always writeable (an :class:`ImageView`'s pixels are
    copied once: numba compiles kernels per signature, read-only being one).

    Raises:
        ImageEncodingError: the encoding is not one of ``SUPPORTED_ENCODINGS``.
        ImageLayoutError: zero width or height, a step shorter than one row
            of pixels, or a data length other than ``step * height``.
    """
    fmt = pixel_format(msg.encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * fmt.bytes_per_pixel
    if height == 0 or width == 0:
        raise ImageLayoutError(f"{msg.encoding} image has zero size {width}x{height}")
    if step < row_bytes:
        raise ImageLayoutError(
            f"{msg.encoding} image step {step} < width {width} x "
            f"{fmt.bytes_per_pixel} bytes per pixel = {row_bytes}"
        )
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if raw.size != step * height:
        kind = "truncated" if raw.size < step * height else "oversized"
        raise ImageLayoutError(
            f"{msg.encoding} image data {kind}: {raw.size} bytes, expected step {step} x "
            f"height {height} = {step * height}"
        )

    stored_dtype = fmt.dtype
    if fmt.dtype.itemsize > 1:
        stored_dtype = fmt.dtype.newbyteorder(">" if msg.is_bigendian else "<")
    # Each row is contiguous, so a byte view of the used part of every row can
    # be reinterpreted as the element type even when rows are padded.
    rows = raw.reshape(height, step)[:, :row_bytes].view(stored_dtype)
    shape = (height, width) if fmt.channels == 1 else (height, width, fmt.channels)
    pixels = rows.reshape(shape)
    if not stored_dtype.isnative:
        return pixels.astype(fmt.dtype)  # byte-swapping copy, C-contiguous
    pixels = np.ascontiguousarray(pixels)
    if not pixels.flags.writeable:
        # A view of received bytes (an ImageView's) is read-only, and numba takes a
        # read-only array for another type: every kernel the nodes warm up on
        # writeable frames compiled again at a node's first real frame (a fresh
        # clone's demo: SFS stalled ~3 s and lost 33 frames). One copy of the
        # pixels (~0.1 ms for 1.2 MB) keeps the signatures the warm-ups load.
        pixels = pixels.copy()
    return pixels


def _packed_pixels(array: np.ndarray, encoding: str) -> tuple[np.ndarray, PixelFormat]:
    """``array`` checked against ``encoding`` and packed in native byte order (no copy if it is)."""
    fmt = pixel_format(encoding)
    pixels = np.asarray(array)
    if pixels.dtype.newbyteorder("=") != fmt.dtype.newbyteorder("="):
        raise ImageEncodingError(
            f"encoding {encoding} needs dtype {fmt.dtype.name}, got {pixels.dtype.name}"
        )
    if fmt.channels == 1 and pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[:, :, 0]
    expected_ndim = 2 if fmt.channels == 1 else 3
    if pixels.ndim != expected_ndim or (
        expected_ndim == 3 and pixels.shape[2] != fmt.channels
    ):
        wanted = "(H, W)" if fmt.channels == 1 else f"(H, W, {fmt.channels})"
        raise ImageLayoutError(
            f"encoding {encoding} needs an array of shape {wanted}, got {pixels.shape}"
        )
    height, width = pixels.shape[:2]
    if height == 0 or width == 0:
        raise ImageLayoutError(f"cannot publish a zero-size {width}x{height} image")
    return np.ascontiguousarray(pixels, dtype=fmt.dtype), fmt  # native order, packed rows


def array_to_image(
    array: np.ndarray, encoding: str, stamp_ns: int = 0, frame_id: str = ""
) -> Image:
    """Return a ``sensor_msgs/Image`` holding ``array`` with ``encoding``.

    Args:
        array: (H, W) for single-channel encodings ((H, W, 1) is accepted
            too) or (H, W, C) for colour ones; the dtype must be the
            encoding's (uint8, uint16 or float32, any byte order).
        encoding: one of ``SUPPORTED_ENCODINGS``.
        stamp_ns: header stamp, integer nanoseconds (>= 0).
        frame_id: header frame id, e.g. ``endoscope_optical_frame``.

    The message is packed (``step = W * bytes_per_pixel``) in native byte
    order, with ``is_bigendian`` set accordingly.

    Raises:
        ImageEncodingError: unsupported encoding, or a dtype that does not
            match it.
        ImageLayoutError: a shape that does not match the encoding, or a
            zero-sized array.
    """
    packed, fmt = _packed_pixels(array, encoding)
    height, width = packed.shape[:2]
    msg = Image()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height = height
    msg.width = width
    msg.encoding = encoding
    msg.is_bigendian = int(_NATIVE_IS_BIGENDIAN)
    msg.step = width * fmt.bytes_per_pixel
    # array.array is the type rclpy stores uint8[] in; building it from bytes
    # is one memcpy, whereas assigning any other sequence is checked per byte.
    msg.data = byte_array("B", packed.tobytes())
    return msg


def array_to_image_cdr(
    array: np.ndarray, encoding: str, stamp_ns: int = 0, frame_id: str = ""
) -> bytes:
    """The CDR bytes of ``array_to_image(array, encoding, stamp_ns, frame_id)``, built directly.

    Byte for byte what :func:`endo_io.bag.serde.serialize` gives for that
    message (little-endian CDR, every padding byte zero, padded to 4 bytes as
    DDS delivers it; tested), in one copy of the pixels instead of the five
    that building the message and serialising it take: writing a 640x480
    32FC1 image this way costs about a tenth (bench/bench_process.py).
    Arguments and errors as :func:`array_to_image`.
    """
    packed, fmt = _packed_pixels(array, encoding)
    height, width = packed.shape[:2]
    head = header_cdr(stamp_ns, frame_id)
    head += bytes(-(len(head) - 4) % 4)
    head += struct.pack("<II", height, width)
    head += cdr_string(encoding)
    head += struct.pack("<B", int(_NATIVE_IS_BIGENDIAN))
    head += bytes(-(len(head) - 4) % 4)
    head += struct.pack("<II", width * fmt.bytes_per_pixel, packed.nbytes)
    tail = bytes(-(len(head) + packed.nbytes) % 4)
    return b"".join((head, packed.data.cast("B"), tail))


def irradiance_to_mono8(
    irradiance: np.ndarray, *, white: float, gamma: float = 0.5
) -> np.ndarray:
    """Map linear irradiance (32FC1, NaN invalid) to 8-bit for feature tracking.

    ``255 · clip(E / white, 0, 1) ** gamma``, NaN and negative values to 0.
    A gamma below 1 spreads the dark far field, where 1/r² shading leaves
    little contrast, over more codes; the mapping is fixed for a given
    ``white``, so keeping ``white`` constant between frames keeps the
    brightness constancy that Lucas–Kanade assumes.

    Args:
        irradiance: (H, W) float linear irradiance, image units.
        white: irradiance mapped to 255 (> 0).
        gamma: exponent of the tone curve (> 0).

    Returns:
        (H, W) uint8, C-contiguous.
    """
    if not (white > 0.0 and np.isfinite(white)):
        raise ValueError(f"white must be positive and finite, got {white}")
    if not gamma > 0.0:
        raise ValueError(f"gamma must be positive, got {gamma}")
    data = np.asarray(irradiance, dtype=np.float32)
    if data.ndim != 2:
        raise ImageLayoutError(f"irradiance must be (H, W), got shape {data.shape}")
    with np.errstate(invalid="ignore"):
        level = np.nan_to_num(data * np.float32(1.0 / white), nan=0.0)
        np.clip(level, 0.0, 1.0, out=level)
    if gamma != 1.0:
        np.power(level, np.float32(gamma), out=level)
    return np.ascontiguousarray((level * np.float32(255.0) + np.float32(0.5)).astype(np.uint8))


#: Irradiance per count of the corrected image's 16-bit fixed point (``16UC1``).
IRRADIANCE_PER_COUNT: Final = 1e-4
#: The count reserved for NaN (saturated or outside the field of view) in ``16UC1``.
IRRADIANCE_NAN_COUNT: Final = 65535
#: The largest irradiance ``16UC1`` holds: 65534 counts = 6.5534; above it saturates.
IRRADIANCE_MAX: Final = (IRRADIANCE_NAN_COUNT - 1) * IRRADIANCE_PER_COUNT
#: Encodings of a single-channel corrected image: 16-bit fixed point (the default), float.
IRRADIANCE_ENCODINGS: Final = ("16UC1", "32FC1")

_COUNTS_PER_UNIT = np.float32(1.0 / IRRADIANCE_PER_COUNT)
_TOP_COUNT = np.float32(IRRADIANCE_NAN_COUNT - 1)


@dataclass(frozen=True)
class EncodedIrradiance:
    """A corrected image ready to publish, and what its encoding clipped.

    Attributes:
        pixels: (H, W) uint16 counts for ``16UC1``, float32 irradiance for
            ``32FC1`` (the input itself, no copy).
        encoding: ``16UC1`` or ``32FC1``.
        saturated: finite pixels above :data:`IRRADIANCE_MAX` (and +inf),
            stored as 65534; always 0 for ``32FC1``.
        negative: pixels below 0 (and -inf), stored as 0; always 0 for ``32FC1``.
    """

    pixels: np.ndarray
    encoding: str
    saturated: int = 0
    negative: int = 0


def _check_irradiance_encoding(encoding: str) -> None:
    if encoding not in IRRADIANCE_ENCODINGS:
        raise ImageEncodingError(
            f"a corrected image is 16UC1 (fixed point, {IRRADIANCE_PER_COUNT:g} per count) "
            f"or 32FC1 (linear irradiance), got {encoding!r}"
        )


def encode_irradiance(irradiance: np.ndarray, encoding: str = "16UC1") -> EncodedIrradiance:
    """Encode linear irradiance for ``/endoscope/image_corrected``.

    ``16UC1``: ``u = round(E / IRRADIANCE_PER_COUNT)`` (half up), NaN ->
    65535, E above :data:`IRRADIANCE_MAX` -> 65534 and E < 0 -> 0; counted
    as saturated or negative only where that moved E by more than half a
    count (6.55341 encodes to 65534 and -1e-5 to 0 as rounding would). The
    decoded value is within ``IRRADIANCE_PER_COUNT / 2`` (plus float32
    rounding, < 1e-6) of E for E in [0, IRRADIANCE_MAX]. ``32FC1``:
    the float32 irradiance as it is.

    Args:
        irradiance: (H, W) linear irradiance, image units (float; converted
            to float32), NaN invalid.
        encoding: one of :data:`IRRADIANCE_ENCODINGS`.

    Returns:
        The pixels to publish with their encoding and the clipped counts.

    Raises:
        ImageEncodingError: ``encoding`` is not 16UC1 or 32FC1.
        ImageLayoutError: ``irradiance`` is not (H, W).
    """
    _check_irradiance_encoding(encoding)
    data = np.asarray(irradiance, dtype=np.float32)
    if data.ndim != 2:
        raise ImageLayoutError(f"irradiance must be (H, W), got shape {data.shape}")
    if encoding == "32FC1":
        return EncodedIrradiance(data, encoding)
    with np.errstate(invalid="ignore", over="ignore"):
        scaled = data * _COUNTS_PER_UNIT  # NaN stays NaN; a fresh array
        # clipped beyond what rounding does anyway (half a count)
        saturated = int(np.count_nonzero(scaled >= _TOP_COUNT + np.float32(0.5)))
        negative = int(np.count_nonzero(scaled < np.float32(-0.5)))
        nan = np.isnan(scaled)
        np.clip(scaled, 0.0, _TOP_COUNT, out=scaled)
        scaled += np.float32(0.5)
        scaled[nan] = IRRADIANCE_NAN_COUNT
        counts = scaled.astype(np.uint16)
    return EncodedIrradiance(counts, encoding, saturated, negative)


def decode_irradiance(pixels: np.ndarray, encoding: str) -> np.ndarray:
    """Linear irradiance of a corrected image's pixels.

    Args:
        pixels: (H, W) uint16 counts (``16UC1``) or float32 irradiance
            (``32FC1``), as :func:`image_to_array` gives them.
        encoding: the message's encoding, one of :data:`IRRADIANCE_ENCODINGS`.

    Returns:
        (H, W) float32 irradiance, image units, NaN invalid: ``u *
        IRRADIANCE_PER_COUNT`` and NaN for 65535 (a new array), or the
        ``32FC1`` pixels themselves.

    Raises:
        ImageEncodingError: another encoding, or a dtype that does not match it.
        ImageLayoutError: ``pixels`` is not (H, W).
    """
    _check_irradiance_encoding(encoding)
    data = np.asarray(pixels)
    if data.ndim != 2:
        raise ImageLayoutError(f"a corrected image must be (H, W), got shape {data.shape}")
    wanted = PIXEL_FORMATS[encoding].dtype
    if data.dtype.newbyteorder("=") != wanted:
        raise ImageEncodingError(f"{encoding} needs dtype {wanted.name}, got {data.dtype.name}")
    if encoding == "32FC1":
        return data
    irradiance = data.astype(np.float32)
    irradiance *= np.float32(IRRADIANCE_PER_COUNT)
    irradiance[data == IRRADIANCE_NAN_COUNT] = np.nan
    return irradiance


def image_to_irradiance(msg: ImageMessage) -> np.ndarray:
    """The linear irradiance of a corrected image message, either encoding.

    Args:
        msg: a ``16UC1`` or ``32FC1`` image (message or :class:`ImageView`).

    Returns:
        (H, W) float32 irradiance, image units, NaN invalid, C-contiguous
        and writeable.

    Raises:
        ImageEncodingError: the encoding is neither 16UC1 nor 32FC1.
        ImageLayoutError: as :func:`image_to_array`.
    """
    _check_irradiance_encoding(msg.encoding)
    return decode_irradiance(image_to_array(msg), msg.encoding)
