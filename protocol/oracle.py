"""Pack and unpack the simulator's ORACLE images (instance ids, depth) as 16-bit PNGs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from protocol.jpeg import MAX_PIXELS, JpegError
from protocol.messages import OracleFrame, rows

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_DECODE_BYTES_PER_PIXEL = 4
"""Peak bytes per pixel while OpenCV decodes a 16-bit PNG (the image and a copy of it, measured)."""


def encode_u16_png(image: np.ndarray) -> bytes:
    """Encode a 2D uint16 image losslessly."""
    if image.ndim != 2 or image.dtype != np.uint16:
        raise ValueError("expected a 2D uint16 image")
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def png_size(data: bytes) -> tuple[int, int]:
    """``(width, height)`` from a PNG's IHDR chunk, without decoding pixels."""
    if len(data) < 24 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise JpegError("not a PNG")
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def decode_u16_png(data: bytes, max_pixels: int = MAX_PIXELS, expected_size: tuple[int, int] | None = None
                   ) -> np.ndarray:
    """Decode a 16-bit PNG; raises ``JpegError`` (the image error type) when corrupt, too large or, with
    ``expected_size`` (width, height), of another size.

    The size is read from the header first, so a small file claiming a huge image (or one that does not
    belong to its frame) is refused before any pixel memory is allocated.
    """
    if not isinstance(data, (bytes, bytearray)) or not data:
        raise JpegError("empty PNG")
    width, height = png_size(bytes(data))
    if width == 0 or height == 0 or width * height > max_pixels:
        raise JpegError(f"PNG of {width}x{height} is empty or exceeds {max_pixels} pixels")
    if expected_size is not None and (width, height) != tuple(expected_size):
        raise JpegError(f"PNG of {width}x{height} does not match its {expected_size[0]}x{expected_size[1]} frame")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise JpegError(f"corrupt PNG: {e}") from None
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise JpegError("corrupt 16-bit PNG")
    return img


def depth_to_png(depth_m: np.ndarray) -> bytes:
    """Depth in metres (0 or non-finite = none) to millimetre PNG (saturates at 65.5 m)."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0)
    return encode_u16_png(np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16))


def png_to_depth(data: bytes, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Millimetre PNG back to float32 metres (0 = none); ``expected_size`` as in :func:`decode_u16_png`."""
    return decode_u16_png(data, expected_size=expected_size).astype(np.float32) / 1000.0


def ids_to_png(instance_ids: np.ndarray) -> bytes:
    """Instance ids (negative = nothing) to a 16-bit PNG (0 = structure or nothing)."""
    return encode_u16_png(np.clip(instance_ids, 0, 65535).astype(np.uint16))


@dataclass(frozen=True)
class OracleCapture:
    """Simulator ground truth for one captured image (ORACLE: only simulated sources produce it)."""

    T_world_cam_true: np.ndarray
    instance_id: np.ndarray
    depth_m: np.ndarray
    labels: dict[int, str] = field(default_factory=dict)

    def message(self, source_id: str, seq: int, stamp_ns: int,
                resize: Callable[[np.ndarray], np.ndarray] | None = None) -> OracleFrame:
        """The :class:`OracleFrame` of frame ``source_id``/``seq``; ``resize`` (nearest-neighbour: ids stay ids)
        brings the images to the size the frame was sent at."""
        same: Callable[[np.ndarray], np.ndarray] = lambda image: image  # noqa: E731
        fit = resize or same
        return OracleFrame(
            source_id=source_id,
            seq=seq,
            stamp_ns=stamp_ns,
            T_world_cam_true=rows(self.T_world_cam_true),
            ids_png=ids_to_png(fit(self.instance_id)),
            depth_png=depth_to_png(fit(self.depth_m)),
            labels={str(k): v for k, v in self.labels.items()},
        )
