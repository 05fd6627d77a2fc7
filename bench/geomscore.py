"""Depth scoring shared by the geometry benchmarks: AbsRel, delta < 1.25, coverage and scale on confident pixels."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from mapper.geometry.contract import CONFIDENT


@dataclass
class DepthScore:
    absrel: float  # median over confident pixels with ground truth
    delta125: float
    confident: float  # confident pixels / pixels with ground truth
    n_gt: int
    scale: float = float("nan")  # median of estimated / true depth over the scored pixels (1 = right scale)


@dataclass
class ScenarioResult:
    name: str
    frames: list[dict[str, Any]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        f = [x for x in self.frames if x.get("n_gt", 0) > 0]
        ab = [x["absrel"] for x in f if np.isfinite(x["absrel"])]
        return {
            "scenario": self.name,
            "n_keyframes": len(f),
            "median_absrel": float(np.median(ab)) if ab else float("nan"),
            "median_delta125": float(np.median([x["delta125"] for x in f if np.isfinite(x["delta125"])]))
            if ab else float("nan"),
            "median_confident": float(np.median([x["confident"] for x in f])) if f else float("nan"),
            "mean_confident": float(np.mean([x["confident"] for x in f])) if f else float("nan"),
            "median_s_per_keyframe": float(np.median(self.seconds)) if self.seconds else float("nan"),
            "p90_s_per_keyframe": float(np.percentile(self.seconds, 90)) if self.seconds else float("nan"),
            "median_cpu_s_per_keyframe": float(np.median([x["cpu_seconds"] for x in f])) if f else float("nan"),
            "median_scale": _median(x.get("scale", float("nan")) for x in f),
            "median_t_poses_s": _median(x.get("t_poses_s", float("nan")) for x in f),
            "median_t_dense_s": _median(x.get("t_dense_s", float("nan")) for x in f),
            "median_cpu_stage_s": {k: _median(x.get("cpu_stage_s", {}).get(k) for x in f)
                                   for k in dict.fromkeys(k for x in f for k in x.get("cpu_stage_s", {}))},
            "median_pose_rot_deg_before": _median(x.get("rot_deg_before", float("nan")) for x in f),
            "median_pose_rot_deg_after": _median(x.get("rot_deg_after", float("nan")) for x in f),
            "median_pose_trans_cm_before": _median(x.get("trans_cm_before", float("nan")) for x in f),
            "median_pose_trans_cm_after": _median(x.get("trans_cm_after", float("nan")) for x in f),
        }


def _median(values: Any) -> float:
    """Median of the finite values (NaN when there are none)."""
    v = [float(x) for x in values if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def score_depth(depth_m: np.ndarray, conf: np.ndarray, gt_m: np.ndarray, gt_valid: np.ndarray) -> DepthScore:
    """Score predicted z-depth against ground truth (resized to the prediction, nearest)."""
    h, w = depth_m.shape
    gt = cv2.resize(gt_m.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    valid = cv2.resize(gt_valid.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    n_gt = int(valid.sum())
    sel = valid & (conf >= CONFIDENT) & (depth_m > 0)
    if n_gt == 0 or not sel.any():
        return DepthScore(float("nan"), float("nan"), 0.0, n_gt)
    d, g = depth_m[sel].astype(np.float64), gt[sel].astype(np.float64)
    ratio = np.maximum(d / g, g / d)
    return DepthScore(float(np.median(np.abs(d - g) / g)), float(np.mean(ratio < 1.25)), float(sel.sum() / n_gt), n_gt,
                      float(np.median(d / g)))
