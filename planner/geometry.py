"""View prediction: candidate camera poses, frustum tests and panoramic z-buffers (pure numpy).

Occlusion is tested against a coarse **panoramic** z-buffer per camera position (azimuth x
elevation bins holding the nearest map point's range). Candidates that share a position (the
headings of one viewpoint) share one panorama, so occlusion costs O(positions x map points) and the
per-candidate work is only a frustum projection of the targets.

The frustum test runs per camera centre on the targets within range of it (one small matrix product for
all the headings there), and only the (camera, target) pairs in view are looked up in the panoramas.
Panoramas whose occluders in range did not change are taken over from the previous decision. Panorama builds,
frustum tests and occlusion look-ups are split across ``VisibilityConfig.threads`` worker threads
(:func:`parallel_map`), with the same results for any count.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from scipy.spatial import cKDTree

from planner.config import VisibilityConfig
from protocol.messages import ViewpointSet
from protocol.poses import camera_pose_from_base

_A = TypeVar("_A")
_R = TypeVar("_R")
_POOLS: dict[int, ThreadPoolExecutor] = {}


def parallel_map(fn: Callable[[_A], _R], items: Sequence[_A], threads: int) -> list[_R]:
    """``[fn(x) for x in items]`` on ``threads`` worker threads (a pool per size, kept for the process), in
    order. Worth it where ``fn`` spends its time in numpy's array loops, which release the interpreter."""
    if threads <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    pool = _POOLS.get(threads)
    if pool is None:
        pool = _POOLS.setdefault(threads, ThreadPoolExecutor(threads, thread_name_prefix="argus-visibility"))
    return list(pool.map(fn, items))


def split_even(weights: np.ndarray, parts: int) -> list[tuple[int, int]]:
    """Contiguous ``[a, b)`` ranges of ``weights``' indices, at most ``parts`` of them, none empty, each
    holding about the same total weight."""
    n = int(weights.shape[0])
    parts = max(1, min(int(parts), n))
    if n == 0:
        return []
    cum = np.cumsum(np.asarray(weights, dtype=np.float64))
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, parts) / parts, side="right")
    edges = np.unique(np.concatenate([[0], np.clip(cuts, 1, n - 1) if n > 1 else [], [n]]).astype(np.int64))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def item_blocks(n: int, threads: int, min_each: int) -> list[tuple[int, int]]:
    """``n`` items as contiguous ranges of about equal size: one per thread once each would hold at least
    ``min_each`` items, else one range (splitting small work costs more than it saves)."""
    return split_even(np.ones(n), threads if n >= min_each * threads else 1)


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
    # p_cam = R^T (X - t): as rows, X @ R - t @ R; one BLAS call for all cameras.
    Rcat = R.transpose(1, 0, 2).reshape(3, 3 * C)
    p = (X @ Rcat).reshape(-1, C, 3).transpose(1, 0, 2) - np.einsum("ck,ckj->cj", t, R)[:, None, :]
    z = p[..., 2]
    rng = np.sqrt(np.einsum("ctk,ctk->ct", p, p))  # range is rotation invariant
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


_OTHER_AXES = np.array([[1, 2], [0, 2], [0, 1]])


def _norm(d: np.ndarray) -> np.ndarray:
    """Euclidean length of the vectors ``d`` (..., 3)."""
    return np.sqrt(np.einsum("...k,...k->...", d, d))


_KEY_HALF = 1 << 20


def _voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """One int64 per voxel index (N, 3) with every |index| < 2**20 (21 bits per axis)."""
    a = ijk + _KEY_HALF
    return (a[:, 0] << 42) | (a[:, 1] << 21) | a[:, 2]


