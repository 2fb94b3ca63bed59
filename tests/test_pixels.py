"""Monochrome pixel unpacking against byte layouts worked out by hand from PFNC / GigE Vision."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.pixels import MONO_FORMATS, expected_bytes, pack, unpack


def test_mono12p_two_pixels_in_three_bytes_lsb_first():
    # 0x123, 0x456 -> stream bits: byte0 = 0x23, byte1 = 0x1 | (0x6 << 4) = 0x61, byte2 = 0x45
    assert unpack(bytes([0x23, 0x61, 0x45]), "Mono12p", 2, 1).tolist() == [[0x123, 0x456]]


def test_mono12packed_gige_vision_layout():
    # 0x123, 0x456 -> byte0 = high 8 bits of p0 (0x12), byte1 = low nibbles (p0 0x3 | p1 0x6 << 4), byte2 = 0x45
    assert unpack(bytes([0x12, 0x63, 0x45]), "Mono12Packed", 2, 1).tolist() == [[0x123, 0x456]]


def test_mono10p_four_pixels_in_five_bytes():
    # 0x3FF, 0x000, 0x155, 0x2AA as a little-endian bit stream:
    # bits 0..9 = 0x3FF, 10..19 = 0, 20..29 = 0x155, 30..39 = 0x2AA
    value = 0x3FF | (0x000 << 10) | (0x155 << 20) | (0x2AA << 30)
    raw = value.to_bytes(5, "little")
    assert unpack(raw, "Mono10p", 4, 1).tolist() == [[0x3FF, 0x000, 0x155, 0x2AA]]


def test_mono10packed_gige_vision_layout():
    # 0x3FE, 0x201: byte0 = 0x3FE >> 2 = 0xFF, byte1 = (0x3FE & 3) | ((0x201 & 3) << 4) = 0x12, byte2 = 0x80
    assert unpack(bytes([0xFF, 0x12, 0x80]), "Mono10Packed", 2, 1).tolist() == [[0x3FE, 0x201]]


def test_mono16_and_lsb_aligned_formats_are_little_endian_words():
    raw = bytes([0x34, 0x12, 0xFF, 0xFF])
    assert unpack(raw, "Mono16", 2, 1).tolist() == [[0x1234, 0xFFFF]]
    assert unpack(raw, "Mono12", 2, 1).tolist() == [[0x234, 0xFFF]]  # bits above 12 are not pixel data


@pytest.mark.parametrize("fmt", MONO_FORMATS)
def test_round_trip_of_a_random_image_and_sizes(fmt):
    rng = np.random.default_rng(3)
    from drivers.pixels import bit_depth

    img = rng.integers(0, 1 << bit_depth(fmt), size=(7, 13), dtype=np.uint16)
    raw = pack(img, fmt)
    assert len(raw) == expected_bytes(fmt, 13, 7)
    out = unpack(raw, fmt, 13, 7)
    assert out.dtype == (np.uint8 if fmt == "Mono8" else np.uint16)
    np.testing.assert_array_equal(out, img)


def test_truncated_buffer_is_refused_not_padded():
    with pytest.raises(ValueError, match="needs 6 bytes, the buffer holds 5"):
        unpack(bytes(5), "Mono12p", 4, 1)
