"""JPEG helpers (libjpeg-turbo through OpenCV). Images are RGB uint8 ``(H, W, 3)``.

Decoding reads the image size from the JPEG header first, so a tiny hostile file that claims a huge
image is refused before any pixel memory is allocated: :func:`jpeg_problem` runs every check that needs
no pixel (size against the expected one, a pixel cap, the coding process, and a floor on compressed bytes
per pixel) and :func:`decode_jpeg` runs it before decoding.

Compressed bytes per pixel: a Huffman-coded JPEG (baseline, extended or progressive: every camera and
encoder in use) spends at least one bit per 8x8 block of each component, so at least ~1953 bytes per
megapixel even for a flat grey image (measured: 5.9 KB/MP for a flat colour image with optimised tables).
A 600-byte file claiming 6000x6000 (36 MP) is therefore not a JPEG of that size; libjpeg would still
"decode" it (a warning, the missing data filled with grey), allocating 108 MB for nothing. Only the bytes from
the first start-of-scan on count (the entropy-coded data): a comment or application segment padded to the
size the floor asks for buys nothing. The floor is a sanity check, not the memory bound: padding can also
follow the image or sit between scans.

The memory bound is :meth:`JpegInfo.decode_bytes`, also from the headers alone: libjpeg decodes at 1/1, 1/2,
1/4 or 1/8 of the size (DCT scaling, ``reduction``) at about the cost of the smaller image, except that a
progressive JPEG (or one whose first scan lacks a component) keeps every DCT coefficient of the full image
while it decodes (2 bytes per coefficient: 3 bytes a pixel at 4:2:0, 6 at 4:4:4). :func:`decode_jpeg`
refuses a JPEG whose decode would need more than ``max_decode_bytes``, whatever its header claims.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

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
PROGRESSIVE_SOF = frozenset({0xC2, 0xC6, 0xCA, 0xCE})
LOSSLESS_SOF = frozenset({0xC3, 0xC7, 0xCB, 0xCF})
"""Lossless coding has no DCT: it cannot be decoded reduced."""
REDUCTIONS = (1, 2, 4, 8)
"""The DCT scalings libjpeg decodes at cheaply (OpenCV's ``IMREAD_REDUCED_COLOR_2/4/8``): 1/1 to 1/8 of the size."""
_IMREAD_FLAGS = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                 8: cv2.IMREAD_REDUCED_COLOR_8}
DECODED_BYTES_PER_PIXEL = 9
"""Peak bytes per decoded pixel in :func:`decode_jpeg`: OpenCV's BGR image and its copy while decoding (6,
measured), then the RGB image beside the BGR one (3 more at most)."""
MAX_DECODE_BYTES = 256 * 1024 * 1024
"""Default of :func:`decode_jpeg`'s ``max_decode_bytes``."""


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
    for marker, i in _segments(b):
        if marker in _SOF_MARKERS:
            return _frame_size(b, i)
        if marker == 0xDA:  # start of scan before any frame header
            break
    raise JpegError("JPEG has no frame header")


