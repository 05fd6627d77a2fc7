"""JPEG helpers (libjpeg-turbo through OpenCV). Images are RGB uint8 ``(H, W, 3)``.

Decoding reads the image size from the JPEG header first, so a tiny hostile file that claims a huge
image is refused before any pixel memory is allocated.
"""

from __future__ import annotations

import cv2
import numpy as np

MAX_JPEG_BYTES = 32 * 1024 * 1024
MAX_PIXELS = 40_000_000
"""Largest image (width x height) decode_jpeg accepts."""
# Start-of-frame markers (baseline, progressive, ...); C4, C8 and CC are other segments.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


class JpegError(ValueError):
    """A corrupt, empty or unsupported JPEG (or image)."""


def encode_jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    """Encode an RGB uint8 image. Raises :class:`JpegError` for a wrong shape or dtype."""
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise JpegError(f"expected an (H, W, 3) uint8 image, got {getattr(rgb, 'shape', None)}")
    if rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise JpegError("empty image")
    if not 1 <= quality <= 100:
        raise JpegError(f"quality must be in 1..100, got {quality}")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise JpegError("JPEG encoding failed")
    return buf.tobytes()


def jpeg_size(data: bytes | bytearray | memoryview) -> tuple[int, int]:
    """``(width, height)`` from the JPEG's start-of-frame header, without decoding pixels."""
    b = bytes(data)
    if len(b) < 4 or b[0] != 0xFF or b[1] != 0xD8:
        raise JpegError("not a JPEG (missing SOI marker)")
    i = 2
    while i + 4 <= len(b):
        if b[i] != 0xFF:
            raise JpegError("corrupt JPEG marker stream")
        marker = b[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        seg_len = (b[i + 2] << 8) | b[i + 3]
        if seg_len < 2:
            raise JpegError("corrupt JPEG segment length")
        if marker in _SOF_MARKERS:
            if i + 9 > len(b):
                break
            height = (b[i + 5] << 8) | b[i + 6]
            width = (b[i + 7] << 8) | b[i + 8]
            if width == 0 or height == 0:
                raise JpegError("JPEG header has a zero image size")
            return width, height
        if marker == 0xDA:  # start of scan before any frame header
            break
        i += 2 + seg_len
    raise JpegError("JPEG has no frame header")


def decode_jpeg(
    data: bytes | bytearray | memoryview,
    expected_size: tuple[int, int] | None = None,
    max_pixels: int = MAX_PIXELS,
) -> np.ndarray:
    """Decode JPEG bytes into RGB uint8. Raises :class:`JpegError` on corrupt or empty data.

    ``expected_size`` ``(width, height)``: refuse, before decoding, a JPEG of another size (for
    example one that disagrees with its frame header). Images over ``max_pixels`` are refused too.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < 4:
        raise JpegError("empty or missing JPEG data")
    if len(data) > MAX_JPEG_BYTES:
        raise JpegError(f"JPEG of {len(data)} bytes exceeds {MAX_JPEG_BYTES}")
    width, height = jpeg_size(data)
    if expected_size is not None and (width, height) != tuple(expected_size):
        raise JpegError(f"JPEG is {width}x{height}, expected {expected_size[0]}x{expected_size[1]}")
    if width * height > max_pixels:
        raise JpegError(f"JPEG of {width}x{height} exceeds {max_pixels} pixels")
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    if b"\xff\xd9" not in bytes(buf[-64:]):
        raise JpegError("truncated JPEG (missing EOI marker)")
    try:
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    except cv2.error as e:
        raise JpegError(f"corrupt JPEG: {e.msg if hasattr(e, 'msg') else e}") from None
    if bgr is None or bgr.ndim != 3:
        raise JpegError("corrupt JPEG")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
