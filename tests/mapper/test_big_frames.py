"""Large frames are worked at a bounded size (issue 37 item 2): the mapper decodes a frame over
``limits.max_working_pixels`` at 1/2, 1/4 or 1/8 (libjpeg DCT scaling), scales its intrinsics and ORACLE images to
that grid, refuses what it cannot decode within ``max_decode_bytes`` whatever the headers claim, and the memory
of the decode is the small image's. Real JPEGs, encoded here; the mapper's own intake (no Zenoh)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from bench.bigframes import padded_jpeg, textured_jpeg, textured_rgb
from mapper.config import MapperConfig
from mapper.inbox import FrameIntake, oracle_data, reduce_nearest
from mapper.intake import InputLimits, frame_problem, view_problem
from protocol.codec import encode
from protocol.jpeg import JpegError, decode_jpeg, encode_jpeg, jpeg_info
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics, OracleFrame
from protocol.oracle import encode_u16_png
from protocol.poses import look_at
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters, decode_frame_bytes

LIM = InputLimits()


def intake(**limits: object) -> FrameIntake:
    cfg = MapperConfig(limits=InputLimits(**limits))  # type: ignore[arg-type]
    return FrameIntake(cfg, Keys(site=cfg.site), Counters(), RateLimitedLog(logging.getLogger("test")))


def header(w: int, h: int, seq: int = 1, hfov_deg: float = 70.0) -> FrameHeader:
    return FrameHeader(source_id="cam", source_kind="fixed", seq=seq, stamp_ns=seq, width=w, height=h,
                       intrinsics=Intrinsics.from_fov(w, h, hfov_deg),
                       T_world_cam=look_at([0, 0, 1], [0, 2, 1]).tolist())


def through(it: FrameIntake, h: FrameHeader, jpeg: bytes, oracle: OracleFrame | None = None):  # type: ignore[no-untyped-def]
    """One frame sample's bytes through the intake; the views it became (none when refused)."""
    it.admit_frame(decode_frame_bytes(it.keys.frame(h.source_kind, h.source_id), encode(h), jpeg))
    views = []
    for f, _ in it.ready(0.0):
        rgb = it.decode(f)
        if rgb is None:
            continue
        views.append(it.view(f, rgb, oracle))
        it.release(f)
    return views


