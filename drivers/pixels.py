"""Monochrome GenICam pixel formats -> numpy images (pure functions, no device).

The layouts are those of the GenICam Pixel Format Naming Convention (PFNC 2.x) and of the
GigE Vision 1.x "Packed" formats:

- ``Mono8``: one byte per pixel.
- ``Mono10``, ``Mono12``, ``Mono14``, ``Mono16``: one little-endian 16-bit word per pixel, the
  value in the low bits (unpacked, "LSB aligned").
- ``Mono10p``, ``Mono12p`` (PFNC "packed"): the pixels as one little-endian bit stream, no
  padding: pixel *k* occupies bits ``k*b .. k*b+b-1`` (4 pixels in 5 bytes for 10 bit, 2 in 3
  for 12 bit).
- ``Mono10Packed``, ``Mono12Packed`` (GigE Vision): 2 pixels in 3 bytes; byte 0 holds the high
  bits of pixel 0, byte 2 those of pixel 1, byte 1 the low bits of both (pixel 0 in bits 0..3,
  pixel 1 in bits 4..7; for 10 bit only bits 0..1 and 4..5 are used).

Every function returns ``(height, width)`` uint8 (Mono8) or uint16 with the sensor's value
(not scaled): a 12-bit pixel reads 0..4095. ``bit_depth(fmt)`` tells how many bits are meaningful.
"""
from __future__ import annotations

import numpy as np

BIT_DEPTH = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16,
             "Mono10p": 10, "Mono12p": 12, "Mono10Packed": 10, "Mono12Packed": 12}
MONO_FORMATS = tuple(BIT_DEPTH)


class PixelFormatUnsupported(ValueError):
    """The format is not one of the monochrome formats this module unpacks."""


class ShortBufferError(ValueError):
    """The buffer holds less than one image of its format and size (a truncated frame is never padded)."""

    def __init__(self, message: str, have: int = 0, need: int = 0, unit: str = "bytes"):
        super().__init__(message)
        self.have, self.need, self.unit = have, need, unit


def bit_depth(fmt: str) -> int:
    try:
        return BIT_DEPTH[fmt]
    except KeyError:
        raise PixelFormatUnsupported(f"pixel format {fmt!r} is not one of {', '.join(MONO_FORMATS)}") from None


