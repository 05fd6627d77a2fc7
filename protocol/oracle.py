"""Pack and unpack the simulator's ORACLE images (instance ids, depth) as 16-bit PNGs."""

from __future__ import annotations

import cv2
import numpy as np

from protocol.jpeg import JpegError


def encode_u16_png(image: np.ndarray) -> bytes:
    """Encode a 2D uint16 image losslessly."""
    if image.ndim != 2 or image.dtype != np.uint16:
        raise ValueError("expected a 2D uint16 image")
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def decode_u16_png(data: bytes) -> np.ndarray:
    """Decode a 16-bit PNG; raises ``JpegError`` (the image error type) when corrupt."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise JpegError("corrupt 16-bit PNG")
    return img


def depth_to_png(depth_m: np.ndarray) -> bytes:
    """Depth in metres (0 or non-finite = none) to millimetre PNG (saturates at 65.5 m)."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0)
    return encode_u16_png(np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16))


def png_to_depth(data: bytes) -> np.ndarray:
    """Millimetre PNG back to float32 metres (0 = none)."""
    return decode_u16_png(data).astype(np.float32) / 1000.0


def ids_to_png(instance_ids: np.ndarray) -> bytes:
    """Instance ids (negative = nothing) to a 16-bit PNG (0 = structure or nothing)."""
    return encode_u16_png(np.clip(instance_ids, 0, 65535).astype(np.uint16))
