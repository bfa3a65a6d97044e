"""The corrected image's 16-bit fixed point (endo_io.image.encode_irradiance and its inverse)."""

from __future__ import annotations

import numpy as np
import pytest

from endo_io.errors import ImageEncodingError, ImageLayoutError
from endo_io.image import (
    IRRADIANCE_MAX,
    IRRADIANCE_NAN_COUNT,
    IRRADIANCE_PER_COUNT,
    array_to_image,
    array_to_image_cdr,
    decode_irradiance,
    encode_irradiance,
    image_from_cdr,
    image_to_irradiance,
)


def _irradiance(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, IRRADIANCE_MAX, size=(48, 64)).astype(np.float32)


def test_round_trip_is_within_half_a_count_over_the_whole_range() -> None:
    irradiance = _irradiance()
    irradiance[0, :5] = [0.0, IRRADIANCE_MAX, 0.5 * IRRADIANCE_PER_COUNT, 1.0, 6.5]
    encoded = encode_irradiance(irradiance)
    assert encoded.encoding == "16UC1" and encoded.pixels.dtype == np.uint16
    assert encoded.saturated == encoded.negative == 0
    decoded = decode_irradiance(encoded.pixels, "16UC1")
    assert decoded.dtype == np.float32 and decoded.shape == irradiance.shape
    error = np.abs(decoded.astype(np.float64) - irradiance)
    assert error.max() <= 0.5 * IRRADIANCE_PER_COUNT + 1e-6
    # 1 irradiance unit is 10000 counts exactly; the top of the range is 65534
    assert encoded.pixels[0, 3] == 10000 and encoded.pixels[0, 1] == 65534
    # decoded counts encode back to themselves (endo-process re-encodes what it solved)
    counts = np.arange(0, 65535, dtype=np.uint16).reshape(1, -1)  # every code but NaN
    assert np.array_equal(encode_irradiance(decode_irradiance(counts, "16UC1")).pixels, counts)


def test_nan_is_the_reserved_code_and_comes_back_nan() -> None:
    irradiance = _irradiance(1)
    irradiance[3:7, 10:20] = np.nan
    encoded = encode_irradiance(irradiance)
    assert np.array_equal(encoded.pixels == IRRADIANCE_NAN_COUNT, np.isnan(irradiance))
    decoded = decode_irradiance(encoded.pixels, "16UC1")
    assert np.array_equal(np.isnan(decoded), np.isnan(irradiance))
    assert encoded.saturated == 0


def test_values_out_of_range_saturate_and_are_counted() -> None:
    irradiance = np.array([[7.0, np.inf, 6.5534, 6.5536, -0.2, -np.inf, 2.0, 6.55341, -1e-5]],
                          np.float32)
    encoded = encode_irradiance(irradiance)
    assert encoded.pixels.tolist() == [[65534, 65534, 65534, 65534, 0, 0, 20000, 65534, 0]]
    # 7, inf, 6.5536 (1.5 counts above the top); -0.2, -inf. Not 6.55341 nor -1e-5:
    # rounding puts them on 65534 and 0 anyway (within half a count)
    assert (encoded.saturated, encoded.negative) == (3, 2)
    decoded = decode_irradiance(encoded.pixels, "16UC1")
    assert decoded[0, 0] == pytest.approx(IRRADIANCE_MAX) and decoded[0, 4] == 0.0


def test_float_passes_unchanged() -> None:
    irradiance = _irradiance(2)
    irradiance[0, 0] = np.nan
    encoded = encode_irradiance(irradiance, "32FC1")
    assert encoded.pixels is irradiance and encoded.saturated == 0
    assert decode_irradiance(irradiance, "32FC1") is irradiance


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_image_to_irradiance_reads_both_encodings_of_a_message(encoding: str) -> None:
    irradiance = _irradiance(3)
    irradiance[5, 5] = np.nan
    encoded = encode_irradiance(irradiance, encoding)
    for msg in (array_to_image(encoded.pixels, encoding, 7, "cam"),
                image_from_cdr(array_to_image_cdr(encoded.pixels, encoding, 7, "cam"))):
        got = image_to_irradiance(msg)
        assert got.dtype == np.float32 and got.flags.writeable and got.flags.c_contiguous
        np.testing.assert_allclose(got, irradiance, atol=0.5 * IRRADIANCE_PER_COUNT + 1e-6)
        assert np.isnan(got[5, 5])


def test_bad_input_is_refused_with_one_line() -> None:
    with pytest.raises(ImageEncodingError, match=r"16UC1 .* or 32FC1"):
        encode_irradiance(_irradiance(), "mono8")
    with pytest.raises(ImageLayoutError, match=r"\(H, W\)"):
        encode_irradiance(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ImageEncodingError, match="needs dtype uint16"):
        decode_irradiance(np.zeros((4, 4), np.float32), "16UC1")
    with pytest.raises(ImageEncodingError, match="got 'mono8'"):
        image_to_irradiance(array_to_image(np.zeros((4, 4), np.uint8), "mono8"))
