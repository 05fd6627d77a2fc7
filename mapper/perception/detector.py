"""``detector`` segmenter and embedder: closed-set class labels on real cameras, offline, on a CPU.

A single-shot detector finds labelled boxes, by default in the whole frame and in four overlapping tiles of it
enlarged to the network's input (small and partly hidden objects get more pixels; a zoomed-out pass and
closer looks at unsure boxes are options; see :mod:`mapper.perception.detector_passes`), merged by per-class
non-maximum suppression; each box becomes a mask by GrabCut (initialised with the
box, run on a small crop) or, when ``mask_method = "box"``, the filled box; when the view's
reconstruction is given the mask also keeps only pixels near the box's median depth. The masks carry the
class as ``Mask2D.hint_label``; the ``detector`` embedder turns that into the detection's label and
describes the region by its appearance (the ``classical`` HSV histogram) joined with a hashed embedding
of the label, so association never merges a "chair" with a "monitor".

Bundled model (the default, ``model = "bundled"``): MediaPipe's SSD-MobileNetV2 trained on 24 Open
Images V4 classes (person, chair, table, desk, computer monitor, laptop, computer mouse, book, box, mug,
coffee cup, bottle, ...), 300x300 input, fp16 TFLite, 9.8 MB, run with ``cv2.dnn``. It ships inside the
npm package ``@mediapipe/objectron`` 0.4.1675468480, whose declared licence is Apache-2.0. The weights
are not in the repository: ``make install`` fetches them once (``python -m mapper.perception.fetch_detector``
cuts them unchanged out of that package's asset bundle and checks their sha256) into the model folder;
the class names, licence and NOTICE are under ``mapper/perception/weights/``.

Own models: any ``cv2.dnn`` readable file (ONNX, TFLite, TensorFlow .pb + .pbtxt, ...) with
``output_format`` ``ssd-raw`` (box encodings + class logits over SSD anchors, like the bundled one) or
``detection-output`` (OpenCV's (1, 1, N, 7) ``[image, class, score, x0, y0, x1, y1]`` rows, what the
TensorFlow object detection zoo's frozen graphs give through ``cv2.dnn.readNet(pb, pbtxt)``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.perception.base import Detection, Mask2D, ViewGeometry, label_descriptor, unit
from mapper.perception.classical import AppearanceEmbedder
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
from mapper.perception.sam import BackendUnavailable

if TYPE_CHECKING:
    from mapper.geometry.contract import View

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
BUNDLED_LABELS = WEIGHTS_DIR / "ssd_mobilenetv2_oidv4_labels.txt"


def bundled_model() -> Path:
    """Where ``make install`` put the bundled model (see :mod:`mapper.perception.fetch_detector`)."""
    from mapper.perception.fetch_detector import model_path

    return model_path()


class DetectorConfig(BaseModel):
    """Options of the ``detector`` segmenter."""

    model_config = ConfigDict(extra="forbid")
    model: str = Field(
        default="bundled",
        description="'bundled' (SSD-MobileNetV2, 24 Open Images classes, Apache-2.0) or a path to a model file "
        "cv2.dnn reads (.onnx, .tflite, .pb, ...)",
    )
    model_config_file: Path | None = Field(
        default=None, description="second file some formats need, e.g. the .pbtxt of a TensorFlow frozen graph"
    )
    labels: Path | None = Field(
        default=None,
        description="class names, one per line, line k = class id k (line 0 is usually the background); "
        "default: the bundled model's",
    )
    output_format: Literal["ssd-raw", "detection-output"] = Field(
        default="ssd-raw",
        description="ssd-raw: outputs (1, A, 4) box encodings and (1, A, C) class logits over SSD anchors; "
        "detection-output: OpenCV's (1, 1, N, 7) rows [image, class, score, x0, y0, x1, y1] in [0, 1]",
    )
    input_size: int = Field(default=300, ge=32, le=2048, description="square network input side (pixels)")
    input_scale: float = Field(default=1.0 / 127.5, gt=0.0, description="pixel value multiplier")
    input_mean: float = Field(default=127.5, description="subtracted from pixel values before scaling")
    swap_rb: bool = Field(default=False, description="feed BGR instead of RGB")
    score_threshold: float = Field(default=0.4, ge=0.0, le=1.0, description="keep boxes at least this sure")
    extra_pass_threshold: float | None = Field(
        default=0.45, ge=0.0, le=1.0,
        description="score threshold of boxes from the extra passes (zoom-out, tiles, closer looks); each pass is "
        "one more chance of a false box, so a stricter threshold keeps precision (None: score_threshold)",
    )
    zoom_out: list[float] = Field(
        default_factory=list,
        description="extra passes, one per entry: the frame shrunk to this fraction (0-1] of the network input, "
        "centred on a neutral canvas (close, large objects fall inside the trained object sizes)",
    )
    tile_grid: int = Field(
        default=2, ge=0, le=4,
        description="extra zoomed-in passes: a tile_grid x tile_grid grid of overlapping tiles, each enlarged "
        "to the whole input (0 = none; each tile costs one more network run)",
    )
    tile_overlap: float = Field(default=0.25, ge=0.0, lt=1.0, description="overlap of neighbouring tiles (of a tile)")
    zoom_proposals: int = Field(
        default=0, ge=0, le=8,
        description="extra zoomed-in passes on this many of the frame pass's unsure boxes (score >= "
        "proposal_score, any class): a square crop around each, proposal_context times its size, is run again "
        "(each costs one more network run)",
    )
    proposal_score: float = Field(default=0.2, ge=0.0, le=1.0, description="least score of a box worth a closer look")
    proposal_context: float = Field(default=1.6, ge=1.0, le=4.0, description="crop side / box side of a closer look")
    tile_edge_margin: float = Field(
        default=0.05, ge=0.0, lt=0.5,
        description="a tile's box reaching this close (tile fraction) to an edge inside the frame is dropped: "
        "the object runs on into the next tile",
    )
    nms_iou: float = Field(default=0.45, ge=0.0, le=1.0, description="per-class non-maximum suppression IoU")
    max_detections: int = Field(default=20, ge=1, le=200, description="boxes kept per image, best first")
    min_box_frac: float = Field(default=0.002, ge=0.0, le=1.0, description="drop boxes smaller (image fraction)")
    max_box_frac: float = Field(default=0.9, gt=0.0, le=1.0, description="drop boxes larger (image fraction)")
    ignore_labels: list[str] = Field(
        default_factory=lambda: ["???", "background"], description="class names never reported"
    )
    mask_method: Literal["grabcut", "box"] = Field(
        default="grabcut", description="how a box becomes a mask: GrabCut (colour) or the filled box"
    )
    grabcut_side: int = Field(
        default=64, ge=16, le=512,
        description="GrabCut runs on the crop shrunk to at most this side (cost grows fast: 96 costs ~2.5x 64)",
    )
    grabcut_iterations: int = Field(default=3, ge=1, le=10, description="GrabCut iterations")
    depth_rel_tolerance: float = Field(
        default=0.25, gt=0.0,
        description="with geometry: keep mask pixels within this relative distance of the box's median depth",
    )


@dataclass(frozen=True)
class Box:
    """One detection: pixel corners (x0, y0, x1, y1), class id, label and score."""

    x0: float
    y0: float
    x1: float
    y1: float
    class_id: int
    label: str
    score: float


def ssd_anchors(
    input_size: int = 300,
    feature_maps: Sequence[int] = (19, 10, 5, 3, 2, 1),
    min_scale: float = 0.2,
    max_scale: float = 0.95,
    aspect_ratios: Sequence[float] = (1.0, 2.0, 0.5, 3.0, 1.0 / 3.0),
    reduce_lowest: bool = True,
) -> np.ndarray:
    """SSD anchors (A, 4) as normalised (cy, cx, h, w): row-major over each feature map, then per cell.

    The standard SSD-MobileNet layout (TensorFlow object detection API): layer scales spread linearly from
    ``min_scale`` to ``max_scale``; the lowest layer has 3 boxes (scale 0.1 ratio 1, and ratios 2, 1/2);
    the others one per aspect ratio plus one of ratio 1 at the geometric mean of this and the next scale.
    """
    n = len(feature_maps)
    scales = [min_scale + (max_scale - min_scale) * i / (n - 1) for i in range(n)] + [1.0]
    out = []
    for i, fm in enumerate(feature_maps):
        if i == 0 and reduce_lowest:
            specs = [(0.1, 1.0), (scales[0], 2.0), (scales[0], 0.5)]
        else:
            specs = [(scales[i], a) for a in aspect_ratios] + [(math.sqrt(scales[i] * scales[i + 1]), 1.0)]
        hw = np.array([[s / math.sqrt(a), s * math.sqrt(a)] for s, a in specs])
        c = (np.arange(fm) + 0.5) / fm
        cy, cx = np.meshgrid(c, c, indexing="ij")
        centres = np.stack([cy.ravel(), cx.ravel()], -1)
        cell = np.concatenate(
            [np.repeat(centres, len(specs), axis=0), np.tile(hw, (fm * fm, 1))], axis=1
        )
        out.append(cell)
    return np.concatenate(out).astype(np.float64)


def decode_ssd(
    encodings: np.ndarray, anchors: np.ndarray, scales: tuple[float, float, float, float] = (10.0, 10.0, 5.0, 5.0)
) -> np.ndarray:
    """Box encodings (A, 4) as (ty, tx, th, tw) over anchors (A, 4) (cy, cx, h, w) -> (A, 4) normalised
    (x0, y0, x1, y1)."""
    ty, tx, th, tw = (encodings[:, k] / scales[k] for k in range(4))
    acy, acx, ah, aw = anchors.T
    cy, cx = ty * ah + acy, tx * aw + acx
    h, w = np.exp(th) * ah, np.exp(tw) * aw
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)


def _read_tflite(path: Path) -> Any:
    """A TFLite model on OpenCV's classic engine where there is a choice (OpenCV 5), which keeps every
    layer's output readable by name."""
    engine = getattr(cv2.dnn, "ENGINE_CLASSIC", None)
    if engine is None:
        return cv2.dnn.readNetFromTFLite(str(path))
    return cv2.dnn.readNetFromTFLite(str(path), engine=engine)


