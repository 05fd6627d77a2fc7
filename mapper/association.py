"""Mask association: which fused nodes a keyframe's detections show, judged in the image (pure: no I/O).

Estimated depth scatters one object's views in 3D: a table seen from two keyframes may come back as two
clouds a few centimetres apart along the viewing rays, each covering the part that had texture. Their point
overlap is small, so 3D association alone makes a node per view (fragments, duplicates). In the image the
same object is one mask whatever its depth: projecting a node's points into a new keyframe and counting how
many land inside a detection's mask tells whether the detection shows that node, and depth errors along
the ray barely move a projection.

Points hidden behind the keyframe's own surface (farther than its confident depth at that pixel by a
margin) are not counted: a chair behind a table projects into the table's mask but is not the table.
Pixels without confident depth cannot hide anything. A node needs ``min_points`` visible points to be
judged at all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from protocol.poses import invert, project


@dataclass(frozen=True)
class KeyframeView:
    """A keyframe as the mask association sees it: camera, confident depth (0 where unknown), its image size."""

    K: np.ndarray  # (3, 3) at the depth map's resolution
    T_world_cam: np.ndarray  # (4, 4)
    depth_m: np.ndarray  # (h, w); 0 (or non-finite) where the depth is not confident
    people: np.ndarray | None = None  # (h, w) bool: pixels 2D perception saw a person at; None: not known

    def visible_pixels(self, points_world: np.ndarray, margin_m: float, margin_rel: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows, columns and indices of the points that project inside the image in front of the camera and
        are not farther than the keyframe's confident depth there by ``margin_m + margin_rel * depth``."""
        h, w = self.depth_m.shape
        T_cam_world = invert(self.T_world_cam)
        # contiguous rotation: the same product bit for bit, without numpy's slow strided loop
        p = points_world.astype(np.float64) @ np.ascontiguousarray(T_cam_world[:3, :3].T) + T_cam_world[:3, 3]
        uv, z = project(self.K, p)
        with np.errstate(invalid="ignore"):
            col = np.floor(uv[:, 0])
            row = np.floor(uv[:, 1])
            ok = (z > 0.05) & np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        idx = np.flatnonzero(ok)
        r, c = row[idx].astype(np.intp), col[idx].astype(np.intp)
        d = self.depth_m[r, c]
        known = np.isfinite(d) & (d > 0)
        hidden = known & (z[idx] > d + margin_m + margin_rel * np.where(known, d, 0.0))
        keep = ~hidden
        return r[keep], c[keep], idx[keep]


def containment(view: KeyframeView, clouds: Sequence[np.ndarray], masks: Sequence[np.ndarray], *,
                min_points: int = 10, max_points: int = 400, margin_m: float = 0.2, margin_rel: float = 0.15
                ) -> np.ndarray:
    """``(len(clouds), len(masks))``: the fraction of each cloud's visible points that fall inside each mask
    (masks at the depth map's resolution); NaN for a cloud with fewer than ``min_points`` visible points.
    Each cloud is thinned to at most ``max_points`` points (a fixed stride: deterministic)."""
    out = np.full((len(clouds), len(masks)), np.nan)
    if not clouds or not masks:
        return out
    parts, owner = [], []
    for k, pts in enumerate(clouds):
        step = max(1, -(-len(pts) // max_points))
        parts.append(np.asarray(pts)[::step])
        owner.append(np.full(len(parts[-1]), k, np.intp))
    r, c, idx = view.visible_pixels(np.concatenate(parts), margin_m, margin_rel)
    who = np.concatenate(owner)
    vis_owner = who[idx]
    n_vis = np.bincount(vis_owner, minlength=len(clouds)).astype(np.float64)
    judged = n_vis >= min_points
    for j, m in enumerate(masks):
        hits = np.bincount(vis_owner, weights=m[r, c].astype(np.float64), minlength=len(clouds))
        out[judged, j] = hits[judged] / n_vis[judged]
    return out
