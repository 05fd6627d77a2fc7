"""JPEG helpers (libjpeg-turbo through OpenCV). Images are RGB uint8 ``(H, W, 3)``.

Decoding reads the image size from the JPEG header first, so a tiny hostile file that claims a huge
image is refused before any pixel memory is allocated: :func:`jpeg_problem` runs every check that needs
no pixel (size against the expected one, a pixel cap, the coding process, and a floor on compressed bytes
per pixel) and :func:`decode_jpeg` runs it before decoding.

Compressed bytes per pixel: a Huffman-coded JPEG (baseline, extended or progressive: every camera and
encoder in use) spends at least one bit per 8x8 block of each component, so at least ~1953 bytes per
megapixel even for a flat grey image (measured: 5.9 KB/MP for a flat colour image with optimised tables).
A 600-byte file claiming 6000x6000 (36 MP) is therefore not a JPEG of that size; libjpeg would still
"decode" it (a warning, the missing data filled with grey), allocating 108 MB for nothing.
"""

from __future__ import annotations

import cv2
import numpy as np

MAX_JPEG_BYTES = 32 * 1024 * 1024
MAX_PIXELS = 40_000_000
"""Largest image (width x height) decode_jpeg accepts."""
MIN_BYTES_PER_MPIXEL_FLOOR = 1953.0
"""Fewest compressed bytes a Huffman-coded JPEG of one megapixel can have (1 bit per 8x8 block, one component)."""
# Start-of-frame markers (baseline, progressive, ...); C4, C8 and CC are other segments.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
HUFFMAN_SOF = frozenset({0xC0, 0xC1, 0xC2})
"""Baseline, extended sequential and progressive Huffman coding: what cameras and encoders produce. The
others (lossless, hierarchical, arithmetic coding) are refused by :func:`jpeg_problem` when asked to."""


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
    width, height, _ = jpeg_header(data)
    return width, height


def jpeg_header(data: bytes | bytearray | memoryview) -> tuple[int, int, int]:
    """``(width, height, sof_marker)`` from the JPEG's start-of-frame header (raises :class:`JpegError`)."""
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
            return width, height, marker
        if marker == 0xDA:  # start of scan before any frame header
            break
        i += 2 + seg_len
    raise JpegError("JPEG has no frame header")


def jpeg_problem(
    data: object,
    expected_size: tuple[int, int] | None = None,
    max_pixels: int = MAX_PIXELS,
    min_bytes_per_mpixel: float = 0.0,
    max_bytes: int = MAX_JPEG_BYTES,
) -> tuple[str, str] | None:
    """Why ``data`` must not be decoded, from its bytes and header alone, or None when it may be.

    Returns ``(reason, detail)``; ``reason`` is a counter name: ``jpeg_too_large`` (over ``max_bytes``
    or ``max_pixels``), ``jpeg_size_mismatch`` (not ``expected_size`` = ``(width, height)``),
    ``jpeg_implausible`` (fewer than ``min_bytes_per_mpixel`` compressed bytes per megapixel, or, when
    that is > 0, a coding process other than :data:`HUFFMAN_SOF`), ``jpeg_corrupt`` (no JPEG header).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < 4:
        return "jpeg_corrupt", "empty or missing JPEG data"
    if len(data) > max_bytes:
        return "jpeg_too_large", f"JPEG of {len(data)} bytes exceeds {max_bytes}"
    try:
        width, height, sof = jpeg_header(data)
    except JpegError as e:
        return "jpeg_corrupt", str(e)
    if expected_size is not None and (width, height) != tuple(expected_size):
        return "jpeg_size_mismatch", f"JPEG is {width}x{height}, expected {expected_size[0]}x{expected_size[1]}"
    if width * height > max_pixels:
        return "jpeg_too_large", f"JPEG of {width}x{height} exceeds {max_pixels} pixels"
    if min_bytes_per_mpixel > 0:
        if sof not in HUFFMAN_SOF:
            return "jpeg_implausible", f"JPEG coding process SOF{sof - 0xC0} is not accepted (Huffman only)"
        need = min_bytes_per_mpixel * width * height / 1e6
        if len(data) < need:
            return "jpeg_implausible", (
                f"JPEG of {len(data)} bytes cannot hold {width}x{height} pixels (at least {need:.0f} bytes)"
            )
    return None


def decode_jpeg(
    data: bytes | bytearray | memoryview,
    expected_size: tuple[int, int] | None = None,
    max_pixels: int = MAX_PIXELS,
    min_bytes_per_mpixel: float = 0.0,
) -> np.ndarray:
    """Decode JPEG bytes into RGB uint8. Raises :class:`JpegError` on corrupt or empty data.

    Before any pixel memory is allocated, :func:`jpeg_problem` refuses a JPEG of another size than
    ``expected_size`` ``(width, height)`` (for example one that disagrees with its frame header), one
    over ``max_pixels``, and, with ``min_bytes_per_mpixel`` > 0, one too small for the size it claims.
    """
    problem = jpeg_problem(data, expected_size, max_pixels, min_bytes_per_mpixel)
    if problem is not None:
        raise JpegError(problem[1])
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
