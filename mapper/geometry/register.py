"""Pose of a camera without extrinsics (an uncalibrated external camera) from its image alone.

``register_view`` matches SIFT features of the new view against keyframes already in the map, lifts the
matched keyframe pixels to 3D with their reconstructed depth and solves PnP + RANSAC, then refines on
the inliers. With nothing mapped yet, ``two_view_pose`` gives the relative pose from the essential
matrix, made metric by a known baseline or camera height. Every result carries its inlier count and an
``ok`` flag with a reason, so callers can refuse a bad registration.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry import features
from mapper.geometry.contract import View
from protocol.messages import Intrinsics

F64 = NDArray[np.float64]


class RegisterConfig(BaseModel):
    """Options of view registration."""

    model_config = ConfigDict(extra="forbid")
    min_inliers: int = Field(default=30, ge=6, description="PnP inliers needed to accept a pose")
    min_inlier_ratio: float = Field(default=0.15, ge=0, le=1, description="inliers / 2D-3D matches needed")
    reproj_px: float = Field(default=4.0, gt=0, description="RANSAC reprojection threshold, pixels")
    ratio: float = Field(default=0.8, gt=0, lt=1, description="Lowe ratio test threshold")
    min_confidence: float = Field(default=0.5, ge=0, le=1, description="map depth confidence to use a point")
    max_features: int = Field(default=4000, ge=50, description="SIFT keypoints of the new view")
    hfov_search_deg: tuple[float, float] = Field(
        default=(40.0, 120.0), description="field-of-view range searched when the view has no intrinsics"
    )


@dataclass(frozen=True)
class MapKeyframe:
    """A keyframe already in the map: its image and pose, and its reconstructed z-depth (any resolution,
    described by ``depth_intrinsics``) with an optional confidence of the same shape."""

    image: NDArray[np.uint8]
    intrinsics: Intrinsics
    T_world_cam: F64
    depth_m: NDArray[np.float32]
    depth_intrinsics: Intrinsics
    confidence: NDArray[np.float32] | None = None
    key: tuple[str, int] | None = None


@dataclass(frozen=True)
class PoseEstimate:
    """Result of a registration. ``T_world_cam`` is None when nothing could be estimated; ``ok`` says the
    caller may use it; ``reason`` explains a refusal. ``intrinsics`` is the (possibly estimated) camera."""

    T_world_cam: F64 | None
    inliers: int
    ok: bool
    reason: str
    n_matches: int = 0
    intrinsics: Intrinsics | None = None
    info: dict[str, float] = field(default_factory=dict)


def keyframes_from_geometry(
    views: Sequence[View], geometry: Any, indices: Sequence[int] | None = None
) -> list[MapKeyframe]:
    """MapKeyframes from views and their ``ComposedGeometry`` (views without intrinsics or depth are skipped)."""
    out = []
    for i in range(len(views)) if indices is None else indices:
        v = views[i]
        if v.intrinsics is None or not np.any(geometry.confidence[i] > 0):
            continue
        out.append(MapKeyframe(v.image, v.intrinsics, geometry.T_world_cam[i], geometry.depth_m[i],
                               geometry.intrinsics[i], geometry.confidence[i], v.key))
    return out


def pnp_pose(
    uv: F64, X_world: F64, K: F64, reproj_px: float = 4.0, iterations: int = 2000
) -> tuple[F64 | None, int]:
    """``T_world_cam`` from 2D-3D correspondences by EPnP + RANSAC then Levenberg-Marquardt on the
    inliers; returns (None, 0) when RANSAC fails."""
    if len(uv) < 6:
        return None, 0
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X_world.astype(np.float64), uv.astype(np.float64), K, None, iterationsCount=iterations,
        reprojectionError=reproj_px, confidence=0.999, flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inl is None or len(inl) < 6:
        return None, 0
    inl = inl.reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(X_world[inl], uv[inl], K, None, rvec, tvec)
    # Re-collect inliers at the refined pose, then refine once more on them.
    proj, _ = cv2.projectPoints(X_world, rvec, tvec, K, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1)
    inl2 = np.flatnonzero(err < reproj_px)
    if len(inl2) >= 6:
        rvec, tvec = cv2.solvePnPRefineLM(X_world[inl2], uv[inl2], K, None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    T_cam_world = np.eye(4)
    T_cam_world[:3, :3] = R
    T_cam_world[:3, 3] = tvec.reshape(3)
    return np.asarray(np.linalg.inv(T_cam_world), dtype=np.float64), int(max(len(inl), len(inl2)))


def _lift(kf: MapKeyframe, uv_full: F64, min_conf: float) -> tuple[F64, NDArray[np.bool_]]:
    """World points of keyframe pixels (full-image coordinates) from its depth map (nearest sample)."""
    di = kf.depth_intrinsics
    sx, sy = di.width / kf.intrinsics.width, di.height / kf.intrinsics.height
    u = np.round((uv_full[:, 0] + 0.5) * sx - 0.5).astype(np.int64)
    v = np.round((uv_full[:, 1] + 0.5) * sy - 0.5).astype(np.int64)
    inside = (u >= 0) & (u < di.width) & (v >= 0) & (v < di.height)
    u, v = np.clip(u, 0, di.width - 1), np.clip(v, 0, di.height - 1)
    d = kf.depth_m[v, u].astype(np.float64)
    ok = inside & (d > 0) & np.isfinite(d)
    if kf.confidence is not None:
        ok &= kf.confidence[v, u] >= min_conf
    # Reject depth on discontinuities: a neighbour differing by > 5 % means the sample may straddle an edge.
    for du, dv in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        dn = kf.depth_m[np.clip(v + dv, 0, di.height - 1), np.clip(u + du, 0, di.width - 1)]
        ok &= np.abs(dn - d) <= 0.05 * np.maximum(d, 1e-6)
    uu = (u - di.cx) / di.fx * d
    vv = (v - di.cy) / di.fy * d
    Xc = np.stack([uu, vv, d], axis=1)
    Xw = Xc @ kf.T_world_cam[:3, :3].T + kf.T_world_cam[:3, 3]
    return Xw, ok


def register_view(
    view: View,
    map_keyframes: Sequence[MapKeyframe],
    config: RegisterConfig | None = None,
    cache: features.LruCache | None = None,
) -> PoseEstimate:
    """Estimate a view's world pose against keyframes already in the map (see module docstring).

    ``cache`` (optional) holds keyframe features by ``MapKeyframe.key`` across calls.
    """
    cfg = config or RegisterConfig()
    if not map_keyframes:
        return PoseEstimate(None, 0, False, "no mapped keyframes to register against")
    fq = features.extract_features(view.image, cfg.max_features)
    if len(fq) < 6:
        return PoseEstimate(None, 0, False, f"too few features in the view ({len(fq)})")
    uv_q, X_w = [], []
    for kf in map_keyframes:
        fk = cast(features.Features | None, cache.get(kf.key) if (cache is not None and kf.key is not None) else None)
        if fk is None:
            fk = features.extract_features(kf.image, cfg.max_features)
            if cache is not None and kf.key is not None:
                cache.put(kf.key, fk)
        m = features.match_features(fq, fk, cfg.ratio)
        if len(m) < 6:
            continue
        Xw, ok = _lift(kf, fk.uv[m[:, 1]], cfg.min_confidence)
        uv_q.append(fq.uv[m[ok, 0]])
        X_w.append(Xw[ok])
    n = int(sum(len(u) for u in uv_q))
    if n < cfg.min_inliers:
        return PoseEstimate(None, 0, False, f"too few 2D-3D matches ({n} < {cfg.min_inliers})", n_matches=n)
    uv = np.concatenate(uv_q)
    X = np.concatenate(X_w)
    if view.intrinsics is not None:
        intr = view.intrinsics
        T, inl = pnp_pose(uv, X, intr.K(), cfg.reproj_px)
    else:
        T, inl, intr = _pnp_unknown_focal(view, uv, X, cfg)
    if T is None:
        return PoseEstimate(None, 0, False, "PnP RANSAC found no consistent pose", n_matches=n, intrinsics=intr)
    if inl < cfg.min_inliers:
        return PoseEstimate(T, inl, False, f"too few PnP inliers ({inl} < {cfg.min_inliers})", n, intr)
    if inl < cfg.min_inlier_ratio * n:
        return PoseEstimate(T, inl, False, f"inlier ratio too low ({inl}/{n})", n, intr)
    return PoseEstimate(T, inl, True, "ok", n, intr)


def _pnp_unknown_focal(
    view: View, uv: F64, X: F64, cfg: RegisterConfig
) -> tuple[F64 | None, int, Intrinsics]:
    """PnP over a coarse-to-fine search of the field of view (principal point at the image centre)."""
    h, w = view.image.shape[:2]
    best: tuple[F64 | None, int, Intrinsics] = (None, 0, Intrinsics.from_fov(w, h, 70.0))
    lo, hi = cfg.hfov_search_deg
    for step in (8.0, 2.0, 0.5):
        centre = best[2].fx
        grid = np.arange(lo, hi + 1e-9, step)
        for fov in grid:
            intr = Intrinsics.from_fov(w, h, float(fov))
            T, inl = pnp_pose(uv, X, intr.K(), cfg.reproj_px, iterations=500)
            if T is not None and inl > best[1]:
                best = (T, inl, intr)
        fov_best = float(np.degrees(2 * np.arctan(w / 2 / (best[2].fx if best[0] is not None else centre))))
        lo, hi = max(10.0, fov_best - step), min(170.0, fov_best + step)
    if best[0] is not None:
        T, inl = pnp_pose(uv, X, best[2].K(), cfg.reproj_px)
        if T is not None:
            best = (T, inl, best[2])
    return best


def two_view_pose(
    view_a: View,
    view_b: View,
    baseline_m: float | None = None,
    camera_height_m: float | None = None,
    min_inliers: int = 30,
) -> PoseEstimate:
    """Pose of ``view_b`` from two images when nothing is mapped: essential matrix, cheirality, then
    metric scale from the known camera-centre distance ``baseline_m`` or from ``camera_height_m``
    (height of view_a above the floor: with a calibrated view_a the floor is the lowest well-supported
    height band of the triangulated points along its known up direction, else the dominant plane).

    The pose is in view_a's world frame when view_a has ``T_world_cam``, else in view_a's camera frame.
    Both views need intrinsics.
    """
    if view_a.intrinsics is None or view_b.intrinsics is None:
        return PoseEstimate(None, 0, False, "two_view_pose needs intrinsics for both views")
    if baseline_m is None and camera_height_m is None:
        return PoseEstimate(None, 0, False, "need baseline_m or camera_height_m to make the pose metric")
    Ka, Kb = view_a.intrinsics.K(), view_b.intrinsics.K()
    fa = features.extract_features(view_a.image)
    fb = features.extract_features(view_b.image)
    m = features.match_features(fa, fb)
    if len(m) < max(8, min_inliers):
        return PoseEstimate(None, 0, False, f"too few matches ({len(m)})", n_matches=len(m))
    na = features.normalise(fa.uv[m[:, 0]], Ka)
    nb = features.normalise(fb.uv[m[:, 1]], Kb)
    f = 0.5 * (Ka[0, 0] + Kb[0, 0])
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1.5 / f)
    if E is None or E.shape != (3, 3):
        return PoseEstimate(None, 0, False, "essential matrix estimation failed", n_matches=len(m))
    n_inl, R, t, mask2 = cv2.recoverPose(E, na, nb, np.eye(3), mask=mask)
    if n_inl < min_inliers:
        return PoseEstimate(None, int(n_inl), False, f"too few inliers ({n_inl} < {min_inliers})", len(m))
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R
    T_b_a[:3, 3] = t.reshape(3)  # unit baseline
    T_a_b = np.linalg.inv(T_b_a)
    if baseline_m is not None:
        scale = float(baseline_m)
    else:
        sel = mask2.reshape(-1) > 0
        P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
        P2 = T_b_a[:3, :]
        Xh = cv2.triangulatePoints(P1, P2, na[sel].T, nb[sel].T)
        Xa = (Xh[:3] / Xh[3]).T
        Xa = Xa[Xa[:, 2] > 0]
        if view_a.T_world_cam is not None:
            # view_a is calibrated: the floor's direction is known, only its distance is not.
            up_a = np.asarray(view_a.T_world_cam, np.float64)[2, :3]  # world z in view_a's camera frame
            h_unit = floor_distance(Xa, up_a)
        else:
            h_unit = _plane_distance(Xa)
        if h_unit is None:
            return PoseEstimate(None, int(n_inl), False, "no ground plane found for the height scale", len(m))
        assert camera_height_m is not None  # checked on entry: one of the two is given
        scale = float(camera_height_m) / h_unit
    T_a_b[:3, 3] *= scale
    T_world_b = np.asarray(view_a.T_world_cam @ T_a_b if view_a.T_world_cam is not None else T_a_b, np.float64)
    return PoseEstimate(T_world_b, int(n_inl), True, "ok", len(m), view_b.intrinsics, {"scale": scale})


def floor_distance(X: F64, up: F64, bins: int = 60, min_share: float = 0.3) -> float | None:
    """Distance from the camera (origin) down to the floor among points ``X`` (N, 3) in its frame, ``up`` the
    world's up direction in that frame: the lowest height band that holds at least ``min_share`` of the
    fullest band's points (table tops and seats lie above the floor; stray points below it are few)."""
    if len(X) < 20:
        return None
    u = np.asarray(up, np.float64) / max(float(np.linalg.norm(up)), 1e-12)
    h = X @ u
    lo, hi = np.percentile(h, [1.0, 99.0])
    if not hi > lo:
        return None
    counts, edges = np.histogram(h, bins=bins, range=(lo, hi))
    first = int(np.flatnonzero(counts >= min_share * counts.max())[0])
    band = (h >= edges[max(first - 1, 0)]) & (h <= edges[min(first + 2, bins)])
    floor_h = float(np.median(h[band]))
    return -floor_h if floor_h < 0 else None


def _plane_distance(X: F64, iters: int = 300, seed: int = 0) -> float | None:
    """Distance from the origin to the RANSAC plane with most support among points ``X`` (N, 3)."""
    if len(X) < 20:
        return None
    rng = np.random.default_rng(seed)
    scale = float(np.median(np.linalg.norm(X, axis=1)))
    tol = 0.01 * scale
    best_n, best_d = 0, None
    for _ in range(iters):
        p = X[rng.choice(len(X), 3, replace=False)]
        nrm = np.cross(p[1] - p[0], p[2] - p[0])
        if np.linalg.norm(nrm) < 1e-12:
            continue
        nrm /= np.linalg.norm(nrm)
        d = -nrm @ p[0]
        cnt = int(np.sum(np.abs(X @ nrm + d) < tol))
        if cnt > best_n:
            best_n, best_d = cnt, abs(d)
    return best_d if best_n >= 15 else None