def downsample_occluders(points: np.ndarray, voxel_m: float, max_points: int) -> np.ndarray:
    """One point per ``voxel_m`` voxel (the first in ``points``' order), capped at ``max_points`` by an even
    stride."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if P.shape[0] and voxel_m > 0:
        ijk = np.floor(P / voxel_m).astype(np.int64)
        if np.abs(ijk).max() < _KEY_HALF:  # one int64 key per voxel: a 1-D unique, much faster than rows
            _, first = np.unique(_voxel_keys(ijk), return_index=True)
        else:
            _, first = np.unique(ijk, axis=0, return_index=True)
        P = P[np.sort(first)]
    if P.shape[0] > max_points:
        P = P[:: int(np.ceil(P.shape[0] / max_points))]
    return P


REUSE_SLACK_M = 1e-3
"""A changed occluder this much beyond the build's range cut still forces a rebuild (rounding of distances)."""


def changed_points(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rows of ``a`` (N,3) not in ``b`` (M,3) and of ``b`` not in ``a``, compared bit for bit."""
    A = np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 3))
    B = np.ascontiguousarray(np.asarray(b, dtype=np.float64).reshape(-1, 3))
    return np.concatenate([A[~_rows_in(A, B)], B[~_rows_in(B, A)]])


def _mix64(z: np.ndarray) -> np.ndarray:
    """The splitmix64 finaliser (every input bit reaches every output bit), modulo 2**64."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _row_hash(u: np.ndarray) -> np.ndarray:
    """A 64-bit hash of each row of ``u`` (N, 3) uint64."""
    return _mix64(_mix64(_mix64(u[:, 0]) ^ u[:, 1]) ^ u[:, 2])


def _rows_in(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(N,) bool: row ``i`` of ``A`` is bit for bit a row of ``B``. Rows are matched on a 64-bit hash and the
    match is then checked on all 192 bits (a hash collision reads as not found: never a false match)."""
    if A.shape[0] == 0 or B.shape[0] == 0:
        return np.zeros(A.shape[0], bool)
    ua, ub = A.view(np.uint64), B.view(np.uint64)
    ha, hb = _row_hash(ua), _row_hash(ub)
    order = np.argsort(hb, kind="stable")
    at = np.minimum(np.searchsorted(hb[order], ha), B.shape[0] - 1)
    j = order[at]
    return (hb[j] == ha) & np.all(ub[j] == ua, axis=1)


class Panoramas:
    """Panoramic z-buffers (nearest map-point range per direction bin) for camera positions.

    Directions are binned on a cube map (6 faces of ``cube_face_bins``^2 bins: divisions only, no
    trigonometry). Rows are built lazily, in batches, only for positions whose visibility is asked
    for, from the occluders within ``far_m`` of the position.
    """

    def __init__(
        self, positions: np.ndarray, occluders: np.ndarray, cfg: VisibilityConfig, far_m: float = np.inf
    ) -> None:
        self.cfg = cfg
        self.res = int(cfg.cube_face_bins)
        self.n_bins = 6 * self.res * self.res
        self.positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        self.occluders = np.asarray(occluders, dtype=np.float64).reshape(-1, 3)
        self.far_m = float(far_m)
        self._rows: dict[int, np.ndarray] = {}

    def _bins(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cube-map bin (...) and range (...) of direction vectors ``d`` (..., 3)."""
        return self._bin_index(d), _norm(d)

    def _bin_index(self, d: np.ndarray) -> np.ndarray:
        """Cube-map bin (...) of direction vectors ``d`` (..., 3).

        The major axis is the first of the largest absolute components (as ``argmax``); everything is
        elementwise (no gathers), the hot loop of the planner's visibility.
        """
        dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
        ax, ay, az = np.abs(dx), np.abs(dy), np.abs(dz)
        mx = (ax >= ay) & (ax >= az)
        my = ~mx & (ay >= az)
        mz = ~mx & ~my
        m = np.maximum(np.where(mx, ax, np.where(my, ay, az)), 1e-12)
        along = np.where(mx, dx, np.where(my, dy, dz))
        R = self.res
        half = R / 2.0
        iu = np.clip(((np.where(mx, dy, dx) / m + 1.0) * half).astype(np.int64), 0, R - 1)
        iv = np.clip(((np.where(mz, dy, dz) / m + 1.0) * half).astype(np.int64), 0, R - 1)
        face = (np.where(mx, 0, np.where(my, 1, 2)) * 2 + (along < 0)).astype(np.int64)
        return (face * R + iu) * R + iv

    def _build(self, rows: list[int]) -> None:
        pts = self.occluders
        threads = max(1, int(self.cfg.threads))
        # batches in flight at once (one per thread) share the bound on the temporaries below
        chunk = max(1, self.cfg.panorama_batch_pairs // (threads * max(1, pts.shape[0])))

        def build(rr: list[int]) -> np.ndarray:
            zb = np.full((len(rr), self.n_bins), np.inf, dtype=np.float32)
            if pts.shape[0]:
                d = pts[None, :, :] - self.positions[rr][:, None, :]
                r = _norm(d)
                at, occ = np.nonzero(r <= self.far_m + 0.5)  # only occluders in range are binned
                flat = at * self.n_bins + self._bin_index(d[at, occ])
                np.minimum.at(zb.reshape(-1), flat, r[at, occ].astype(np.float32))
                zb = self._fill_holes(zb)
            return zb

        batches = [rows[c0 : c0 + chunk] for c0 in range(0, len(rows), chunk)]
        for rr, zb in zip(batches, parallel_map(build, batches, threads), strict=True):
            for j, i in enumerate(rr):
                self._rows[i] = zb[j]

    def reuse(self, prev: Panoramas | None) -> int:
        """Take over ``prev``'s z-buffers (the previous decision's) for the positions both have whose occluders in
        range are the same: no occluder within ``far_m + 0.5`` (the build's cut) of the position was added or
        removed. Such a z-buffer is the one :meth:`_build` would compute; returns how many were taken over."""
        if prev is None or not prev._rows or prev.res != self.res or prev.far_m != self.far_m:
            return 0
        at = {prev.positions[i].tobytes(): i for i in prev._rows}
        keys = (p.tobytes() for p in self.positions)
        pairs = [(i, at[k]) for i, k in enumerate(keys) if k in at and i not in self._rows]
        if not pairs:
            return 0
        mine = np.array([i for i, _ in pairs])
        changed = changed_points(prev.occluders, self.occluders)
        same = np.ones(mine.shape[0], bool)
        if changed.shape[0]:
            reach = self.far_m + 0.5 + REUSE_SLACK_M
            dist, _ = cKDTree(changed).query(self.positions[mine], k=1, distance_upper_bound=reach)
            same = ~np.isfinite(dist)  # inf: no changed occluder within reach
        for (i, j), ok in zip(pairs, same, strict=True):
            if ok:
                self._rows[i] = prev._rows[j]
        return int(same.sum())

    def row(self, i: int) -> np.ndarray:
        """The z-buffer of position ``i`` (6 * R * R,), built on first use."""
        if i not in self._rows:
            self._build([i])
        return self._rows[i]

    def _fill_holes(self, zb: np.ndarray) -> np.ndarray:
        # Sparse far surfaces leave empty bins that rays would slip through: an empty bin takes the
        # nearest range of its 8 neighbours (within a face) when at least 3 of them are filled.
        R = self.res
        z = zb.reshape(-1, 6, R, R)
        padded = np.pad(z, ((0, 0), (0, 0), (1, 1), (1, 1)), constant_values=np.inf)
        nmin = np.full(z.shape, np.inf, dtype=np.float32)
        filled = np.zeros(z.shape, dtype=np.int8)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if (di, dj) == (0, 0):
                    continue
                nb = padded[:, :, 1 + di : 1 + di + R, 1 + dj : 1 + dj + R]
                np.minimum(nmin, nb, out=nmin)
                filled += np.isfinite(nb)
        hole = ~np.isfinite(z) & (filled >= 3)
        out = z.copy()
        out[hole] = nmin[hole]
        return out.reshape(zb.shape)

    def unoccluded_pairs(self, targets_world: np.ndarray, pos_rows: np.ndarray) -> np.ndarray:
        """(n,) bool: whether target ``i`` is not hidden behind the map from position ``pos_rows[i]``
        (:meth:`unoccluded` for a list of pairs instead of every position with every target)."""
        X = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
        rows = np.asarray(pos_rows, dtype=np.int64).reshape(-1)
        if X.shape[0] == 0:
            return np.zeros(0, bool)
        uniq = np.flatnonzero(np.bincount(rows, minlength=self.positions.shape[0]))
        missing = sorted(set(uniq.tolist()) - self._rows.keys())
        if missing:
            self._build(missing)
        local = np.zeros(self.positions.shape[0], np.int64)
        local[uniq] = np.arange(uniq.shape[0])
        Z = np.stack([self._rows[int(i)] for i in uniq])

        def look_up(ab: tuple[int, int]) -> np.ndarray:
            rr = rows[ab[0] : ab[1]]
            b, r = self._bins(X[ab[0] : ab[1]] - self.positions[rr])
            return r <= Z[local[rr], b] + self.cfg.occlusion_tol_m + self.cfg.occlusion_tol_rel * r

        threads = max(1, int(self.cfg.threads))
        return np.concatenate(parallel_map(look_up, item_blocks(X.shape[0], threads, 4096), threads))

    def unoccluded(self, targets_world: np.ndarray, pos_rows: np.ndarray | None = None) -> np.ndarray:
        """(P', T) bool: whether each target is not hidden behind the map from each position."""
        X = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
        rows = (
            np.arange(self.positions.shape[0]) if pos_rows is None else np.asarray(pos_rows, dtype=np.int64)
        )
        if X.shape[0] == 0 or rows.shape[0] == 0:
            return np.zeros((rows.shape[0], X.shape[0]), bool)
        missing = sorted({int(i) for i in rows} - self._rows.keys())
        if missing:
            self._build(missing)
        d = X[None, :, :] - self.positions[rows][:, None, :]
        b, r = self._bins(d)
        Z = np.stack([self._rows[int(i)] for i in rows])
        zb = np.take_along_axis(Z, b, axis=1)
        return r <= zb + self.cfg.occlusion_tol_m + self.cfg.occlusion_tol_rel * r


def image_cone_cos(K: np.ndarray, width: int, height: int, margin_frac: float = 0.0) -> float:
    """Cosine of the half-angle of the narrowest cone about the optical axis that holds the whole image (shrunk
    by ``margin_frac`` on every side): a camera-frame point ``p`` that projects inside has ``p_z >= cos * |p|``."""
    mu, mv = margin_frac * width, margin_frac * height
    tx = max(abs(-0.5 + mu - K[0, 2]), abs(width - 0.5 - mu - K[0, 2])) / K[0, 0]
    ty = max(abs(-0.5 + mv - K[1, 2]), abs(height - 0.5 - mv - K[1, 2])) / K[1, 1]
    return float(1.0 / np.sqrt(1.0 + tx * tx + ty * ty))


def in_view_pairs(
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    targets_world: np.ndarray,
    near_m: float,
    far_m: float,
    margin_frac: float = 0.0,
    sizes_m: np.ndarray | None = None,
    min_pixels: float = 0.0,
    threads: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """The (camera ``cams[i]``, target ``tgts[i]``) pairs in view: :func:`project_many`'s test (and, with
    ``sizes_m``, at least ``min_pixels`` big), listed instead of a dense (C, T) matrix.

    Cameras that share a centre (the headings of one viewpoint) are tested together, on the targets within
    ``far_m`` of that centre only: one small matrix product gives every heading's camera coordinates. The
    centres are split across ``threads`` worker threads (the same pairs, in the same order, for any count)."""
    C = T_world_cam.shape[0]
    X = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
    if C == 0 or X.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    centres, group = np.unique(T_world_cam[:, :3, 3], axis=0, return_inverse=True)
    group = group.reshape(-1)
    order = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[order], np.arange(centres.shape[0] + 1))
    # squared range centre -> target, |X|^2 - 2 X.c + |c|^2 (one product); a slack keeps the cut conservative
    d2 = (X @ centres.T).T
    d2 *= -2.0
    d2 += np.einsum("tk,tk->t", X, X)[None, :]
    d2 += np.einsum("ck,ck->c", centres, centres)[:, None]
    near_enough = d2 <= (far_m + RANGE_SLACK_M) ** 2
    mu, mv = margin_frac * width, margin_frac * height
    cone = image_cone_cos(K, width, height, margin_frac) - RANGE_SLACK_M
    size = None if sizes_m is None or min_pixels <= 0 else np.asarray(sizes_m, dtype=np.float64).reshape(-1)

    def centre_pairs(g: int) -> tuple[np.ndarray, np.ndarray] | None:
        idx = np.flatnonzero(near_enough[g])
        if idx.shape[0] == 0:
            return None
        cg = order[bounds[g] : bounds[g + 1]]
        D = X[idx] - centres[g]
        rng = np.sqrt(np.einsum("tk,tk->t", D, D))
        # columns [0, H), [H, 2H), [2H, 3H): every heading's camera-frame x, y, z of each target
        H = cg.shape[0]
        p = D @ T_world_cam[cg, :3, :3].transpose(1, 2, 0).reshape(3, 3 * H)
        z = p[:, 2 * H :]
        # conservative cut (in front, in range, inside the image's cone), then the exact test on what is left
        t, h = np.nonzero((z >= near_m) & (z >= cone * rng[:, None] - RANGE_SLACK_M) & (rng <= far_m)[:, None])
        x, y, z = p[t, h], p[t, H + h], z[t, h]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * x / z + K[0, 2]
            v = K[1, 1] * y / z + K[1, 2]
        ok = (u >= -0.5 + mu) & (u <= width - 0.5 - mu) & (v >= -0.5 + mv) & (v <= height - 0.5 - mv)
        if size is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                ok &= K[0, 0] * size[idx[t]] / np.maximum(z, 1e-6) >= min_pixels
        return cg[h[ok]], idx[t[ok]]

    def block_pairs(ab: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
        return [p for p in map(centre_pairs, range(ab[0], ab[1])) if p is not None]

    # blocks of centres of about equal work: (targets in range) x (headings there)
    work = near_enough.sum(axis=1) * np.diff(bounds)
    found = [p for block in parallel_map(block_pairs, split_even(work, threads), threads) for p in block]
    if not found:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate([c for c, _ in found]), np.concatenate([t for _, t in found])


RANGE_SLACK_M = 1e-6
"""Slack of the range pre-cut (metres): far above rounding, so no target in range is dropped."""


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

    ``pos_index`` (C,) maps each camera to its row in ``panoramas``. The frustum, range and size tests run
    per camera centre on the targets in range (:func:`in_view_pairs`); only the pairs in view are tested
    for occlusion (:meth:`Panoramas.unoccluded_pairs`).
    """
    margin = cfg.image_margin_frac if margin_frac is None else margin_frac
    X = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((T_world_cam.shape[0], X.shape[0]), bool)
    cams, tgts = in_view_pairs(
        T_world_cam, K, width, height, X, cfg.near_m, far_m, margin, sizes_m, min_pixels, cfg.threads
    )
    if cams.shape[0]:
        vis = panoramas.unoccluded_pairs(X[tgts], np.asarray(pos_index, dtype=np.int64).reshape(-1)[cams])
        out[cams[vis], tgts[vis]] = True
    return out
