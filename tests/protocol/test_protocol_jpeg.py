from __future__ import annotations

import numpy as np
import pytest

from protocol.jpeg import JpegError, decode_jpeg, encode_jpeg
from protocol.oracle import decode_u16_png, depth_to_png, ids_to_png, png_to_depth


def _img() -> np.ndarray:
    yy, xx = np.mgrid[0:48, 0:64]
    return np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).astype(np.uint8)


def test_round_trip_keeps_size_and_content() -> None:
    img = _img()
    back = decode_jpeg(encode_jpeg(img, 95))
    assert back.shape == img.shape and back.dtype == np.uint8
    assert np.abs(back.astype(int) - img).mean() < 3


def test_colour_order_is_rgb() -> None:
    img = np.zeros((16, 16, 3), np.uint8)
    img[..., 0] = 255
    back = decode_jpeg(encode_jpeg(img, 95))
    assert back[..., 0].mean() > 240 and back[..., 2].mean() < 15


@pytest.mark.parametrize("data", [b"", b"\xff\xd8", b"not a jpeg at all", b"\xff\xd8" + b"\x00" * 100])
def test_corrupt_data_raises(data: bytes) -> None:
    with pytest.raises(JpegError):
        decode_jpeg(data)


def test_truncated_jpeg_raises() -> None:
    data = encode_jpeg(_img())
    with pytest.raises(JpegError):
        decode_jpeg(data[: len(data) // 2])


BAD_IMAGES = [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 3), np.float32), np.zeros((0, 4, 3), np.uint8)]


@pytest.mark.parametrize("bad", BAD_IMAGES)
def test_bad_images_are_refused(bad: np.ndarray) -> None:
    with pytest.raises(JpegError):
        encode_jpeg(bad)


def test_oracle_pngs_round_trip() -> None:
    depth = np.array([[0.0, 1.234], [np.inf, 65.0]], np.float32)
    assert np.allclose(png_to_depth(depth_to_png(depth)), [[0, 1.234], [0, 65.0]], atol=5e-4)
    ids = np.array([[-1, 0], [7, 300]], np.int32)
    assert decode_u16_png(ids_to_png(ids)).tolist() == [[0, 0], [7, 300]]


def _claim_size(jpeg: bytes, width: int, height: int) -> bytes:
    """Rewrite the SOF header of a JPEG to claim another size."""
    b = bytearray(jpeg)
    i = 2
    while not (b[i] == 0xFF and b[i + 1] in (0xC0, 0xC2)):
        i += 2 + ((b[i + 2] << 8) | b[i + 3])
    b[i + 5 : i + 7] = height.to_bytes(2, "big")
    b[i + 7 : i + 9] = width.to_bytes(2, "big")
    return bytes(b)


def test_jpeg_size_reads_the_header() -> None:
    from protocol.jpeg import jpeg_size

    assert jpeg_size(encode_jpeg(_img())) == (64, 48)
    assert jpeg_size(_claim_size(encode_jpeg(_img()), 40000, 30000)) == (40000, 30000)


def test_a_size_bomb_is_refused_before_decoding() -> None:
    bomb = _claim_size(encode_jpeg(_img()), 60000, 60000)
    with pytest.raises(JpegError, match="exceeds"):
        decode_jpeg(bomb)


def test_size_disagreeing_with_the_expectation_is_refused() -> None:
    data = encode_jpeg(_img())
    assert decode_jpeg(data, expected_size=(64, 48)).shape == (48, 64, 3)
    with pytest.raises(JpegError, match="expected"):
        decode_jpeg(data, expected_size=(640, 480))


def test_png_size_bomb_is_refused() -> None:
    from protocol.oracle import png_size

    png = bytearray(ids_to_png(np.zeros((4, 4), np.int32)))
    assert png_size(bytes(png)) == (4, 4)
    png[16:24] = (40000).to_bytes(4, "big") + (40000).to_bytes(4, "big")
    with pytest.raises(JpegError):
        decode_u16_png(bytes(png))


# --- decoding reduced (issue 37) ---------------------------------------------------------------------------
def _odd() -> np.ndarray:
    return np.random.default_rng(2).integers(0, 255, (30, 41, 3), dtype=np.uint8)