def expected_bytes(fmt: str, width: int, height: int) -> int:
    """Bytes of one ``width x height`` image in ``fmt`` (packed lines are not padded)."""
    n = int(width) * int(height)
    if fmt == "Mono8":
        return n
    if fmt in ("Mono10", "Mono12", "Mono14", "Mono16"):
        return 2 * n
    if fmt in ("Mono10p", "Mono12p"):
        return (n * bit_depth(fmt) + 7) // 8
    if fmt in ("Mono10Packed", "Mono12Packed"):
        return 3 * ((n + 1) // 2)
    raise PixelFormatUnsupported(f"pixel format {fmt!r} is not one of {', '.join(MONO_FORMATS)}")


def unpack(raw: np.ndarray | bytes, fmt: str, width: int, height: int) -> np.ndarray:
    """The image in ``raw`` (the buffer's bytes, at least :func:`expected_bytes`) as ``(height, width)``.

    Raises ``ValueError`` when ``raw`` is shorter than one image in that format (a truncated
    buffer is never padded into a picture).
    """
    data = np.frombuffer(raw, dtype=np.uint8) if isinstance(raw, (bytes, bytearray, memoryview)) \
        else np.ascontiguousarray(raw).view(np.uint8).ravel()
    need = expected_bytes(fmt, width, height)
    if data.size < need:
        raise ShortBufferError(f"{fmt} {width}x{height} needs {need} bytes, the buffer holds {data.size}",
                               int(data.size), need, "bytes")
    data = data[:need]
    n = int(width) * int(height)
    if fmt == "Mono8":
        out = data.copy()
    elif fmt in ("Mono10", "Mono12", "Mono14", "Mono16"):
        out = data.view("<u2").astype(np.uint16)
        if fmt != "Mono16":
            out &= np.uint16((1 << bit_depth(fmt)) - 1)
    elif fmt == "Mono12p":
        out = _unpack12p(data, n)
    elif fmt == "Mono10p":
        out = _unpack10p(data, n)
    else:  # GigE Vision Mono10Packed / Mono12Packed
        out = _unpack_gev_packed(data, n, bit_depth(fmt))
    return out.reshape(int(height), int(width))


def from_component(data: np.ndarray, fmt: str, width: int, height: int) -> np.ndarray:
    """The image of a harvesters image component's ``data``, as ``(height, width)`` with the sensor's values.

    harvesters (1.4.x, ``Component2DImage``) hands ``data`` already through the pixel format's own ``expand``: one
    uint16 per pixel for Mono10..16 *and* for the packed formats (Mono10p/12p, Mono10Packed/12Packed), one uint8 per
    pixel for Mono8. Its dtype says which it is: uint16 -> pixel values (taken as they are, never unpacked again);
    uint8 -> the wire's bytes (Mono8, or a consumer that hands the raw buffer), unpacked by :func:`unpack`.
    Raises :class:`ShortBufferError` for fewer pixels (bytes) than one image and ``PixelFormatUnsupported`` for a
    dtype that fits neither (a Mono8 frame in 16-bit words, a float array ...).
    """
    arr = np.asarray(data)
    bits = bit_depth(fmt)
    if arr.dtype == np.uint8:
        return unpack(arr.ravel(), fmt, width, height)
    n = int(width) * int(height)
    if arr.dtype != np.uint16 or bits == 8:
        raise PixelFormatUnsupported(f"{fmt} {width}x{height}: the consumer handed {arr.dtype} data, neither the "
                                     "bytes of the frame (uint8) nor one 16-bit word per pixel")
    flat = arr.ravel()
    if flat.size < n:
        raise ShortBufferError(f"{fmt} {width}x{height} needs {n} pixels, the buffer holds {flat.size}",
                               int(flat.size), n, "pixels")
    out = flat[:n].astype(np.uint16)
    if bits < 16:
        if fmt in ("Mono10", "Mono12", "Mono14"):  # LSB-aligned words: the bits above are not pixel data (as unpack)
            out &= np.uint16((1 << bits) - 1)
        elif int(out.max(initial=0)) >= (1 << bits):  # an expanded packed format cannot exceed its depth
            raise PixelFormatUnsupported(f"{fmt} {width}x{height}: a pixel of {int(out.max())} exceeds {bits} bits; "
                                         "the frame is not in this format")
    return out.reshape(int(height), int(width))


def _unpack12p(data: np.ndarray, n: int) -> np.ndarray:
    pad = (-data.size) % 3
    b = np.concatenate([data, np.zeros(pad, np.uint8)]).reshape(-1, 3).astype(np.uint16)
    p0 = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
    p1 = (b[:, 1] >> 4) | (b[:, 2] << 4)
    return np.stack([p0, p1], axis=1).ravel()[:n]


def _unpack10p(data: np.ndarray, n: int) -> np.ndarray:
    pad = (-data.size) % 5
    b = np.concatenate([data, np.zeros(pad, np.uint8)]).reshape(-1, 5).astype(np.uint16)
    p0 = b[:, 0] | ((b[:, 1] & 0x03) << 8)
    p1 = (b[:, 1] >> 2) | ((b[:, 2] & 0x0F) << 6)
    p2 = (b[:, 2] >> 4) | ((b[:, 3] & 0x3F) << 4)
    p3 = (b[:, 3] >> 6) | (b[:, 4] << 2)
    return np.stack([p0, p1, p2, p3], axis=1).ravel()[:n]


def _unpack_gev_packed(data: np.ndarray, n: int, bits: int) -> np.ndarray:
    b = data.reshape(-1, 3).astype(np.uint16)
    low = bits - 8
    mask = (1 << low) - 1
    p0 = (b[:, 0] << low) | (b[:, 1] & mask)
    p1 = (b[:, 2] << low) | ((b[:, 1] >> 4) & mask)
    return np.stack([p0, p1], axis=1).ravel()[:n]


def pack(image: np.ndarray, fmt: str) -> bytes:
    """The inverse of :func:`unpack` (how a camera lays the pixels out); used by the emulators and tests."""
    v = np.asarray(image, dtype=np.uint16).ravel()
    bits = bit_depth(fmt)
    if int(v.max(initial=0)) >= (1 << bits):
        raise ValueError(f"{fmt}: a value exceeds {bits} bits")
    if fmt == "Mono8":
        return v.astype(np.uint8).tobytes()
    if fmt in ("Mono10", "Mono12", "Mono14", "Mono16"):
        return v.astype("<u2").tobytes()
    if fmt in ("Mono10p", "Mono12p"):
        # little-endian bit stream: bit j of pixel k is stream bit k*bits + j
        bitstream = ((v[:, None] >> np.arange(bits, dtype=np.uint16)) & 1).astype(np.uint8).ravel()
        return np.packbits(bitstream, bitorder="little").tobytes()
    low = bits - 8
    mask = (1 << low) - 1
    if v.size % 2:
        v = np.concatenate([v, [0]]).astype(np.uint16)
    p = v.reshape(-1, 2)
    b0 = p[:, 0] >> low
    b1 = (p[:, 0] & mask) | ((p[:, 1] & mask) << 4)
    b2 = p[:, 1] >> low
    return np.stack([b0, b1, b2], axis=1).astype(np.uint8).tobytes()
