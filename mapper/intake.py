"""What the mapper accepts from a peer, checked before it costs memory or reaches the graph (pure: no I/O).

Every limit is a field of :class:`InputLimits` (``[limits]`` in the mapper's TOML, ``argus mapper --describe``).
A refused frame is counted under its reason (the counter names below) and logged, rate-limited, by the mapper;
it never takes a ring slot, is never decoded and never reaches the graph.

``frame_problem`` runs on each frame sample as it arrives (header decoded, JPEG bytes not): compressed size,
pixel count, the JPEG's own start-of-frame size against the header, compressed bytes per pixel, the size it
will be worked at (:func:`working_reduction`: the JPEG is decoded at 1/1, 1/2, 1/4 or 1/8 of its size, the
least reduction that brings it to ``max_working_pixels``) and the memory decoding it takes, intrinsics and the
pose against the site's bounds. ``view_problem`` runs the checks that apply to an in-process :class:`View`
at :meth:`mapper.core.MapperCore.ingest` (benchmarks and the explorer feed the core directly).

Counter names (the ``reason`` returned): ``frames_too_large``, ``frames_size_mismatch``, ``frames_implausible_jpeg``,
``frames_corrupt_jpeg``, ``frames_bad_intrinsics``, ``frames_outside_site``. The first four (:data:`IMAGE_REASONS`:
the image itself is refused) also count as ``decode_errors``, like a JPEG that fails to decode.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from protocol.jpeg import MIN_BYTES_PER_MPIXEL_FLOOR, JpegInfo, jpeg_info, jpeg_problem
from protocol.messages import FrameHeader, Intrinsics

if TYPE_CHECKING:
    from mapper.geometry.contract import View

Problem = tuple[str, str]
"""``(counter name, detail)``."""

_JPEG_REASONS = {
    "jpeg_too_large": "frames_too_large",
    "jpeg_size_mismatch": "frames_size_mismatch",
    "jpeg_implausible": "frames_implausible_jpeg",
    "jpeg_corrupt": "frames_corrupt_jpeg",
}


IMAGE_REASONS = frozenset(_JPEG_REASONS.values())
"""Reasons that refuse a frame's image (counted as ``decode_errors`` too)."""


