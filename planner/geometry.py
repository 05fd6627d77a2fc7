"""View prediction: candidate camera poses, frustum tests and panoramic z-buffers (pure numpy).

Occlusion is tested against a coarse **panoramic** z-buffer per camera position (azimuth x
elevation bins holding the nearest map point's range). Candidates that share a position (the
headings of one viewpoint) share one panorama, so occlusion costs O(positions x map points) and the
per-candidate work is only a frustum projection of the targets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.config import VisibilityConfig
from protocol.messages import ViewpointSet
from protocol.poses import camera_pose_from_base

EL_MIN_RAD = -np.pi / 2
EL_MAX_RAD = np.pi / 2


@dataclass(frozen=True)
class Candidates:
    """The candidate views of one robot, with their camera poses precomputed.

    ``T_world_cam`` (C,4,4); ``xy_yaw`` (C,3) base poses; ``vp_ids`` (C,); ``rooms`` per candidate;
    ``pos_index`` (C,) index into ``positions`` (P,3), the distinct camera centres.
    """

    robot_id: str
    vp_ids: np.ndarray
    xy_yaw: np.ndarray
    rooms: tuple[str | None, ...]
    T_world_cam: np.ndarray
    positions: np.ndarray
    pos_index: np.ndarray
    K: np.ndarray
    width: int
    height: int
    max_range_m: float

    @property
    def size(self) -> int:
        return int(self.vp_ids.shape[0])


def candidates_from_viewpoints(vps: ViewpointSet) -> Candidates:
    """Precompute camera poses (protocol convention, the set's mount) for every viewpoint."""
    n = len(vps.viewpoints)
    xy_yaw = np.array([[v.x, v.y, v.yaw_rad] for v in vps.viewpoints], dtype=np.float64).reshape(n, 3)
    T = (
        np.stack(
            [
                camera_pose_from_base(v.x, v.y, v.yaw_rad, vps.camera_height_m, vps.camera_pitch_deg)
                for v in vps.viewpoints
            ]
        )
        if n
        else np.zeros((0, 4, 4))
    )
    centres = T[:, :3, 3] if n else np.zeros((0, 3))
    keys = np.round(centres, 3)
    positions, pos_index = (
        np.unique(keys, axis=0, return_inverse=True) if n else (np.zeros((0, 3)), np.zeros(0, int))
    )
    return Candidates(
        robot_id=vps.robot_id,
        vp_ids=np.array([v.vp_id for v in vps.viewpoints], dtype=np.int64),
        xy_yaw=xy_yaw,
        rooms=tuple(v.room for v in vps.viewpoints),
        T_world_cam=T,
        positions=positions.astype(np.float64),
        pos_index=np.asarray(pos_index, dtype=np.int64).reshape(-1),
        K=vps.intrinsics.K(),
        width=vps.intrinsics.width,
        height=vps.intrinsics.height,
        max_range_m=vps.max_range_m,
    )


def project_many(
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    targets_world: np.ndarray,
    near_m: float,
    far_m: float,
    margin_frac: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Frustum test of ``targets_world`` (T,3) for cameras ``T_world_cam`` (C,4,4).

    Returns ``(in_view (C,T) bool, depth_m (C,T) z-depth)``. A target is in view when its z-depth is
    in ``[near_m, far_m]`` (range along the ray, really: far is checked on the Euclidean distance)
    and it projects inside the image shrunk by ``margin_frac`` on every side.
    """
    C = T_world_cam.shape[0]
    X = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
    if C == 0 or X.shape[0] == 0:
        return np.zeros((C, X.shape[0]), bool), np.zeros((C, X.shape[0]))
    R = T_world_cam[:, :3, :3]  # world_R_cam
    t = T_world_cam[:, :3, 3]
    # p_cam = R^T (X - t): as rows, (X - t) @ R
    d = X[None, :, :] - t[:, None, :]
    p = np.einsum("ctk,ckj->ctj", d, R)
    z = p[..., 2]
    rng = np.linalg.norm(d, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[..., 0] / z + K[0, 2]
        v = K[1, 1] * p[..., 1] / z + K[1, 2]
    mu, mv = margin_frac * width, margin_frac * height
    ok = (
        (z >= near_m)
        & (rng <= far_m)
        & (u >= -0.5 + mu)
        & (u <= width - 0.5 - mu)
        & (v >= -0.5 + mv)
        & (v <= height - 0.5 - mv)
    )
    return ok, z


class Panoramas:
    """Panoramic z-buffers (nearest map-point range per azimuth/elevation bin) for camera positions."""

    def __init__(self, positions: np.ndarray, occluders: np.ndarray, cfg: VisibilityConfig) -> None:
        self.cfg = cfg
        self.positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        P = self.positions.shape[0]
        n_az, n_el = cfg.n_azimuth_bins, cfg.n_elevation_bins
        self.zbuf = np.full((P, n_el * n_az), np.inf, dtype=np.float32)
        pts = np.asarray(occluders, dtype=np.float64).reshape(-1, 3)
        if P == 0 or pts.shape[0] == 0:
            return
        for i in range(P):
            b, r = self._bins(i, pts)
            np.minimum.at(self.zbuf[i], b, r.astype(np.float32))
        self._fill_holes()

    def _bins(self, i: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = pts - self.positions[i]
        r = np.linalg.norm(d, axis=1)
        az = np.arctan2(d[:, 1], d[:, 0])
        el = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        n_az, n_el = self.cfg.n_azimuth_bins, self.cfg.n_elevation_bins
        ia = np.clip(((az + np.pi) / (2 * np.pi) * n_az).astype(np.int64), 0, n_az - 1)
        ie = np.clip(((el - EL_MIN_RAD) / (EL_MAX_RAD - EL_MIN_RAD) * n_el).astype(np.int64), 0, n_el - 1)
        return ie * n_az + ia, r

    def _fill_holes(self) -> None:
        # Sparse far surfaces leave empty bins that rays would slip through: an empty bin takes the
        # nearest range of its 8 neighbours (azimuth wraps around) when at least 3 of them are filled.
        n_az, n_el = self.cfg.n_azimuth_bins, self.cfg.n_elevation_bins
        z = self.zbuf.reshape(-1, n_el, n_az)
        padded = np.pad(z, ((0, 0), (1, 1), (0, 0)), constant_values=np.inf)
        padded = np.concatenate([padded[:, :, -1:], padded, padded[:, :, :1]], axis=2)
        neigh = np.stack(
            [
                padded[:, 1 + di : 1 + di + n_el, 1 + dj : 1 + dj + n_az]
                for di in (-1, 0, 1)
                for dj in (-1, 0, 1)
                if (di, dj) != (0, 0)
            ]
        )
        filled = np.isfinite(neigh).sum(axis=0)
        nmin = neigh.min(axis=0)
        hole = ~np.isfinite(z) & (filled >= 3)
        z[hole] = nmin[hole]
        self.zbuf = z.reshape(-1, n_el * n_az)

    def unoccluded(self, targets_world: np.ndarray, pos_rows: np.ndarray | None = None) -> np.ndarray:
        """(P', T) bool: whether each target is not hidden behind the map from each position."""
        X = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
        rows = (
            np.arange(self.positions.shape[0]) if pos_rows is None else np.asarray(pos_rows, dtype=np.int64)
        )
        out = np.zeros((rows.shape[0], X.shape[0]), bool)
        if X.shape[0] == 0:
            return out
        for j, i in enumerate(rows):
            b, r = self._bins(int(i), X)
            zb = self.zbuf[i][b]
            out[j] = r <= zb + self.cfg.occlusion_tol_m + self.cfg.occlusion_tol_rel * r
        return out


def detect_matrix(
    T_world_cam: np.ndarray,
    pos_index: np.ndarray,
    panoramas: Panoramas,
    K: np.ndarray,
    width: int,
    height: int,
    targets_world: np.ndarray,
    far_m: float,
    cfg: VisibilityConfig,
    sizes_m: np.ndarray | None = None,
    min_pixels: float = 0.0,
    margin_frac: float | None = None,
) -> np.ndarray:
    """(C,T) bool: target in the frustum, within range, unoccluded and (if sizes given) big enough.

    ``pos_index`` (C,) maps each camera to its row in ``panoramas``.
    """
    margin = cfg.image_margin_frac if margin_frac is None else margin_frac
    ok, z = project_many(T_world_cam, K, width, height, targets_world, cfg.near_m, far_m, margin)
    if sizes_m is not None and min_pixels > 0:
        with np.errstate(divide="ignore", invalid="ignore"):
            px = K[0, 0] * np.asarray(sizes_m, dtype=np.float64)[None, :] / np.maximum(z, 1e-6)
        ok &= px >= min_pixels
    if not ok.any():
        return ok
    cols = np.flatnonzero(ok.any(axis=0))
    uniq, inv = np.unique(pos_index, return_inverse=True)
    vis = panoramas.unoccluded(np.asarray(targets_world).reshape(-1, 3)[cols], uniq)
    ok[:, cols] &= vis[inv.reshape(-1)]
    return ok
