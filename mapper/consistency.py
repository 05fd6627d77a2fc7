"""Depth that agrees before it is fused (pure: no I/O).

A keyframe's depth is checked against the depth maps of other keyframes (any source) that see the same
surfaces: a pixel keeps its confidence only where at least ``min_views`` of the views that can check it
agree (forward-backward reprojection and relative depth, ``planesweep.consistency_count``). A layer that
no other view confirms (a wrong match, a depth from a bad pose) never reaches the object map, which is
what makes one object into two nodes. Pixels that no other view covers yet cannot be checked: they keep
their confidence (the reconstructor's own window already cross-checked them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapper.geometry.planesweep import consistency_count

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class DepthMap:
    """A keyframe's confident depth for checking others: depth (h, w) metres (0 = none), K at that size,
    T_world_cam."""

    depth_m: F32
    K: F64
    T_world_cam: F64


@dataclass(frozen=True)
class CheckStats:
    checked: int  # confident pixels at least one other view covers
    rejected: int  # of those, confident pixels that too few views confirmed
    unchecked: int  # confident pixels no other view covers


def downsample(depth_m: F32, confidence: F32, K: F64, T_world_cam: F64, width: int, min_conf: float) -> DepthMap:
    """A small copy of a keyframe's confident depth (nearest; unconfident pixels 0) for later checks."""
    h, w = depth_m.shape
    sw = min(width, w)
    sh = max(1, round(h * sw / w))
    d = np.where(confidence >= min_conf, depth_m, 0.0).astype(np.float32)
    small = cv2.resize(d, (sw, sh), interpolation=cv2.INTER_NEAREST)
    Ks = K.copy()
    Ks[0] *= sw / w
    Ks[1] *= sh / h
    # Pixel centres: u' + 0.5 = (u + 0.5) * s.
    Ks[0, 2] = (K[0, 2] + 0.5) * sw / w - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * sh / h - 0.5
    return DepthMap(np.asarray(small, np.float32), Ks, np.asarray(T_world_cam, np.float64))


def coverage_count(depth_m: F32, K: F64, T_world_cam: F64, others: Sequence[DepthMap]) -> NDArray[np.int32]:
    """How many other depth maps have a depth at the pixel where each reference pixel's point projects."""
    h, w = depth_m.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    d = depth_m.astype(np.float64)
    X = np.stack([(uu - K[0, 2]) / K[0, 0] * d, (vv - K[1, 2]) / K[1, 1] * d, d], -1)
    count = np.zeros((h, w), np.int32)
    for o in others:
        T = np.linalg.inv(o.T_world_cam) @ T_world_cam
        p = X @ T[:3, :3].T + T[:3, 3]
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(p[..., 0] / z * o.K[0, 0] + o.K[0, 2])
            v = np.round(p[..., 1] / z * o.K[1, 1] + o.K[1, 2])
        hn, wn = o.depth_m.shape
        ok = (d > 0) & (z > 1e-3) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < wn) & (v >= 0) & (v < hn)
        has = np.zeros((h, w), bool)
        has[ok] = o.depth_m[v[ok].astype(np.int64), u[ok].astype(np.int64)] > 0
        count += has
    return count


def verify_depth(
    depth_m: F32,
    confidence: F32,
    K: F64,
    T_world_cam: F64,
    others: Sequence[DepthMap],
    min_views: int = 2,
    rel_tol: float = 0.05,
    reproj_px: float = 2.0,
    min_conf: float = 0.5,
) -> tuple[F32, CheckStats]:
    """Confidence with unconfirmed pixels zeroed, and what the check did.

    A confident pixel that ``n >= 1`` other views cover needs ``min(min_views, n)`` of them to agree within
    ``rel_tol`` (relative depth) and ``reproj_px`` (reprojection, pixels of the other map)."""
    conf = confidence.astype(np.float32, copy=True)
    confident = (conf >= min_conf) & (depth_m > 0)
    if not others or not confident.any():
        return conf, CheckStats(0, 0, int(confident.sum()))
    d = np.where(confident, depth_m, 0.0).astype(np.float32)
    cover = coverage_count(d, K, T_world_cam, others)
    agree = consistency_count(d, K, T_world_cam, [(o.depth_m, o.K, o.T_world_cam) for o in others],
                              rel_tol, reproj_px, 0)
    need = np.minimum(cover, min_views)
    checked = confident & (cover > 0)
    rejected = checked & (agree < need)
    conf[rejected] = 0.0
    return conf, CheckStats(int(checked.sum()), int(rejected.sum()), int((confident & (cover == 0)).sum()))
