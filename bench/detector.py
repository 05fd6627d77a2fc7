"""``argus bench detector``: the ``detector`` segmenter on the real RGB-D frames, end to end to 3D nodes.

Per frame: the bundled detector finds labelled boxes, GrabCut + depth gating make masks, the ``detector``
embedder labels them, and the recorded depth and poses lift and fuse them into nodes (the fusion code the
mapper runs). Geometry is the RECORDED depth here, so the figures are about perception and fusion, not
RGB-only depth. Saved for checking by eye: every frame with boxes, labels and masks
(``<sequence>-frame-NNNNNN.png``) and the first and last frames with every node's centroid projected and
labelled (``<sequence>-nodes-*.png``). Where the sequence has object masks (label-fusion's ``segm.png``)
each node is also matched to the nearest true object centroid, each box to the true object it covers, and
each true object gets the model's best class scores on it (what the model makes of it, found or not).
Sequences: label-fusion's close-range shelf, the TUM desk and the HoloLens office (``../shared/data``).

    argus bench detector --out bench_out/detector
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import ValidationError

from bench.report import key_values
from bench.video import DATA_ROOT, Frame, available, load_sequence, read_image
from mapper.fusion import FusionConfig, ObjectMap, lift_detections
from mapper.perception.base import ViewGeometry
from mapper.perception.detector import Box, DetectorEmbedder, DetectorSegmenter, draw_boxes
from mapper.perception.detector_passes import iou_matrix

SEQUENCES = ("labelfusion", "tum-fr1-xyz", "hololens-dvmvs")


def view_geometry(frame: Frame) -> ViewGeometry:
    """Recorded depth back-projected with the recorded pose (invalid depth: confidence 0)."""
    K = frame.view.intrinsics.K() if frame.view.intrinsics is not None else None
    assert K is not None
    h, w = frame.depth_m.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = frame.depth_m.astype(np.float64)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    T = np.asarray(frame.T_true)
    world = cam @ T[:3, :3].T + T[:3, 3]
    return ViewGeometry(points_world=world.astype(np.float32), depth_m=np.where(frame.valid, z, 0).astype(np.float32),
                        confidence=frame.valid.astype(np.float32))


def true_objects(base: Path, frames: Sequence[Frame]) -> dict[int, np.ndarray]:
    """Object id -> 3D centroid from the sequence's object masks (``segm.png``) and recorded depth."""
    pts: dict[int, list[np.ndarray]] = {}
    for f in frames:
        p = base / "frames" / f"frame-{f.view.seq:06d}.segm.png"
        if not p.is_file():
            continue
        seg = read_image(p, cv2.IMREAD_UNCHANGED)
        g = view_geometry(f)
        for k in np.unique(seg):
            sel = (seg == k) & f.valid
            if k > 0 and sel.sum() > 50:
                pts.setdefault(int(k), []).append(g.points_world[sel])
    return {k: np.median(np.concatenate(v), axis=0) for k, v in pts.items()}


def true_boxes(base: Path, frame: Frame) -> dict[int, tuple[int, int, int, int]]:
    """Object id -> pixel bounding box (x0, y0, x1, y1) in this frame's object masks (none without masks)."""
    p = base / "frames" / f"frame-{frame.view.seq:06d}.segm.png"
    if not p.is_file():
        return {}
    seg = read_image(p, cv2.IMREAD_UNCHANGED)
    out = {}
    for k in np.unique(seg):
        ys, xs = np.nonzero(seg == k)
        if k > 0 and len(xs) > 50:
            out[int(k)] = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    return out


def truth_rows(seg: DetectorSegmenter, image: np.ndarray, boxes: Sequence[Box],
               truth: dict[int, tuple[int, int, int, int]]) -> tuple[list[int], dict[int, dict[str, Any]]]:
    """Each box's true object (IoU >= 0.5 with its bounding box; 0 = none), and per true object the labels
    of the boxes on it and the model's best score per class over every candidate box on it (what the model
    makes of the object, found or not)."""
    if not truth:
        return [0] * len(boxes), {}
    ids = list(truth)
    iou = iou_matrix(np.array([[b.x0, b.y0, b.x1, b.y1] for b in boxes]).reshape(-1, 4), np.array(list(truth.values())))
    on = [ids[int(np.argmax(r))] if r.max(initial=0) >= 0.5 else 0 for r in iou]
    per = {k: {"box": list(t), "labels": [b.label for b, o in zip(boxes, on, strict=True) if o == k],
               "evidence": dict(list(seg.class_evidence(image, t).items())[:3])} for k, t in truth.items()}
    return on, per