class InputLimits(BaseModel):
    """Limits on what peers may send the mapper. Memory of the frame path (README, "Hostile input and the
    mapper's memory bound"): compressed frames buffered <= ``2 * max_buffered_frame_bytes`` (receive rings +
    frames waiting for their ORACLE sample); one frame decoded at a time, in at most ``max_decode_bytes`` while
    libjpeg decodes it, to at most ``max_working_pixels`` (3 bytes each once decoded, also the size of every
    keyframe kept); decoded pixels in flight <= ``decode_budget_pixels``."""

    model_config = ConfigDict(extra="forbid")
    max_frame_bytes: int = Field(
        default=8 * 1024 * 1024, ge=1024,
        description="largest compressed frame (JPEG bytes) accepted; larger ones are refused on arrival "
        "(frames_too_large). 8 MiB holds a 16 MP JPEG at quality 95",
    )
    max_frame_pixels: int = Field(
        default=8192 * 8192, ge=1,
        description="largest frame (width x height, from its header and its JPEG) accepted (frames_too_large); "
        "default 67 MP: 8192x8192, more than a 48 MP phone camera or 8K video. What a frame costs is bounded by "
        "max_working_pixels and max_decode_bytes, not by this",
    )
    max_working_pixels: int = Field(
        default=1920 * 1080, ge=64,
        description="pixels a frame is worked at (decoded, kept as a keyframe, reconstructed): a larger frame is "
        "decoded at 1/2, 1/4 or 1/8 of its size, the least of these that brings it to this many pixels or fewer "
        "(libjpeg DCT scaling: about the cost of decoding the smaller image; its intrinsics are scaled alike); "
        "a frame over it even at 1/8 is refused (frames_too_large). Default: Full HD (1920x1080 is worked at "
        "full size, 4000x3000 at 1/4)",
    )
    max_decode_bytes: int = Field(
        default=256 * 1024 * 1024, ge=1024 * 1024,
        description="memory libjpeg may take to decode one frame at its working size, from its headers: about 9 "
        "bytes per decoded pixel, plus, for a progressive JPEG (or one whose first scan lacks a component), 2 "
        "bytes per DCT coefficient of the whole full-size image (3 bytes a pixel at 4:2:0, 6 at 4:4:4) whatever "
        "the reduction; over it the frame is refused (frames_too_large). 256 MiB: a progressive 8000x8000 "
        "4:2:0 frame (183 MiB of coefficients) passes, a progressive 4:4:4 one (366 MiB) does not; a baseline "
        "frame of any accepted size needs at most 9 x max_working_pixels bytes (18 MiB)",
    )
    min_jpeg_bytes_per_mpixel: float = Field(
        default=1000.0, ge=0.0,
        description="a JPEG with fewer compressed bytes per megapixel than this is refused unread "
        f"(frames_implausible_jpeg): a Huffman-coded JPEG cannot have fewer than {MIN_BYTES_PER_MPIXEL_FLOOR:.0f}; "
        "0 turns the check off (and admits arithmetic-coded, lossless and hierarchical JPEGs)",
    )
    max_buffered_frame_bytes: int = Field(
        default=256 * 1024 * 1024, ge=1024,
        description="compressed frames buffered across all sources before processing; the oldest are dropped "
        "beyond it (frames_dropped). The frames waiting for an ORACLE sample have the same bound",
    )
    decode_budget_pixels: int = Field(
        default=4096 * 4096, ge=1,
        description="decoded pixels (at the working size) in flight across all sources (frames decoded and not yet "
        "processed); frames are decoded one at a time just before processing, so this is at least "
        "max_working_pixels",
    )
    min_hfov_deg: float = Field(
        default=5.0, gt=0.0, lt=180.0,
        description="narrowest horizontal field of view accepted from a frame's intrinsics "
        "(frames_bad_intrinsics): a narrower view (a longer focal length) is no camera watching a room",
    )
    max_hfov_deg: float = Field(
        default=175.0, gt=0.0, lt=180.0,
        description="widest horizontal or vertical field of view accepted (a pinhole model cannot describe "
        "180 deg; fx=1e-300 is ~180)",
    )
    max_pixel_aspect: float = Field(
        default=4.0, ge=1.0, description="largest fx/fy (or fy/fx) accepted: square pixels are 1"
    )
    principal_point_margin: float = Field(
        default=0.25, ge=0.0,
        description="the principal point may lie outside the image by at most this fraction of its width/height",
    )
    site_min_m: tuple[float, float, float] = Field(
        default=(-100.0, -100.0, -10.0),
        description="world-frame lower corner (x, y, z metres) of the site's bounding box; a frame whose camera "
        "position lies outside the box is refused (frames_outside_site). Set it to the site's extent plus a margin "
        "(a simulated apartment: its scene bounds)",
    )
    site_max_m: tuple[float, float, float] = Field(
        default=(100.0, 100.0, 30.0), description="upper corner of the site's bounding box (see site_min_m)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> InputLimits:
        if self.min_hfov_deg >= self.max_hfov_deg:
            raise ValueError("min_hfov_deg must be below max_hfov_deg")
        if self.decode_budget_pixels < self.max_working_pixels:
            raise ValueError("decode_budget_pixels must be at least max_working_pixels")
        if self.max_working_pixels > self.max_frame_pixels:
            raise ValueError("max_working_pixels must be at most max_frame_pixels")
        if self.max_decode_bytes < 9 * self.max_working_pixels:
            raise ValueError("max_decode_bytes must be at least 9 bytes per working pixel (9 x max_working_pixels)")
        if self.max_buffered_frame_bytes < self.max_frame_bytes:
            raise ValueError("max_buffered_frame_bytes must be at least max_frame_bytes")
        if not all(math.isfinite(v) for v in (*self.site_min_m, *self.site_max_m)) or any(
            lo >= hi for lo, hi in zip(self.site_min_m, self.site_max_m, strict=True)
        ):
            raise ValueError("site_min_m must be finite and below site_max_m on every axis")
        return self


def _fov_deg(focal_px: float, size_px: int) -> float:
    return math.degrees(2.0 * math.atan2(size_px / 2.0, focal_px))


def intrinsics_problem(intr: Intrinsics, width: int, height: int, limits: InputLimits) -> Problem | None:
    """Why ``intr`` cannot describe a real camera taking ``width`` x ``height`` images, or None."""
    values = (intr.fx, intr.fy, intr.cx, intr.cy)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        return "frames_bad_intrinsics", f"intrinsics are not finite: {values}"
    if (intr.width, intr.height) != (width, height):
        return "frames_bad_intrinsics", f"intrinsics are for {intr.width}x{intr.height}, frame is {width}x{height}"
    if intr.fx <= 0 or intr.fy <= 0:
        return "frames_bad_intrinsics", f"focal lengths must be > 0: fx={intr.fx:g}, fy={intr.fy:g}"
    hfov, vfov = _fov_deg(intr.fx, width), _fov_deg(intr.fy, height)
    if not limits.min_hfov_deg <= hfov <= limits.max_hfov_deg:
        return "frames_bad_intrinsics", (
            f"horizontal field of view {hfov:.3g} deg (fx {intr.fx:g} px over {width} px) is outside "
            f"[{limits.min_hfov_deg:g}, {limits.max_hfov_deg:g}] deg"
        )
    if vfov > limits.max_hfov_deg:
        return "frames_bad_intrinsics", (
            f"vertical field of view {vfov:.3g} deg (fy {intr.fy:g} px over {height} px) is over "
            f"{limits.max_hfov_deg:g} deg"
        )
    if not 1.0 / limits.max_pixel_aspect <= intr.fx / intr.fy <= limits.max_pixel_aspect:
        return "frames_bad_intrinsics", f"pixel aspect fx/fy = {intr.fx / intr.fy:.3g} is implausible"
    m = limits.principal_point_margin
    if not (-m * width <= intr.cx <= (1 + m) * width and -m * height <= intr.cy <= (1 + m) * height):
        return "frames_bad_intrinsics", f"principal point ({intr.cx:g}, {intr.cy:g}) is far outside the image"
    return None


def pose_problem(T_world_cam: object, limits: InputLimits) -> Problem | None:
    """Why a camera at ``T_world_cam`` cannot be on the site (position outside its box), or None."""
    try:
        t = np.asarray(T_world_cam, dtype=np.float64)[:3, 3]
    except (TypeError, ValueError, IndexError) as e:
        return "frames_outside_site", f"pose is not a 4x4 matrix: {e}"
    lo, hi = np.asarray(limits.site_min_m), np.asarray(limits.site_max_m)
    if t.shape != (3,) or not np.all(np.isfinite(t)) or np.any(t < lo) or np.any(t > hi):
        return "frames_outside_site", (
            f"camera position {np.round(t, 2).tolist()} is outside the site box {list(lo)}..{list(hi)} m"
        )
    return None


def working_reduction(info: JpegInfo, limits: InputLimits) -> int | None:
    """The reduction (1, 2, 4 or 8) a frame with JPEG ``info`` is decoded and worked at: the least that brings it
    to ``limits.max_working_pixels`` or fewer. None: over it even at 1/8 (or lossless, which cannot be reduced)."""
    return info.reduction_for(limits.max_working_pixels)


def frame_problem(header: FrameHeader, jpeg: bytes, limits: InputLimits) -> Problem | None:
    """Why a received frame (decoded header, undecoded JPEG bytes) must be refused, or None. Nothing here
    allocates pixel memory: the JPEG's size, sampling and scans are read from its headers."""
    w, h = header.width, header.height
    if w * h > limits.max_frame_pixels:
        return "frames_too_large", f"frame header claims {w}x{h} > {limits.max_frame_pixels} pixels"
    jp = jpeg_problem(jpeg, (w, h), limits.max_frame_pixels, limits.min_jpeg_bytes_per_mpixel,
                      limits.max_frame_bytes)
    if jp is not None:
        return _JPEG_REASONS[jp[0]], jp[1]
    reduction = working_reduction(jpeg_info(jpeg), limits)  # the headers parsed above: no JpegError
    if reduction is None:
        return "frames_too_large", (
            f"a {w}x{h} frame is over limits.max_working_pixels ({limits.max_working_pixels}) even decoded at "
            "its smallest (1/8; lossless JPEGs: 1/1)"
        )
    jp = jpeg_problem(jpeg, reduction=reduction, max_pixels=limits.max_frame_pixels,
                      max_bytes=limits.max_frame_bytes, max_decode_bytes=limits.max_decode_bytes)
    if jp is not None:
        return _JPEG_REASONS[jp[0]], jp[1] + " (limits.max_decode_bytes)"
    if header.intrinsics is not None:
        p = intrinsics_problem(header.intrinsics, w, h, limits)
        if p is not None:
            return p
    if header.T_world_cam is not None:
        return pose_problem(header.T_world_cam, limits)
    return None


def view_problem(view: View, limits: InputLimits) -> Problem | None:
    """The checks of :func:`frame_problem` that apply to an in-process view (decoded image, no JPEG): its image is
    what the mapper works at, so it must be within ``max_working_pixels``."""
    h, w = view.image.shape[:2]
    if w * h > limits.max_working_pixels:
        return "frames_too_large", (
            f"view of {w}x{h} > limits.max_working_pixels ({limits.max_working_pixels}): reduce it first "
            "(argus mapper decodes frames reduced)"
        )
    if view.intrinsics is not None:
        p = intrinsics_problem(view.intrinsics, w, h, limits)
        if p is not None:
            return p
    if view.T_world_cam is not None:
        return pose_problem(view.T_world_cam, limits)
    return None
