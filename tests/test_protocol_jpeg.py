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
