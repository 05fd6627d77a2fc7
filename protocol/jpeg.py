"""JPEG helpers (libjpeg-turbo through OpenCV). Images are RGB uint8 ``(H, W, 3)``."""

from __future__ import annotations

import cv2
import numpy as np

MAX_JPEG_BYTES = 32 * 1024 * 1024


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


def decode_jpeg(data: bytes | bytearray | memoryview) -> np.ndarray:
    """Decode JPEG bytes into RGB uint8. Raises :class:`JpegError` on corrupt or empty data."""
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < 4:
        raise JpegError("empty or missing JPEG data")
    if len(data) > MAX_JPEG_BYTES:
        raise JpegError(f"JPEG of {len(data)} bytes exceeds {MAX_JPEG_BYTES}")
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    if buf[0] != 0xFF or buf[1] != 0xD8:
        raise JpegError("not a JPEG (missing SOI marker)")
    if b"\xff\xd9" not in bytes(buf[-64:]):
        raise JpegError("truncated JPEG (missing EOI marker)")
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if bgr is None or bgr.ndim != 3:
        raise JpegError("corrupt JPEG")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
