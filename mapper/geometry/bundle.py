"""Feature tracks, triangulation and bundle adjustment with pose priors as soft constraints.

Odometry and recorded poses are priors, not truth: a bundle adjustment over feature tracks moves them
to agree with the images while a prior term per camera keeps the gauge and the metric scale. Cameras
with a surveyed calibration are held fixed. Pure numpy / scipy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def build_tracks(n_kp: list[int], pair_matches: dict[tuple[int, int], I64]) -> list[I64]:
    """Join pairwise matches into tracks with union-find.

    n_kp: keypoint count per view; pair_matches[(i, j)]: (M, 2) keypoint indices in views i and j.
    Returns tracks as (L, 2) arrays of (view, keypoint) with L >= 2 and at most one keypoint per view
    (tracks that hit a view twice are inconsistent and dropped).
    """
    offsets = np.concatenate([[0], np.cumsum(n_kp)]).astype(np.int64)
    parent = np.arange(offsets[-1], dtype=np.int64)

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for (i, j), m in pair_matches.items():
        for a, b in m:
            ra, rb = find(offsets[i] + int(a)), find(offsets[j] + int(b))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    used = set()
    for (i, j), m in pair_matches.items():
        for a, b in m:
            used.add(offsets[i] + int(a))
            used.add(offsets[j] + int(b))
    for node in used:
        groups.setdefault(find(node), []).append(node)
    tracks = []
    for nodes in groups.values():
        if len(nodes) < 2:
            continue
        nodes_a = np.array(sorted(nodes), dtype=np.int64)
        views = np.searchsorted(offsets, nodes_a, side="right") - 1
        if len(np.unique(views)) != len(views):
            continue
        tracks.append(np.stack([views, nodes_a - offsets[views]], axis=1))
    return tracks


def projection_matrix(K: F64, T_world_cam: F64) -> F64:
    """3x4 matrix mapping homogeneous world points to homogeneous pixels."""
    T_cam_world = np.linalg.inv(T_world_cam)
    return K @ T_cam_world[:3, :]


def triangulate(Ps: list[F64], uvs: F64) -> F64:
    """Linear (DLT) triangulation of one point from L >= 2 views: Ps 3x4 matrices, uvs (L, 2)."""
    A = []
    for P, (u, v) in zip(Ps, uvs, strict=True):
        A.append(u * P[2] - P[0])
        A.append(v * P[2] - P[1])
    _, _, vt = np.linalg.svd(np.asarray(A))
    X = vt[-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)


def reproject(K: F64, T_world_cam: F64, X_world: F64) -> tuple[F64, F64]:
    """Pixels (N, 2) and camera z (N,) of world points (N, 3)."""
    T_cw = np.linalg.inv(T_world_cam)
    p = X_world @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / z[:, None] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, z


@dataclass
class BundleProblem:
    """Observations of points in cameras: obs_cam[k] sees obs_pt[k] at obs_uv[k] (pixels)."""

    Ks: list[F64]
    T_world_cam: list[F64]
    points_world: F64
    obs_cam: I64
    obs_pt: I64
    obs_uv: F64
    fixed: list[bool] = field(default_factory=list)
    has_prior: list[bool] = field(default_factory=list)


@dataclass
class BundleResult:
    T_world_cam: list[F64]
    points_world: F64
    inlier_obs: NDArray[np.bool_]
    rms_px_before: float
    rms_px_after: float
    n_iterations: int


def _skew(v: F64) -> F64:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1),
         np.stack([-v[..., 1], v[..., 0], z], -1)], -2
    )


def bundle_adjust(
    prob: BundleProblem,
    sigma_rot_deg: float = 1.0,
    sigma_trans_m: float = 0.03,
    huber_px: float = 2.0,
    max_iterations: int = 20,
) -> BundleResult:
    """Refine camera poses and points: Huber reprojection error plus a prior per camera.

    The prior pulls each non-fixed camera with ``has_prior`` towards its starting pose (rotation in
    units of ``sigma_rot_deg``, camera centre in units of ``sigma_trans_m``, both scaled so that one
    sigma costs like ``huber_px`` of reprojection error), which fixes the gauge and keeps the metric
    scale of the priors. Cameras with ``fixed`` do not move. Levenberg-Marquardt with analytic
    Jacobians and the Schur complement on the points (cameras are few, points many).
    """
    n_cam = len(prob.Ks)
    n_pt = prob.points_world.shape[0]
    fixed = np.array(prob.fixed or [False] * n_cam, bool)
    has_prior = np.array(prob.has_prior or [True] * n_cam, bool) & ~fixed
    oc, op, ouv = prob.obs_cam, prob.obs_pt, prob.obs_uv
    n_obs = len(oc)
    fxy = np.stack([[K[0, 0], K[1, 1]] for K in prob.Ks])
    cxy = np.stack([K[:2, 2] for K in prob.Ks])
    R_prior = np.stack([np.linalg.inv(T)[:3, :3] for T in prob.T_world_cam])  # R_cam_world
    C_prior = np.stack([T[:3, 3] for T in prob.T_world_cam])
    w_rot = huber_px / np.deg2rad(sigma_rot_deg)
    w_trans = huber_px / sigma_trans_m

    def residuals(R: F64, C: F64, X: F64) -> tuple[F64, F64, F64, F64]:
        p = np.einsum("nij,nj->ni", R[oc], X[op] - C[oc])
        z = np.maximum(p[:, 2], 1e-6)
        uv = p[:, :2] / z[:, None] * fxy[oc] + cxy[oc]
        r_rot = w_rot * Rotation.from_matrix(np.einsum("nij,nkj->nik", R, R_prior)).as_rotvec()
        r_c = w_trans * (C - C_prior)
        return uv - ouv, p, r_rot, r_c

    def cost(r: F64, r_rot: F64, r_c: F64) -> float:
        e = np.linalg.norm(r, axis=1)
        rho = np.where(e <= huber_px, 0.5 * e**2, huber_px * (e - 0.5 * huber_px))
        return float(rho.sum() + 0.5 * ((r_rot[has_prior] ** 2).sum() + (r_c[has_prior] ** 2).sum()))

    R, C, X = R_prior.copy(), C_prior.copy(), prob.points_world.astype(np.float64).copy()
    r, p, r_rot, r_c = residuals(R, C, X)
    rms0 = float(np.sqrt(np.mean(np.sum(r**2, 1)))) if n_obs else 0.0
    cur = cost(r, r_rot, r_c)
    lam = 1e-3
    it = 0
    free_idx = np.flatnonzero(~fixed)
    for it in range(1, max_iterations + 1):  # noqa: B007
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
        z = np.maximum(p[:, 2], 1e-6)
        f = fxy[oc]
        J_proj = np.zeros((n_obs, 2, 3))
        J_proj[:, 0, 0] = f[:, 0] / z
        J_proj[:, 0, 2] = -f[:, 0] * p[:, 0] / z**2
        J_proj[:, 1, 1] = f[:, 1] / z
        J_proj[:, 1, 2] = -f[:, 1] * p[:, 1] / z**2
        Jp = J_proj @ R[oc]  # d uv / d X
        Jc = np.concatenate([J_proj @ -_skew(p), -Jp], axis=2)  # d uv / d (omega, C)
        wJc = Jc * w[:, None, None]
        wJp = Jp * w[:, None, None]
        Hcc = np.zeros((n_cam, 6, 6))
        np.add.at(Hcc, oc, np.einsum("kai,kaj->kij", wJc, Jc))
        bc = np.zeros((n_cam, 6))
        np.add.at(bc, oc, np.einsum("kai,ka->ki", wJc, r))
        Hpp = np.zeros((n_pt, 3, 3))
        np.add.at(Hpp, op, np.einsum("kai,kaj->kij", wJp, Jp))
        bp = np.zeros((n_pt, 3))
        np.add.at(bp, op, np.einsum("kai,ka->ki", wJp, r))
        Hcp = np.zeros((n_pt, n_cam, 6, 3))
        np.add.at(Hcp, (op, oc), np.einsum("kai,kaj->kij", wJc, Jp))
        pr = np.flatnonzero(has_prior)
        Hcc[pr, :3, :3] += w_rot**2 * np.eye(3)
        Hcc[pr, 3:, 3:] += w_trans**2 * np.eye(3)
        bc[pr, :3] += w_rot * r_rot[pr]
        bc[pr, 3:] += w_trans * r_c[pr]
        improved = False
        for _ in range(8):
            Hpp_d = Hpp + lam * (np.einsum("nii->ni", Hpp)[:, :, None] * np.eye(3) + 1e-9 * np.eye(3))
            Hpp_inv = np.linalg.inv(Hpp_d)
            Y = np.einsum("nmas,nst->nmat", Hcp, Hpp_inv)  # (P, cam, 6, 3)
            Yr = Y.transpose(1, 2, 0, 3).reshape(6 * n_cam, 3 * n_pt)
            Hr = Hcp.transpose(1, 2, 0, 3).reshape(6 * n_cam, 3 * n_pt)
            Hcc_d = Hcc.copy()
            Hcc_d += lam * (np.einsum("nii->ni", Hcc)[:, :, None] * np.eye(6) + 1e-9 * np.eye(6))
            S = np.zeros((6 * n_cam, 6 * n_cam))
            for i in range(n_cam):
                S[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = Hcc_d[i]
            S -= Yr @ Hr.T
            rhs = bc.reshape(-1) - Yr @ bp.reshape(-1)
            sel = np.concatenate([np.arange(6 * i, 6 * i + 6) for i in free_idx]) if len(free_idx) else np.zeros(0, int)
            dc = np.zeros(6 * n_cam)
            if len(sel):
                try:
                    dc[sel] = -np.linalg.solve(S[np.ix_(sel, sel)], rhs[sel])
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
            dcs = dc.reshape(n_cam, 6)
            dX = -np.einsum("nst,nt->ns", Hpp_inv, bp + np.einsum("nmas,ma->ns", Hcp, dcs))
            R_new = np.einsum("nij,njk->nik", Rotation.from_rotvec(dcs[:, :3]).as_matrix(), R)
            C_new = C + dcs[:, 3:]
            X_new = X + dX
            r_n, p_n, rr_n, rc_n = residuals(R_new, C_new, X_new)
            new = cost(r_n, rr_n, rc_n)
            if new < cur:
                R, C, X, r, p, r_rot, r_c = R_new, C_new, X_new, r_n, p_n, rr_n, rc_n
                rel = (cur - new) / max(cur, 1e-12)
                cur = new
                lam = max(lam / 3, 1e-7)
                improved = True
                break
            lam *= 10
        if not improved or rel < 1e-5:
            break
    err = np.linalg.norm(r, axis=1)
    T_out = []
    for i in range(n_cam):
        T = np.eye(4)
        T[:3, :3] = R[i].T
        T[:3, 3] = C[i]
        T_out.append(T)
    return BundleResult(
        T_world_cam=T_out,
        points_world=X,
        inlier_obs=(err < 3.0 * huber_px) & (p[:, 2] > 0),
        rms_px_before=rms0,
        rms_px_after=float(np.sqrt(np.mean(err**2))) if n_obs else 0.0,
        n_iterations=it,
    )