def project(point: np.ndarray, frame: Frame) -> tuple[int, int] | None:
    K = frame.view.intrinsics.K() if frame.view.intrinsics is not None else np.eye(3)
    T = np.linalg.inv(np.asarray(frame.T_true))
    c = T[:3, :3] @ point + T[:3, 3]
    if c[2] <= 0.05:
        return None
    u, v = K[0, 0] * c[0] / c[2] + K[0, 2], K[1, 1] * c[1] / c[2] + K[1, 2]
    return int(round(u)), int(round(v))


def draw_nodes(frame: Frame, nodes: Sequence[dict[str, Any]]) -> np.ndarray:
    vis = cv2.cvtColor(frame.view.image, cv2.COLOR_RGB2BGR)
    for n in nodes:
        uv = project(np.array(n["centroid"]), frame)
        if uv is None:
            continue
        cv2.drawMarker(vis, uv, (0, 0, 255), cv2.MARKER_CROSS, 22, 3)
        cv2.putText(vis, f"{n['id']} {n['label']}", (uv[0] + 8, uv[1] - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                    (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(vis, f"{n['id']} {n['label']}", (uv[0] + 8, uv[1] - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return vis


def run_sequence(name: str, out: Path | None, seg: DetectorSegmenter, emb: DetectorEmbedder) -> dict[str, Any]:
    frames, _ = load_sequence(name)
    fusion = FusionConfig(min_z_m=-1e9, max_z_m=1e9)  # these worlds are not z-up rooms
    objects = ObjectMap(fusion)
    per_frame: list[dict[str, Any]] = []
    t_detect: list[float] = []
    t_masks: list[float] = []
    for f in frames:
        t0 = time.perf_counter()
        boxes = seg.detect(f.view.image)
        t1 = time.perf_counter()
        masks = seg.masks(f.view.image, boxes, view_geometry(f))
        t_detect.append(t1 - t0)
        t_masks.append(time.perf_counter() - t1)
        dets = emb.embed(f.view, masks)
        g = view_geometry(f)
        objs, stats = lift_detections(dets, g.points_world, g.confidence, g.depth_m, fusion)
        objects.integrate(objs, name, f.view.seq)
        on, per_object = truth_rows(seg, f.view.image, boxes, true_boxes(DATA_ROOT / name, f))
        per_frame.append({"seq": f.view.seq, "boxes": [
            {"label": b.label, "score": round(b.score, 3), "box": [round(x, 1) for x in (b.x0, b.y0, b.x1, b.y1)],
             **({"true_object": o} if per_object else {})} for b, o in zip(boxes, on, strict=True)],
            "lifted": stats.lifted, **({"true_objects": per_object} if per_object else {})})
        if out is not None:
            vis = draw_boxes(f.view.image, boxes, [m.mask for m in masks] if len(masks) == len(boxes) else None)
            cv2.imwrite(str(out / f"{name}-frame-{f.view.seq:06d}.png"), vis)
    nodes = []
    for nid, n in sorted(objects.nodes.items()):
        label = max(n.label_votes.items(), key=lambda kv: kv[1])[0]
        nodes.append({"id": nid, "label": label, "centroid": [round(float(x), 4) for x in np.median(n.points, 0)],
                      "observations": n.observations, "points": len(n.points)})
    truth = true_objects(DATA_ROOT / name, frames)
    for node in nodes:
        if truth:
            k, c = min(truth.items(), key=lambda kv: float(np.linalg.norm(kv[1] - np.array(node["centroid"]))))
            node["nearest_true_object"] = k
            node["distance_to_it_m"] = round(float(np.linalg.norm(c - np.array(node["centroid"]))), 3)
    if out is not None:
        for tag, f in (("first", frames[0]), ("last", frames[-1])):
            cv2.imwrite(str(out / f"{name}-nodes-{tag}.png"), draw_nodes(f, nodes))
    return {
        "sequence": name, "frames": len(frames), "per_frame": per_frame, "nodes": nodes,
        "true_objects": {k: [round(float(x), 4) for x in v] for k, v in truth.items()},
        "detect_s_median": float(np.median(t_detect)), "masks_s_median": float(np.median(t_masks)),
        "frame_s_median": float(np.median(np.add(t_detect, t_masks))),
        "boxes_per_frame": float(np.mean([len(p["boxes"]) for p in per_frame])),
    }


def markdown(report: dict[str, Any]) -> str:
    lines = ["# Detector benchmark (bundled SSD-MobileNetV2, 24 Open Images classes, CPU)", "",
             "Recorded depth and poses lift the detections; check labels by eye in the saved images.", ""]
    for r in report["sequences"]:
        lines += [f"## {r['sequence']} ({r['frames']} frames)", "",
                  f"boxes per frame {r['boxes_per_frame']:.1f}; detection {1000 * r['detect_s_median']:.0f} ms, "
                  f"masks {1000 * r['masks_s_median']:.0f} ms per frame (median)", "",
                  "| node | label | observations | centroid (m) | nearest true object, distance |",
                  "| --- | --- | --- | --- | --- |"]
        for n in r["nodes"]:
            near = f"{n['nearest_true_object']}, {n['distance_to_it_m']:.3f} m" if "nearest_true_object" in n else "-"
            lines.append(f"| {n['id']} | {n['label']} | {n['observations']} | {n['centroid']} | {near} |")
        lines.append("")
        lines += truth_summary(r["per_frame"])
    return "\n".join(lines)


def truth_summary(per_frame: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: per true object, the frames with a box on it, its labels, and the model's best classes."""
    objects: dict[int, list[dict[str, Any]]] = {}
    for pf in per_frame:
        for k, row in pf.get("true_objects", {}).items():
            objects.setdefault(int(k), []).append(row)
    if not objects:
        return []
    stray = [b["label"] for pf in per_frame for b in pf["boxes"] if b.get("true_object") == 0]
    lines = ["| true object | frames with a box on it | labels given | best classes on it (median score) |",
             "| --- | --- | --- | --- |"]
    for k, rows in sorted(objects.items()):
        labels = sorted({lab for r in rows for lab in r["labels"]})
        scores: dict[str, list[float]] = {}
        for r in rows:
            for lab, v in r["evidence"].items():
                scores.setdefault(lab, []).append(v)
        top = sorted(((float(np.median(v + [0.0] * (len(rows) - len(v)))), lab) for lab, v in scores.items()),
                     reverse=True)[:3]
        lines.append(f"| {k} | {sum(bool(r['labels']) for r in rows)}/{len(rows)} | {', '.join(labels) or '-'} | "
                     + ", ".join(f"{lab} {v:.2f}" for v, lab in top) + " |")
    lines += ["", f"boxes on no true object: {len(stray)} ({', '.join(sorted(set(stray))) or '-'})", ""]
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="argus bench detector", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=None, help="directory for detector.json, detector.md and images")
    p.add_argument("--quick", action="store_true", help="accepted for `argus bench all` (the run is already short)")
    p.add_argument("--sequences", nargs="+", default=list(SEQUENCES), choices=SEQUENCES, help="real sequences")
    p.add_argument("--score-threshold", type=float, default=None, help="detector score threshold (default: its own)")
    p.add_argument("--threads", type=int, default=None, help="OpenCV threads (default: OpenCV's choice)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a detector option (DetectorConfig field; VALUE as JSON, e.g. tile_grid=0 or zoom_out=[0.6])")
    a = p.parse_args(list(argv) if argv is not None else None)
    opts = {} if a.score_threshold is None else {"score_threshold": a.score_threshold}
    opts.update(key_values(a.option, "--option", p.error))
    if a.threads is not None:
        cv2.setNumThreads(a.threads)
    try:
        seg, emb = DetectorSegmenter(**opts), DetectorEmbedder()
    except ValidationError as e:
        p.error(f"detector options: {e.errors()[0]['loc']}: {e.errors()[0]['msg']}")
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
    todo = [s for s in a.sequences if available(s)]
    for s in sorted(set(a.sequences) - set(todo)):
        print(f"argus bench detector: {s} not found under {DATA_ROOT}, skipped")
    report = {"detector": seg.description, "config": seg.config.model_dump(mode="json"),
              "sequences": [run_sequence(s, a.out, seg, emb) for s in todo]}
    md = markdown(report)
    print(md)
    if a.out is not None:
        (a.out / "detector.json").write_text(json.dumps(report, indent=1))
        (a.out / "detector.md").write_text(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
