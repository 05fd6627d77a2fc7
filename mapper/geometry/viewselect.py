"""Source-view selection for multi-view stereo by parallax (pure numpy, no I/O).

A reference view's depth can only be triangulated against views that see the same surfaces from a
different place. The usual MVS view-selection scores (COLMAP's, ACMM's) weigh three things, and so does
``score_sources``:

* triangulation angle at the reference's typical depth: below ~1 deg the sweep cannot tell depths apart,
  above ~30 deg the appearance changes too much to match; ~5-20 deg is best;
* baseline-to-depth ratio (the same information, kept as the hard floor that video-rate frames fail);
* overlap: the fraction of the reference's rays, sampled at its typical depth, that the candidate sees.

Views come from any source: a robot's keyframes and calibrated fixed cameras are candidates alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from protocol.messages import Intrinsics
from protocol.poses import rotation_angle_deg

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class ViewSelectParams:
    """Thresholds of the source-view score (angles in degrees, ratios unitless)."""

    min_triangulation_deg: float = 1.5
    best_triangulation_deg: float = 5.0
    max_triangulation_deg: float = 30.0
    min_overlap: float = 0.3
    max_rotation_deg: float = 60.0


@dataclass(frozen=True)
class Candidate:
    """A possible source view: its pose, intrinsics (full resolution) and index in the caller's list."""

    index: int
    T_world_cam: F64
    intrinsics: Intrinsics


@dataclass(frozen=True)
class SourceScore:
    index: int
    score: float
    triangulation_deg: float
    baseline_m: float
    overlap: float
    rotation_deg: float


def sample_rays(intr: Intrinsics, nu: int = 12, nv: int = 9) -> F64:
    """(nu * nv, 3) camera-frame rays (z = 1) on a regular grid over the image."""
    gu, gv = np.meshgrid(np.linspace(0, intr.width - 1, nu), np.linspace(0, intr.height - 1, nv))
    return np.stack([(gu - intr.cx) / intr.fx, (gv - intr.cy) / intr.fy, np.ones_like(gu)], -1).reshape(-1, 3)


def visible(points_world: F64, T_world_cam: F64, intr: Intrinsics) -> NDArray[np.bool_]:
    """Which world points (N, 3) are in front of a camera and inside its image."""
    if len(points_world) == 0:
        return np.zeros(0, dtype=bool)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    p = (points_world - t) @ R  # world -> camera: R^T (X - t)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = p[:, 0] / z * intr.fx + intr.cx
        v = p[:, 1] / z * intr.fy + intr.cy
    return np.asarray((z > 1e-6) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height))


def overlap_fraction(points_world: F64, T_world_cam: F64, intr: Intrinsics) -> float:
    """Fraction of world points (N, 3) in front of a camera and inside its image."""
    if len(points_world) == 0:
        return 0.0
    return float(np.mean(visible(points_world, T_world_cam, intr)))


def triangulation_deg(baseline_m: float, depth_m: float) -> float:
    """Angle between the two rays to a point at ``depth_m`` in front of the middle of a ``baseline_m`` base."""
    return float(np.degrees(2.0 * np.arctan2(0.5 * baseline_m, max(depth_m, 1e-6))))


def score_sources(
    T_world_ref: F64,
    intr_ref: Intrinsics,
    depth_m: float,
    candidates: Sequence[Candidate],
    params: ViewSelectParams = ViewSelectParams(),
) -> list[SourceScore]:
    """Usable source views for a reference, best first (candidates without usable parallax are left out).

    ``depth_m`` is the reference's typical scene depth (median of its sparse points or of its last depth map).
    Score = overlap x angle quality x exp(-rotation / 45 deg); angle quality rises linearly to 1 at
    ``best_triangulation_deg`` and falls off past 20 deg.
    """
    rays = sample_rays(intr_ref)
    X = (rays * depth_m) @ T_world_ref[:3, :3].T + T_world_ref[:3, 3]
    out = []
    for c in candidates:
        base = float(np.linalg.norm(c.T_world_cam[:3, 3] - T_world_ref[:3, 3]))
        tri = triangulation_deg(base, depth_m)
        rot = rotation_angle_deg(T_world_ref, c.T_world_cam)
        if tri < params.min_triangulation_deg or tri > params.max_triangulation_deg or rot > params.max_rotation_deg:
            continue
        ov = overlap_fraction(X, c.T_world_cam, c.intrinsics)
        if ov < params.min_overlap:
            continue
        q_tri = min(1.0, tri / params.best_triangulation_deg) * float(np.exp(-max(0.0, tri - 20.0) / 10.0))
        out.append(SourceScore(c.index, ov * q_tri * float(np.exp(-rot / 45.0)), tri, base, ov, rot))
    out.sort(key=lambda s: (-s.score, s.index))
    return out


def select_sources(
    T_world_ref: F64,
    intr_ref: Intrinsics,
    depth_m: float,
    candidates: Sequence[Candidate],
    k: int,
    params: ViewSelectParams = ViewSelectParams(),
    min_separation_deg: float = 1.0,
    coverage_weights: tuple[float, ...] = (1.0, 0.5, 0.15),
) -> list[SourceScore]:
    """The ``k`` best sources, chosen greedily for what each adds to the ones already chosen.

    Each pick maximises angle quality x rotation term x the weighted share of the reference's rays it
    sees, a ray weighing ``coverage_weights[n]`` when ``n`` chosen sources already see it (the last
    weight for more): a second view of an uncovered part of the image beats a fourth view of the middle,
    which is what the depth check (agreement in 2 views) needs. The first pick is the best
    ``score_sources`` score. A source whose centre is within ``min_separation_deg`` (seen from the
    reference's typical surface point) of a chosen one adds no new direction and is skipped (two video
    frames 1 cm apart are one source, not two).
    """
    rays = sample_rays(intr_ref)
    X = (rays * depth_m) @ T_world_ref[:3, :3].T + T_world_ref[:3, 3]
    centre = T_world_ref[:3, :3] @ np.array([0.0, 0.0, depth_m]) + T_world_ref[:3, 3]
    by_index = {c.index: c for c in candidates}
    scored = score_sources(T_world_ref, intr_ref, depth_m, candidates, params)
    seen = {s.index: visible(X, by_index[s.index].T_world_cam, by_index[s.index].intrinsics) for s in scored}
    w = np.asarray(coverage_weights, dtype=np.float64)
    times_seen = np.zeros(len(X), dtype=np.int64)
    chosen: list[SourceScore] = []
    dirs: list[F64] = []
    remaining = list(scored)
    while remaining and len(chosen) < k:
        ray_w = w[np.minimum(times_seen, len(w) - 1)]
        gains = [s.score / max(s.overlap, 1e-12) * float(np.mean(ray_w * seen[s.index])) for s in remaining]
        best = remaining.pop(int(np.argmax(gains)))  # ties: the earlier (better-scored) candidate
        d = by_index[best.index].T_world_cam[:3, 3] - centre
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        if any(float(np.degrees(np.arccos(np.clip(d @ e, -1.0, 1.0)))) < min_separation_deg for e in dirs):
            continue
        chosen.append(best)
        dirs.append(d)
        times_seen += seen[best.index]
    return chosen