@pytest.mark.parametrize("reduction", [1, 2, 4, 8])
def test_decoding_reduced_gives_libjpegs_rounded_up_size(reduction: int) -> None:
    from protocol.jpeg import jpeg_info, reduced_size

    data = encode_jpeg(_odd())
    img = decode_jpeg(data, reduction=reduction)
    assert img.shape == (-(-30 // reduction), -(-41 // reduction), 3)
    assert (img.shape[1], img.shape[0]) == reduced_size((41, 30), reduction) == jpeg_info(data).output_size(reduction)


def test_a_reduction_other_than_1_2_4_8_is_refused() -> None:
    from protocol.jpeg import reduced_size

    with pytest.raises(ValueError, match="reduction"):
        reduced_size((40, 30), 3)
    with pytest.raises(JpegError, match="1/3"):
        decode_jpeg(encode_jpeg(_odd()), reduction=3)


def test_jpeg_info_reads_sampling_and_scans_from_the_headers() -> None:
    import cv2

    from protocol.jpeg import jpeg_info

    bgr = _odd()
    base = jpeg_info(cv2.imencode(".jpg", bgr)[1].tobytes())
    assert base.sampling == ((2, 2), (1, 1), (1, 1)) and not base.multi_scan and base.coefficient_bytes() == 0
    prog_bytes = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    prog = jpeg_info(prog_bytes)
    # 41x30 at 4:2:0: luma 6x4 blocks rounded up to whole 2x2 MCUs (6x4), each chroma 3x2 blocks: 36 blocks.
    assert prog.multi_scan and prog.coefficient_bytes() == (6 * 4 + 2 * 3 * 2) * 64 * 2
    assert 0 < prog.data_bytes < len(prog_bytes)
    grey = jpeg_info(cv2.imencode(".jpg", bgr[:, :, 0])[1].tobytes())
    assert grey.sampling == ((1, 1),) and not grey.multi_scan
    # A first scan with fewer components than the frame: libjpeg buffers the whole image too.
    b = bytearray(cv2.imencode(".jpg", bgr)[1].tobytes())
    sos = b.find(b"\xff\xda")
    b[sos + 4] = 1
    assert jpeg_info(bytes(b)).multi_scan
    with pytest.raises(JpegError, match="no scan"):
        jpeg_info(bytes(b[:sos]))


def test_comment_padding_does_not_count_towards_the_byte_floor() -> None:
    """Issue 37: a small JPEG claiming 4000x4000, padded with comment segments to the floor, passed it."""
    from bench.bigframes import claim_size, with_comments
    from protocol.jpeg import jpeg_problem

    bomb = claim_size(encode_jpeg(_img()), 4000, 4000)
    assert jpeg_problem(bomb, (4000, 4000), min_bytes_per_mpixel=1000.0)[0] == "jpeg_implausible"
    padded = with_comments(bomb, 17_000)  # 16 000 bytes would do for 16 MP at 1000 bytes per megapixel
    reason, detail = jpeg_problem(padded, (4000, 4000), min_bytes_per_mpixel=1000.0) or ("", "")
    assert reason == "jpeg_implausible" and "of coded data" in detail
    real = encode_jpeg(_img())  # a real one passes with its comments
    assert jpeg_problem(with_comments(real, 100_000), (64, 48), min_bytes_per_mpixel=1000.0) is None


def test_reduced_intrinsics_keep_pixel_centres_and_scale_exactly() -> None:
    from protocol.messages import Intrinsics

    intr = Intrinsics(width=1001, height=803, fx=800.0, fy=790.0, cx=500.0, cy=401.0)
    r = intr.reduced(4)
    assert (r.width, r.height) == (251, 201)  # rounded up, as libjpeg does
    assert (r.fx, r.fy) == (200.0, 197.5)  # exactly 1/4, not 251/1001
    assert (r.cx, r.cy) == ((500.0 + 0.5) / 4 - 0.5, (401.0 + 0.5) / 4 - 0.5)
    assert intr.reduced(1) == intr
    assert Intrinsics.from_fov(4000, 3000, 70.0).reduced(4) == Intrinsics.from_fov(1000, 750, 70.0)
    with pytest.raises(ValueError):
        intr.reduced(0)