def _status_kb(name: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(name + ":"):
            return int(line.split()[1])
    raise KeyError(name)


@contextmanager
def peak_rss_growth_mb() -> Iterator[list[float]]:
    """How far this process's peak resident memory rose above its resident memory at the start (Linux: the peak
    is reset through ``/proc/self/clear_refs``)."""
    Path("/proc/self/clear_refs").write_text("5")
    start = _status_kb("VmRSS")
    out: list[float] = []
    yield out
    out.append((_status_kb("VmHWM") - start) / 1024)


# --- the working size ------------------------------------------------------------------------------------
def test_a_4000x4000_frame_is_worked_at_1000x1000_with_its_intrinsics_scaled() -> None:
    import cv2

    rgb = textured_rgb(4000, 4000, seed=3)
    jpeg = encode_jpeg(rgb, 90)
    h = header(4000, 4000)
    it = intake()
    (v,) = through(it, h, jpeg)
    assert v.image.shape == (1000, 1000, 3)  # 1/2 is 4 MP > 2.07 MP: 1/4
    assert h.intrinsics is not None and v.intrinsics is not None
    assert v.intrinsics == h.intrinsics.reduced(4)
    assert v.intrinsics.fx == pytest.approx(h.intrinsics.fx / 4) and v.intrinsics.cx == pytest.approx(499.5)
    assert it.decode_budget.peak == 1000 * 1000 and it.decode_budget.in_flight == 0
    # The same picture as the full image averaged over 4x4 blocks (DCT scaling, not a crop or a skip).
    area = cv2.resize(rgb, (1000, 1000), interpolation=cv2.INTER_AREA)
    assert np.abs(v.image.astype(np.int16) - area).mean() < 4.0


def test_an_8000x8000_frame_is_accepted_and_worked_at_1_8() -> None:
    it = intake()
    (v,) = through(it, header(8000, 8000), textured_jpeg(8000, 8000, seed=4))
    assert v.image.shape == (1000, 1000, 3) and v.intrinsics is not None and v.intrinsics.width == 1000
    assert it.counters.get("frames_too_large") == 0


def test_a_full_hd_frame_is_worked_at_full_size() -> None:
    it = intake()
    h = header(1920, 1080)
    (v,) = through(it, h, textured_jpeg(1920, 1080, seed=5))
    assert v.image.shape == (1080, 1920, 3) and v.intrinsics == h.intrinsics


def test_a_frame_over_the_working_size_even_at_1_8_is_refused_unread() -> None:
    it = intake(max_working_pixels=10_000)  # 1000x1000 at 1/8: 125 x 125 = 15625 pixels
    assert through(it, header(1000, 1000), textured_jpeg(1000, 1000)) == []
    assert it.counters.get("frames_too_large") == 1 and it.counters.get("decode_errors") == 1
    assert it.decode_budget.peak == 0
    reason, detail = frame_problem(header(1000, 1000), textured_jpeg(1000, 1000), it.config.limits) or ("", "")
    assert reason == "frames_too_large" and "even decoded at its smallest" in detail


def test_an_in_process_view_over_the_working_size_is_refused() -> None:
    from tests.support.boxes import view

    v = view([0.0, 0.0, 1.2], 1)
    assert view_problem(v, LIM) is None
    reason, detail = view_problem(v, InputLimits(max_working_pixels=100)) or ("", "")
    assert reason == "frames_too_large" and "max_working_pixels" in detail


# --- padded and progressive JPEGs: memory bounded from the headers ---------------------------------------------
@pytest.mark.parametrize("size", [4000, 8000])
def test_a_jpeg_padded_with_comments_is_refused_as_implausible(size: int) -> None:
    """Issue 37: comment segments padded up to the byte floor passed it; only coded data counts now."""
    jpeg = padded_jpeg(size, size)
    assert len(jpeg) > LIM.min_jpeg_bytes_per_mpixel * size * size / 1e6  # what the old check counted
    reason, detail = frame_problem(header(size, size), jpeg, LIM) or ("", "")
    assert reason == "frames_implausible_jpeg" and "of coded data" in detail


def test_with_the_floor_off_a_padded_8000x8000_jpeg_decodes_at_1_8_in_little_memory() -> None:
    it = intake(min_jpeg_bytes_per_mpixel=0.0)
    jpeg = padded_jpeg(8000, 8000)
    with peak_rss_growth_mb() as grew:
        (v,) = through(it, header(8000, 8000), jpeg)  # libjpeg fills the missing data grey...
    assert v.image.shape == (1000, 1000, 3)  # ...at 1/8: 3 MB, not the 192 MB the header claims
    assert grew[0] < 40, f"peak RSS grew {grew[0]:.0f} MiB"


def test_a_progressive_jpeg_whose_coefficients_exceed_max_decode_bytes_is_refused_from_its_headers() -> None:
    """A progressive JPEG keeps every DCT coefficient of its full size while it decodes, whatever the reduction:
    8000x8000 at 4:4:4 is 366 MiB, refused unread; at 4:2:0 (183 MiB) it fits the default 256 MiB."""
    lim = InputLimits(min_jpeg_bytes_per_mpixel=0.0)
    big = padded_jpeg(8000, 8000, progressive=True, subsampling="444")
    info = jpeg_info(big)
    assert info.multi_scan and info.coefficient_bytes() == 8000 * 8000 * 3 * 2
    reason, detail = frame_problem(header(8000, 8000), big, lim) or ("", "")
    assert reason == "frames_too_large" and "366 MiB of DCT coefficients" in detail and "max_decode_bytes" in detail
    ok = padded_jpeg(8000, 8000, progressive=True, subsampling="420")
    assert jpeg_info(ok).coefficient_bytes() == 8000 * 8000 * 3 // 2 * 2
    assert frame_problem(header(8000, 8000), ok, lim) is None
    with pytest.raises(JpegError, match="DCT coefficients"):
        decode_jpeg(big, max_pixels=8000 * 8000, reduction=8)


def test_decoding_a_real_8000x8000_jpeg_at_1_8_costs_the_small_image() -> None:
    jpeg = textured_jpeg(8000, 8000, seed=6)
    with peak_rss_growth_mb() as grew:
        img = decode_jpeg(jpeg, max_pixels=8000 * 8000, reduction=8)
    assert img.shape == (1000, 1000, 3)
    assert grew[0] < 40, f"peak RSS grew {grew[0]:.0f} MiB (a full decode: ~370)"


# --- ORACLE images on the working grid ---------------------------------------------------------------------
def test_oracle_images_are_brought_to_the_working_grid_by_nearest_neighbour() -> None:
    W = H = 2000  # worked at 1/2
    ids = (np.arange(W, dtype=np.uint16)[None, :] // 7 + np.arange(H, dtype=np.uint16)[:, None] // 11 * 300)
    depth_mm = (np.arange(W, dtype=np.uint16)[None, :] + np.zeros((H, 1), np.uint16) + 500).astype(np.uint16)
    o = OracleFrame(source_id="cam", seq=1, stamp_ns=1, T_world_cam_true=np.eye(4).tolist(),
                    ids_png=encode_u16_png(ids), depth_png=encode_u16_png(depth_mm), labels={"3": "chair"})
    it = intake()
    (v,) = through(it, header(W, H), textured_jpeg(W, H), oracle=o)
    assert v.image.shape == (1000, 1000, 3)
    assert v.oracle is not None and v.oracle.instance_id is not None
    assert v.oracle.instance_id.shape == (1000, 1000) and v.oracle.depth_m.shape == (1000, 1000)
    # Each pixel is the full image's pixel nearest its 2x2 block's centre: ids stay ids (no blending).
    assert np.array_equal(v.oracle.instance_id, ids[1::2, 1::2].astype(np.int32))
    assert np.allclose(v.oracle.depth_m, depth_mm[1::2, 1::2] / 1000.0)


def test_reduce_nearest_keeps_partial_edge_blocks_inside() -> None:
    img = np.arange(10 * 9).reshape(10, 9)
    out = reduce_nearest(img, 4)  # 3 x 3: the last block of each axis is partial
    assert out.shape == (3, 3)
    assert out.tolist() == [[img[r, c] for c in (2, 6, 8)] for r in (2, 6, 9)]
    assert reduce_nearest(img, 1) is img


def test_an_oracle_png_too_large_to_decode_is_refused() -> None:
    o = OracleFrame(source_id="cam", seq=1, stamp_ns=1, T_world_cam_true=np.eye(4).tolist(),
                    ids_png=encode_u16_png(np.zeros((600, 800), np.uint16)))
    ids = oracle_data(o, (800, 600), 2, max_decode_bytes=4 * 800 * 600).instance_id
    assert ids is not None and ids.shape == (300, 400)
    with pytest.raises(JpegError, match="ORACLE PNG"):
        oracle_data(o, (800, 600), 2, max_decode_bytes=4 * 800 * 600 - 1)


# --- intrinsics at the working size -----------------------------------------------------------------------------
@pytest.mark.parametrize("reduction", [2, 4, 8])
def test_reduced_intrinsics_project_where_the_reduced_image_shows_a_point(reduction: int) -> None:
    """A bright dot drawn where the full camera sees a 3D point is found, in the image decoded at 1/reduction,
    where the reduced intrinsics project it (odd sizes: the scale is exactly 1/reduction)."""
    import cv2

    W, H = 1603, 1205
    intr = Intrinsics(width=W, height=H, fx=1100.0, fy=1090.0, cx=811.3, cy=590.8)
    p_cam = np.array([0.31, -0.17, 2.0])
    u, v = (intr.K() @ p_cam)[:2] / p_cam[2]
    img = np.zeros((H, W, 3), np.uint8)
    cv2.circle(img, (round(u * 16), round(v * 16)), 12 * 16, (255, 255, 255), -1, lineType=cv2.LINE_AA, shift=4)
    small = decode_jpeg(encode_jpeg(img, 95), reduction=reduction)[:, :, 1].astype(float)
    red = intr.reduced(reduction)
    assert small.shape == (red.height, red.width) == (-(-H // reduction), -(-W // reduction))
    ys, xs = np.mgrid[0 : small.shape[0], 0 : small.shape[1]]
    found = np.array([(xs * small).sum(), (ys * small).sum()]) / small.sum()
    expected = (red.K() @ p_cam)[:2] / p_cam[2]
    assert np.allclose(found, expected, atol=0.05), (found, expected)