@dataclass(frozen=True)
class JpegInfo:
    """What decoding a JPEG costs, from its headers alone (:func:`jpeg_info`; nothing decoded)."""

    width: int
    height: int
    sof: int
    """The start-of-frame marker (coding process)."""
    sampling: tuple[tuple[int, int], ...]
    """Each component's (horizontal, vertical) sampling factor."""
    multi_scan: bool
    """libjpeg keeps every DCT coefficient of the full image while decoding: a progressive JPEG, or one whose
    first scan lacks a component."""
    data_bytes: int
    """Bytes from the first start-of-scan marker to the end: the entropy-coded data (and what follows it)."""

    @property
    def scalable(self) -> bool:
        """Whether libjpeg can decode it reduced (DCT-based coding: all but lossless)."""
        return self.sof not in LOSSLESS_SOF

    def reductions(self) -> tuple[int, ...]:
        """The reductions it can be decoded at."""
        return REDUCTIONS if self.scalable else (1,)

    def output_size(self, reduction: int) -> tuple[int, int]:
        """``(width, height)`` decoded at 1/``reduction`` (libjpeg rounds up)."""
        return reduced_size((self.width, self.height), reduction)

    def coefficient_bytes(self) -> int:
        """Bytes of the full image's DCT coefficients libjpeg holds while decoding (0 for a single-scan JPEG)."""
        if not self.multi_scan:
            return 0
        hmax = max(h for h, _ in self.sampling)
        vmax = max(v for _, v in self.sampling)
        blocks = 0
        for h, v in self.sampling:  # libjpeg's jdcoefct.c: blocks rounded up to whole MCUs, 64 int16 each
            wb = -(-self.width * h // (8 * hmax))
            hb = -(-self.height * v // (8 * vmax))
            blocks += -(-wb // h) * h * (-(-hb // v) * v)
        return blocks * 64 * 2

    def decode_bytes(self, reduction: int = 1) -> int:
        """Peak memory of :func:`decode_jpeg` at 1/``reduction``: the coefficients (multi-scan) and the decoded
        images (:data:`DECODED_BYTES_PER_PIXEL`)."""
        w, h = self.output_size(reduction)
        return self.coefficient_bytes() + DECODED_BYTES_PER_PIXEL * w * h

    def reduction_for(self, max_pixels: int) -> int | None:
        """The least reduction that decodes it at ``max_pixels`` or fewer, or None when even 1/8 is over."""
        for r in self.reductions():
            w, h = self.output_size(r)
            if w * h <= max_pixels:
                return r
        return None


def reduced_size(size: tuple[int, int], reduction: int) -> tuple[int, int]:
    """``(width, height)`` of an image of ``size`` decoded at 1/``reduction`` (libjpeg rounds up)."""
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction must be one of {REDUCTIONS}, got {reduction}")
    return -(-size[0] // reduction), -(-size[1] // reduction)


def jpeg_info(data: bytes | bytearray | memoryview) -> JpegInfo:
    """A JPEG's size, coding process, sampling and scan layout from its headers (up to the first start-of-scan;
    raises :class:`JpegError` when they are missing or corrupt)."""
    b = bytes(data)
    frame: tuple[int, int, int, tuple[tuple[int, int], ...]] | None = None
    for marker, i in _segments(b):
        if marker in _SOF_MARKERS:
            if frame is not None:
                raise JpegError("JPEG has two frame headers")
            width, height, sof = _frame_size(b, i)
            n = b[i + 9] if i + 10 <= len(b) else 0
            if n == 0 or i + 10 + 3 * n > len(b):
                raise JpegError("JPEG frame header is truncated or has no component")
            sampling = tuple((b[i + 11 + 3 * k] >> 4, b[i + 11 + 3 * k] & 15) for k in range(n))
            if any(not (1 <= h <= 4 and 1 <= v <= 4) for h, v in sampling):
                raise JpegError(f"JPEG has impossible sampling factors {sampling}")
            frame = (width, height, sof, sampling)
        elif marker == 0xDA:
            if frame is None:
                break
            if i + 5 > len(b):
                raise JpegError("JPEG scan header is truncated")
            width, height, sof, sampling = frame
            return JpegInfo(width, height, sof, sampling,
                            multi_scan=sof in PROGRESSIVE_SOF or b[i + 4] < len(sampling), data_bytes=len(b) - i)
    raise JpegError("JPEG has no frame header" if frame is None else "JPEG has no scan")


def _segments(b: bytes) -> Iterator[tuple[int, int]]:
    """``(marker, offset)`` of each marker segment up to and including the first start-of-scan (whose entropy-coded
    data follows it); raises :class:`JpegError` on a broken marker stream."""
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
        yield marker, i
        if marker == 0xDA:
            return
        i += 2 + seg_len


def _frame_size(b: bytes, i: int) -> tuple[int, int, int]:
    """``(width, height, marker)`` of the start-of-frame segment at ``i``."""
    if i + 9 > len(b):
        raise JpegError("JPEG frame header is truncated")
    height = (b[i + 5] << 8) | b[i + 6]
    width = (b[i + 7] << 8) | b[i + 8]
    if width == 0 or height == 0:
        raise JpegError("JPEG header has a zero image size")
    return width, height, b[i + 1]


def jpeg_problem(
    data: object,
    expected_size: tuple[int, int] | None = None,
    max_pixels: int = MAX_PIXELS,
    min_bytes_per_mpixel: float = 0.0,
    max_bytes: int = MAX_JPEG_BYTES,
    reduction: int = 1,
    max_decode_bytes: int | None = None,
) -> tuple[str, str] | None:
    """Why ``data`` must not be decoded (at 1/``reduction``), from its bytes and headers alone, or None when it
    may be.

    Returns ``(reason, detail)``; ``reason`` is a counter name: ``jpeg_too_large`` (over ``max_bytes``,
    ``max_pixels`` at its full size, or ``max_decode_bytes`` to decode at 1/``reduction``: see
    :meth:`JpegInfo.decode_bytes`; or lossless, which cannot be decoded reduced), ``jpeg_size_mismatch`` (its
    full size is not ``expected_size`` = ``(width, height)``), ``jpeg_implausible`` (fewer than
    ``min_bytes_per_mpixel`` entropy-coded bytes per megapixel, or, when that is > 0, a coding process other
    than :data:`HUFFMAN_SOF`), ``jpeg_corrupt`` (no JPEG headers or no scan).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) < 4:
        return "jpeg_corrupt", "empty or missing JPEG data"
    if len(data) > max_bytes:
        return "jpeg_too_large", f"JPEG of {len(data)} bytes exceeds {max_bytes}"
    try:
        info = jpeg_info(data)
    except JpegError as e:
        return "jpeg_corrupt", str(e)
    width, height = info.width, info.height
    if expected_size is not None and (width, height) != tuple(expected_size):
        return "jpeg_size_mismatch", f"JPEG is {width}x{height}, expected {expected_size[0]}x{expected_size[1]}"
    if width * height > max_pixels:
        return "jpeg_too_large", f"JPEG of {width}x{height} exceeds {max_pixels} pixels"
    if min_bytes_per_mpixel > 0:
        if info.sof not in HUFFMAN_SOF:
            return "jpeg_implausible", f"JPEG coding process SOF{info.sof - 0xC0} is not accepted (Huffman only)"
        need = min_bytes_per_mpixel * width * height / 1e6
        if info.data_bytes < need:
            return "jpeg_implausible", (
                f"JPEG of {len(data)} bytes ({info.data_bytes} of coded data) cannot hold {width}x{height} pixels "
                f"(at least {need:.0f} bytes of coded data)"
            )
    if reduction not in info.reductions():
        return "jpeg_too_large", f"a JPEG of coding process SOF{info.sof - 0xC0} cannot be decoded at 1/{reduction}"
    if max_decode_bytes is not None:
        need_bytes = info.decode_bytes(reduction)
        if need_bytes > max_decode_bytes:
            ow, oh = info.output_size(reduction)
            coefs = info.coefficient_bytes()
            held = f"{coefs / 2**20:.0f} MiB of DCT coefficients (multi-scan) and " if coefs else ""
            return "jpeg_too_large", (
                f"decoding the {width}x{height} JPEG at 1/{reduction} ({ow}x{oh}) needs {held}"
                f"{(need_bytes - coefs) / 2**20:.0f} MiB of image: over {max_decode_bytes / 2**20:.0f} MiB"
            )
    return None


def decode_jpeg(
    data: bytes | bytearray | memoryview,
    expected_size: tuple[int, int] | None = None,
    max_pixels: int = MAX_PIXELS,
    min_bytes_per_mpixel: float = 0.0,
    reduction: int = 1,
    max_decode_bytes: int = MAX_DECODE_BYTES,
) -> np.ndarray:
    """Decode JPEG bytes into RGB uint8, at 1/``reduction`` of its size (libjpeg's DCT scaling: the image is
    ``ceil(width / reduction)`` x ``ceil(height / reduction)``; see :func:`reduced_size`). Raises
    :class:`JpegError` on corrupt or empty data.

    Before any pixel memory is allocated, :func:`jpeg_problem` refuses a JPEG of another size than
    ``expected_size`` ``(width, height)`` (for example one that disagrees with its frame header), one
    over ``max_pixels`` (at its full size), one whose decode needs more than ``max_decode_bytes`` (whatever
    its header claims: :meth:`JpegInfo.decode_bytes`) and, with ``min_bytes_per_mpixel`` > 0, one too small for
    the size it claims.
    """
    problem = jpeg_problem(data, expected_size, max_pixels, min_bytes_per_mpixel, reduction=reduction,
                           max_decode_bytes=max_decode_bytes)
    if problem is not None:
        raise JpegError(problem[1])
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    if b"\xff\xd9" not in bytes(buf[-64:]):
        raise JpegError("truncated JPEG (missing EOI marker)")
    try:
        bgr = cv2.imdecode(buf, _IMREAD_FLAGS[reduction])
    except cv2.error as e:
        raise JpegError(f"corrupt JPEG: {e.msg if hasattr(e, 'msg') else e}") from None
    if bgr is None or bgr.ndim != 3:
        raise JpegError("corrupt JPEG")
    width, height = jpeg_size(data)
    ow, oh = reduced_size((width, height), reduction)
    if bgr.shape[:2] != (oh, ow):  # libjpeg scales by whole 8x8 blocks; anything else is no JPEG decoder of ours
        raise JpegError(f"JPEG decoded at 1/{reduction} to {bgr.shape[1]}x{bgr.shape[0]}, not {ow}x{oh}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
