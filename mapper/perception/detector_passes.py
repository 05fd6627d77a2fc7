"""Test-time passes of the ``detector``: which views of one image the network sees, and merging their boxes.

A square-input detector sees the whole frame squeezed into its input (the ``frame`` pass). Extra passes
show it the same image at other scales: ``zoom-out`` puts the frame, smaller, in the middle of a neutral
canvas (large, close objects then fall inside the object sizes the detector was trained on), ``tile``
passes show overlapping parts of the frame enlarged (small or far objects get more input pixels). Each
pass is an axis-aligned map from image pixels to network-input pixels, ``q = p * (sx, sy) + (tx, ty)``;
boxes found in a pass are mapped back through its inverse, boxes cut by a tile's inner edge are dropped
(the object runs on into the next tile, where another pass sees it whole), and the passes' boxes are merged
by per-class non-maximum suppression. All pure (no OpenCV network here), so each piece is tested exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Window:
    """One pass: image pixel p -> network-input pixel ``p * (sx, sy) + (tx, ty)``; ``region`` is the part of
    the image (x0, y0, x1, y1) the pass shows, ``kind`` is ``frame``, ``zoom-out`` or ``tile``."""

    sx: float
    sy: float
    tx: float
    ty: float
    region: tuple[float, float, float, float]
    kind: str

    def matrix(self, pixel_centres: bool = False) -> np.ndarray:
        """The 2x3 affine matrix. Coordinates are continuous (pixel k spans [k, k + 1]); with
        ``pixel_centres`` the matrix maps pixel indices instead (pixel k's centre is k + 0.5), which is what
        ``cv2.warpAffine`` samples, so a warp of the frame window equals ``cv2.resize``."""
        tx, ty = self.tx, self.ty
        if pixel_centres:
            tx, ty = tx + 0.5 * self.sx - 0.5, ty + 0.5 * self.sy - 0.5
        return np.array([[self.sx, 0.0, tx], [0.0, self.sy, ty]])

    def to_image(self, boxes_input: np.ndarray) -> np.ndarray:
        """(N, 4) boxes (x0, y0, x1, y1) in network-input pixels -> image pixels."""
        b = np.asarray(boxes_input, dtype=np.float64).reshape(-1, 4)
        s = np.array([self.sx, self.sy, self.sx, self.sy])
        t = np.array([self.tx, self.ty, self.tx, self.ty])
        return (b - t) / s


def frame_window(width: int, height: int, side: int) -> Window:
    """The whole frame stretched onto the ``side`` x ``side`` input (what a single-pass detector does)."""
    return Window(side / width, side / height, 0.0, 0.0, (0.0, 0.0, float(width), float(height)), "frame")


def zoom_out_window(width: int, height: int, side: int, fraction: float) -> Window:
    """The whole frame stretched onto the centred ``fraction`` of the input; the rest is neutral canvas."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"zoom-out fraction must be in (0, 1], got {fraction}")
    off = (1.0 - fraction) * side / 2.0
    return Window(fraction * side / width, fraction * side / height, off, off,
                  (0.0, 0.0, float(width), float(height)), "zoom-out")


def tile_windows(width: int, height: int, side: int, grid: int, overlap: float) -> list[Window]:
    """``grid`` x ``grid`` tiles covering the frame, neighbours overlapping by ``overlap`` of a tile, each
    stretched onto the whole input (row-major)."""
    if grid < 1 or not 0.0 <= overlap < 1.0:
        raise ValueError(f"tiles need grid >= 1 and overlap in [0, 1), got {grid}, {overlap}")
    tw, th = width / (grid - (grid - 1) * overlap), height / (grid - (grid - 1) * overlap)
    out = []
    for r in range(grid):
        for c in range(grid):
            x0, y0 = c * tw * (1.0 - overlap), r * th * (1.0 - overlap)
            sx, sy = side / tw, side / th
            out.append(Window(sx, sy, -x0 * sx, -y0 * sy, (x0, y0, x0 + tw, y0 + th), "tile"))
    return out


def cut_by_inner_edge(box: Sequence[float], window: Window, width: int, height: int, margin: float) -> bool:
    """Whether ``box`` (image pixels) reaches within ``margin`` pixels of an edge of the window's region
    that is not also an edge of the image (the object probably goes on beyond the tile)."""
    x0, y0, x1, y1 = box
    rx0, ry0, rx1, ry1 = window.region
    return bool((rx0 > 0.5 and x0 <= rx0 + margin) or (ry0 > 0.5 and y0 <= ry0 + margin)
                or (rx1 < width - 0.5 and x1 >= rx1 - margin) or (ry1 < height - 0.5 and y1 >= ry1 - margin))


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) intersection over union of (N, 4) and (M, 4) boxes (x0, y0, x1, y1)."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    ix = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = ix * iy
    area_a = np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float) -> list[int]:
    """Greedy per-class non-maximum suppression: indices kept, best score first (ties: lower index first).
    A box is dropped when a better box of its class overlaps it by more than ``iou``."""
    boxes, scores, classes = np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(scores), np.asarray(classes)
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    overlap = iou_matrix(boxes, boxes)
    kept: list[int] = []
    for i in order:
        if not any(classes[k] == classes[i] and overlap[i, k] > iou for k in kept):
            kept.append(i)
    return kept


def crop_window(box: Sequence[float], context: float, width: int, height: int, side: int) -> Window:
    """A square window centred on ``box`` (image pixels), ``context`` times its longer side, enlarged onto
    the whole input; parts outside the frame are neutral canvas."""
    x0, y0, x1, y1 = (float(v) for v in box)
    span = max(x1 - x0, y1 - y0, 1.0) * context
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    s = side / span
    left, top = cx - span / 2.0, cy - span / 2.0
    region = (max(0.0, left), max(0.0, top), min(float(width), left + span), min(float(height), top + span))
    return Window(s, s, -left * s, -top * s, region, "crop")


def proposals(boxes: np.ndarray, scores: np.ndarray, count: int, iou: float, width: int, height: int,
              context: float, min_side_frac: float = 0.05) -> list[int]:
    """Indices of up to ``count`` boxes worth a closer look, best first: class-agnostic NMS at ``iou``, and only
    boxes whose ``context`` crop is smaller than the frame (a bigger crop shows nothing new) and whose longer
    side is at least ``min_side_frac`` of the frame's."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    longest = np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
    frame = max(width, height)
    fits = (longest * context < 0.9 * min(width, height)) & (longest >= min_side_frac * frame)
    idx = np.nonzero(fits)[0]
    kept = nms(b[idx], np.asarray(scores)[idx], np.zeros(len(idx), dtype=int), iou)
    return [int(idx[k]) for k in kept[:count]]
