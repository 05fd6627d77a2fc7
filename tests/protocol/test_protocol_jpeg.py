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