def load_labels(path: Path) -> list[str]:
    """Class names, one per line (line k = class k), blank lines kept as empty names."""
    try:
        return [line.strip() for line in Path(path).read_text(encoding="utf-8").splitlines()]
    except OSError as e:
        raise BackendUnavailable(f"cannot read detector labels {path}: {e.strerror or e}") from None


class DetectorSegmenter:
    """Labelled boxes from an SSD detector, turned into masks (see module docstring)."""

    name = "detector"
    description = "closed-set detector (bundled SSD-MobileNetV2, 24 Open Images classes) + GrabCut masks, CPU"

    def __init__(self, **opts: object) -> None:
        self.config = cfg = DetectorConfig.model_validate(opts)
        model = bundled_model() if cfg.model == "bundled" else Path(cfg.model).expanduser()
        labels = cfg.labels or (BUNDLED_LABELS if cfg.model == "bundled" else None)
        if not model.is_file():
            raise BackendUnavailable(
                f"detector model {model} does not exist"
                + (": the bundled weights are fetched once at install time: make install, or "
                   "python -m mapper.perception.fetch_detector" if cfg.model == "bundled" else "")
            )
        if labels is None:
            raise BackendUnavailable("a detector model of your own needs its class names: set `labels` to a text file")
        self.labels = load_labels(labels)
        try:
            if cfg.model_config_file is not None:
                self._net = cv2.dnn.readNet(str(model), str(cfg.model_config_file))
            elif model.suffix == ".tflite":
                self._net = _read_tflite(model)
            else:
                self._net = cv2.dnn.readNet(str(model))
        except cv2.error as e:
            msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
            raise BackendUnavailable(f"OpenCV cannot load detector model {model}: {msg}") from None
        # TensorFlow SSDs: read the per-layer predictor convolutions and flatten them ourselves (OpenCV 5.0
        # scrambles the box encodings in its reshape + concat of NHWC tensors; the class logits survive).
        names = list(self._net.getLayerNames())
        self._heads = [
            sorted((n for n in names if n.startswith("BoxPredictor_") and f"/{kind}/BiasAdd" in n),
                   key=lambda n: int(n.split("/", 1)[0].rsplit("_", 1)[1]))
            for kind in ("BoxEncodingPredictor", "ClassPredictor")
        ]
        self._anchors = ssd_anchors(cfg.input_size) if cfg.output_format == "ssd-raw" else None

    def windows(self, width: int, height: int) -> list[Window]:
        """The passes run on a ``width`` x ``height`` image: the frame, then zoom-outs, then tiles."""
        cfg, side = self.config, self.config.input_size
        wins = [frame_window(width, height, side)]
        wins += [zoom_out_window(width, height, side, f) for f in cfg.zoom_out]
        if cfg.tile_grid >= 2:
            wins += tile_windows(width, height, side, cfg.tile_grid, cfg.tile_overlap)
        return wins

    def detect(self, image: np.ndarray) -> list[Box]:
        """Labelled boxes of an (H, W, 3) uint8 RGB image, best first, after per-class NMS over all passes."""
        cfg = self.config
        H, W = image.shape[:2]
        extra = cfg.score_threshold if cfg.extra_pass_threshold is None else cfg.extra_pass_threshold
        floor = min(cfg.score_threshold, cfg.proposal_score) if cfg.zoom_proposals else cfg.score_threshold
        found = [self._detect_window(image, w, floor if w.kind == "frame" else extra) for w in self.windows(W, H)]
        if cfg.zoom_proposals:
            b, c, s = found[0]
            for k in proposals(b, s, cfg.zoom_proposals, cfg.nms_iou, W, H, cfg.proposal_context):
                win = crop_window(b[k], cfg.proposal_context, W, H, cfg.input_size)
                found.append(self._detect_window(image, win, extra))
            sure = s >= cfg.score_threshold
            found[0] = (b[sure], c[sure], s[sure])
        boxes = np.concatenate([f[0] for f in found])
        return self._select(boxes, np.concatenate([f[1] for f in found]), np.concatenate([f[2] for f in found]), W, H)

    def _detect_window(self, image: np.ndarray, win: Window, floor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Candidate boxes (image pixels), classes and scores of one pass (scores at least ``floor``)."""
        cfg = self.config
        H, W = image.shape[:2]
        boxes, probs = self._run_window(image, win)
        cls = probs.argmax(axis=1)
        scores = probs[np.arange(len(cls)), cls]
        keep = scores >= floor
        boxes, cls, scores = boxes[keep], cls[keep], scores[keep]
        if win.kind in ("tile", "crop"):
            rx0, ry0, rx1, ry1 = win.region
            margin = cfg.tile_edge_margin * max(rx1 - rx0, ry1 - ry0)
            whole = np.array([not cut_by_inner_edge(b, win, W, H, margin) for b in boxes], dtype=bool)
            boxes, cls, scores = boxes[whole], cls[whole], scores[whole]
        return boxes, cls, scores

    def _run_window(self, image: np.ndarray, win: Window) -> tuple[np.ndarray, np.ndarray]:
        """One network run on the window: every candidate box (image pixels) and its class scores (N, C),
        background zeroed."""
        cfg, side = self.config, self.config.input_size
        fill = float(np.clip(cfg.input_mean, 0, 255))  # the canvas reads as zero input
        net_in = cv2.warpAffine(np.ascontiguousarray(image), win.matrix(pixel_centres=True), (side, side),
                                flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(fill,) * 3)
        blob = cv2.dnn.blobFromImage(net_in, scalefactor=cfg.input_scale, size=(side, side),
                                     mean=(cfg.input_mean,) * 3, swapRB=cfg.swap_rb, crop=False)
        self._net.setInput(blob)
        if cfg.output_format == "ssd-raw":
            boxes, probs = self._raw_outputs(self._ssd_outputs())
        else:
            boxes, cls, scores = detection_output_rows(np.asarray(self._net.forward()))
            probs = np.zeros((len(cls), max(len(self.labels), int(cls.max(initial=0)) + 1)))
            probs[np.arange(len(cls)), np.clip(cls, 0, None)] = scores
        probs[:, 0] = 0.0  # background
        return win.to_image(boxes * side), probs

    def class_evidence(self, image: np.ndarray, box: Sequence[float], min_iou: float = 0.5) -> dict[str, float]:
        """For checking what the model makes of a known object: over every pass and every candidate box
        overlapping ``box`` (image pixels) by at least ``min_iou``, each class's best score, best first."""
        H, W = image.shape[:2]
        best = np.zeros(len(self.labels))
        for win in self.windows(W, H):
            boxes, probs = self._run_window(image, win)
            near = iou_matrix(boxes, np.asarray(box, np.float64).reshape(1, 4))[:, 0] >= min_iou
            if near.any():
                n = min(len(best), probs.shape[1])
                best[:n] = np.maximum(best[:n], probs[near, :n].max(axis=0))
        order = np.argsort(-best)
        return {self.labels[k]: round(float(best[k]), 3) for k in order if best[k] > 0}

    def _ssd_outputs(self) -> list[np.ndarray]:
        """Box encodings (A, 4) and class logits (A, C)."""
        enc_names, cls_names = self._heads
        if not enc_names or len(enc_names) != len(cls_names):
            return [np.asarray(o) for o in self._net.forward(self._net.getUnconnectedOutLayersNames())]
        outs = [np.asarray(o) for o in self._net.forward(enc_names + cls_names)]
        encs, logits = outs[: len(enc_names)], outs[len(enc_names) :]
        per_cell = [e.shape[1] // 4 for e in encs]  # NCHW: channels = anchors per cell x 4
        return [
            np.concatenate([e.transpose(0, 2, 3, 1).reshape(-1, 4) for e in encs]),
            np.concatenate([c.transpose(0, 2, 3, 1).reshape(-1, c.shape[1] // k)
                            for c, k in zip(logits, per_cell, strict=True)]),
        ]

    def _raw_outputs(self, outs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Decoded boxes (A, 4, normalised) and class probabilities (A, C)."""
        assert self._anchors is not None
        n_anchor = len(self._anchors)
        flat = [np.asarray(o).reshape(n_anchor, -1) for o in outs]
        enc = next((o for o in flat if o.shape[1] == 4), None)
        logits = next((o for o in flat if o.shape[1] != 4), None)
        if enc is None or logits is None:
            raise RuntimeError(f"detector outputs {[o.shape for o in outs]} are not SSD box encodings + class logits")
        return decode_ssd(enc, self._anchors), 1.0 / (1.0 + np.exp(-logits))

    def _select(self, boxes: np.ndarray, cls: np.ndarray, scores: np.ndarray, W: int, H: int) -> list[Box]:
        """Boxes (already above their pass's threshold) of reportable classes and sizes, per-class NMS."""
        cfg = self.config
        names = [self.labels[c] if 0 <= c < len(self.labels) else str(c) for c in cls]
        wh = np.clip(boxes[:, 2:] - boxes[:, :2], 0, None)
        frac = wh[:, 0] * wh[:, 1] / max(W * H, 1)
        ok = (frac >= cfg.min_box_frac) & (frac <= cfg.max_box_frac)
        ok &= np.array([bool(n) and n not in cfg.ignore_labels for n in names], dtype=bool)
        idx = np.nonzero(ok)[0]
        found: list[Box] = []
        for k in nms(boxes[idx], scores[idx], cls[idx], cfg.nms_iou):
            j = idx[k]
            x0, y0, x1, y1 = (float(np.clip(v, 0, lim)) for v, lim in zip(boxes[j], (W, H, W, H), strict=True))
            found.append(Box(x0, y0, x1, y1, class_id=int(cls[j]), label=names[j], score=float(scores[j])))
        found.sort(key=lambda b: -b.score)
        return found[: cfg.max_detections]

    def segment(self, view: View, geometry: ViewGeometry | None = None) -> list[Mask2D]:
        return self.masks(view.image, self.detect(view.image), geometry)

    def masks(self, image: np.ndarray, boxes: Sequence[Box], geometry: ViewGeometry | None = None) -> list[Mask2D]:
        """One mask per box (in order; boxes whose mask comes out empty are left out)."""
        out = []
        for k, b in enumerate(boxes):
            mask = box_mask(image, b, self.config)
            if geometry is not None:
                mask = depth_gate(mask, geometry, self.config.depth_rel_tolerance)
            if mask.any():
                out.append(Mask2D(mask=mask, instance_key=k + 1, hint_label=b.label, score=b.score))
        return out


def detection_output_rows(out: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV DetectionOutput rows (..., 7) ``[image, class, score, x0, y0, x1, y1]`` -> boxes, classes,
    scores."""
    rows = out.reshape(-1, 7)
    return rows[:, 3:7].astype(np.float64), rows[:, 1].astype(int), rows[:, 2].astype(np.float64)


def box_mask(image: np.ndarray, box: Box, cfg: DetectorConfig) -> np.ndarray:
    """(H, W) bool mask of the object in ``box``: GrabCut on the box's crop, or the filled box."""
    H, W = image.shape[:2]
    x0, y0 = int(np.clip(math.floor(box.x0), 0, W - 1)), int(np.clip(math.floor(box.y0), 0, H - 1))
    x1, y1 = int(np.clip(math.ceil(box.x1), x0 + 1, W)), int(np.clip(math.ceil(box.y1), y0 + 1, H))
    mask = np.zeros((H, W), dtype=bool)
    if cfg.mask_method == "box" or (x1 - x0) < 8 or (y1 - y0) < 8:
        mask[y0:y1, x0:x1] = True
        return mask
    # crop with a margin so GrabCut sees background around the box
    mx, my = max(2, (x1 - x0) // 8), max(2, (y1 - y0) // 8)
    cx0, cy0, cx1, cy1 = max(0, x0 - mx), max(0, y0 - my), min(W, x1 + mx), min(H, y1 + my)
    crop = image[cy0:cy1, cx0:cx1]
    s = min(1.0, cfg.grabcut_side / max(crop.shape[:2]))  # never enlarged: that adds cost, not detail
    small = cv2.resize(crop, (max(8, round(crop.shape[1] * s)), max(8, round(crop.shape[0] * s))),
                       interpolation=cv2.INTER_AREA)
    sh, sw = small.shape[:2]
    rx0, ry0 = int((x0 - cx0) * sw / crop.shape[1]), int((y0 - cy0) * sh / crop.shape[0])
    rx1, ry1 = int(math.ceil((x1 - cx0) * sw / crop.shape[1])), int(math.ceil((y1 - cy0) * sh / crop.shape[0]))
    rect = (rx0, ry0, max(2, min(sw, rx1) - rx0), max(2, min(sh, ry1) - ry0))
    gc = np.zeros((sh, sw), np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(cv2.cvtColor(small, cv2.COLOR_RGB2BGR), gc, rect, bgd, fgd, cfg.grabcut_iterations,
                    cv2.GC_INIT_WITH_RECT)
    except cv2.error:  # degenerate crop (one colour): fall back to the box
        mask[y0:y1, x0:x1] = True
        return mask
    fg = ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)).astype(np.uint8)
    fg = cv2.resize(fg, (crop.shape[1], crop.shape[0]), interpolation=cv2.INTER_NEAREST).astype(bool)
    mask[cy0:cy1, cx0:cx1] = fg
    inside = np.zeros_like(mask)
    inside[y0:y1, x0:x1] = True
    mask &= inside
    if mask.sum() < 0.15 * (x1 - x0) * (y1 - y0):  # GrabCut lost the object: the box is the better guess
        return inside
    return mask


def depth_gate(mask: np.ndarray, geometry: ViewGeometry, rel_tol: float) -> np.ndarray:
    """``mask`` at the geometry's resolution, keeping pixels whose depth is within ``rel_tol`` of the
    mask's median confident depth (drops the background GrabCut left inside the box)."""
    from mapper.fusion import resize_mask

    h, w = geometry.depth_m.shape
    m = resize_mask(mask, h, w)
    d = geometry.depth_m
    valid = m & np.isfinite(d) & (d > 0) & (geometry.confidence > 0)
    if valid.sum() < 4:
        return m
    med = float(np.median(d[valid]))
    return valid & (np.abs(d - med) <= rel_tol * med)


class DetectorEmbedderConfig(BaseModel):
    """Options of the ``detector`` embedder."""

    model_config = ConfigDict(extra="forbid")
    label_weight: float = Field(
        default=0.7, ge=0.0, le=1.0,
        description="share of the descriptor given to the label (the rest is the HSV appearance histogram)",
    )
    unlabelled: str = Field(default="object", description="label of masks that carry none")
    label_dim: int = Field(default=128, ge=8, le=4096, description="length of the hashed label embedding")


class DetectorEmbedder:
    """Labels from the masks' ``hint_label`` (the detector's class), confidence = the box score; the
    descriptor joins the label embedding and the appearance histogram."""

    name = "detector"
    description = "labels from the detector segmenter's classes + appearance descriptor (no weights)"

    def __init__(self, **opts: object) -> None:
        self.config = DetectorEmbedderConfig.model_validate(opts)
        self._appearance = AppearanceEmbedder()

    def embed(self, view: View, masks: Sequence[Mask2D]) -> list[Detection]:
        cfg = self.config
        described = self._appearance.embed(view, masks)  # in order, empty masks dropped
        pairs, j = [], 0
        for m in masks:
            if j < len(described) and described[j].mask is m.mask:
                pairs.append((m, described[j]))
                j += 1
        out = []
        for m, d in pairs:
            label = m.hint_label or cfg.unlabelled
            desc = np.concatenate(
                [math.sqrt(cfg.label_weight) * label_descriptor(label, cfg.label_dim),
                 math.sqrt(1.0 - cfg.label_weight) * d.descriptor]
            )
            out.append(Detection(mask=d.mask, label=label, confidence=float(np.clip(m.score, 0.0, 1.0)),
                                 descriptor=unit(desc), instance_key=d.instance_key))
        return out


def draw_boxes(image: np.ndarray, boxes: Sequence[Box], masks: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """A BGR copy of the RGB ``image`` with masks tinted and boxes + ``label score`` drawn (for bench output)."""
    vis = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    rng = np.random.default_rng(7)
    for k, b in enumerate(boxes):
        colour = tuple(int(c) for c in rng.integers(60, 255, 3))
        if masks is not None and k < len(masks):
            m = masks[k] if masks[k].shape == vis.shape[:2] else cv2.resize(
                masks[k].astype(np.uint8), vis.shape[1::-1], interpolation=cv2.INTER_NEAREST).astype(bool)
            vis[m] = (0.55 * vis[m] + 0.45 * np.array(colour)).astype(np.uint8)
        p0, p1 = (int(b.x0), int(b.y0)), (int(b.x1), int(b.y1))
        cv2.rectangle(vis, p0, p1, colour, 2)
        text = f"{b.label} {b.score:.2f}"
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        ty = max(th + 2, p0[1])
        cv2.rectangle(vis, (p0[0], ty - th - 3), (p0[0] + tw + 2, ty), colour, -1)
        cv2.putText(vis, text, (p0[0] + 1, ty - 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return vis


def describe(boxes: Sequence[Box]) -> list[dict[str, Any]]:
    """JSON-ready rows of boxes."""
    return [{"label": b.label, "score": round(b.score, 3), "box": [round(v, 1) for v in (b.x0, b.y0, b.x1, b.y1)]}
            for b in boxes]
