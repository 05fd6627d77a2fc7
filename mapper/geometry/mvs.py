"""``mvs`` reconstructor (default, no weights): classical multi-view stereo on the CPU.

Pipeline per call (a window of views, dense depth for ``targets``):

1. Poses first. Odometry / recorded poses are priors, not truth: SIFT tracks across the window are
   triangulated with the priors and refined on a GTSAM factor graph (``bundle``): robust reprojection
   factors, absolute priors, odometry between-factors whose rotation sigma comes from the source's
   declared accuracy (``View.prior_rel_rot_deg``) or from how well the images' essential-matrix rotation
   agrees with the priors, and a rescale to the priors' metric scale (images have none). Degenerate
   windows (little parallax, few inliers, a large scale change) keep the priors and say why in
   ``info["ba"]``. Every 5th track is held out of the solve: the refined poses replace the priors only
   when they explain those tracks clearly better ("holdout_not_better" otherwise), and the scene's depth
   scale moves only as far as the priors' own held-out error explains (at most 10 %). Surveyed
   calibrations (``pose_trusted``) stay fixed; priors declared with independent per-frame errors
   (``prior_rel_rot_deg = inf``) are not judged. Views without any pose are registered by PnP + RANSAC
   against the triangulated tracks.
2. Dense depth per target by plane sweep over its best sources (``viewselect``: triangulation angle, overlap), census
   cost, 4-path SGM aggregation, sub-plane refinement, over a depth range fitted to the sparse points,
   at ~224 px width (160 px on real frames measured as good).
3. Confidence = multi-view geometric consistency with neighbour depth maps (from this call or cached
   from earlier calls), damped on textureless pixels; depth and confidence are upsampled edge-aware.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry import bundle, features, planesweep, viewselect
from mapper.geometry.contract import FactoredReconstruction, View, factored_from_metric
from protocol.messages import Intrinsics
from protocol.poses import invert, rotation_angle_deg

F64 = np.ndarray


class MvsConfig(BaseModel):
    """Options of the ``mvs`` reconstructor."""

    model_config = ConfigDict(extra="forbid")
    sweep_width: int = Field(
        default=224, ge=32, le=1280,
        description="plane-sweep resolution (width, px); 224 measured best on the sim scenes, 160 on real frames",
    )
    output_width: int = Field(default=320, ge=32, le=4096, description="width of the returned depth maps, px")
    n_planes: int = Field(default=64, ge=8, le=256, description="depth planes, uniform in inverse depth")
    n_sources: int = Field(default=4, ge=1, le=8, description="neighbour views swept per target")
    source_min_triangulation_deg: float = Field(
        default=1.0, ge=0.0, description="a source view needs this triangulation angle at the target's median depth"
    )
    census_radius: int = Field(default=3, ge=1, le=5, description="census window radius at sweep resolution")
    census_stride: int = Field(default=2, ge=1, le=3, description="use every n-th pixel of the census window")
    sgm_p1: float = Field(default=0.1, ge=0, description="SGM penalty for a one-plane step")
    sgm_p2: float = Field(default=0.6, ge=0, description="SGM penalty for a larger jump (shrinks at edges)")
    best_k_sources: int = Field(default=2, ge=1, le=2, description="average the k cheapest sources per pixel")
    depth_min_m: float = Field(default=0.2, gt=0, description="lower clamp of the fitted depth range")
    depth_max_m: float = Field(default=20.0, gt=0, description="upper clamp of the fitted depth range")
    range_far_factor: float = Field(
        default=1.5, ge=1.0,
        description="the sweep reaches this many times the far (98th percentile) depth of the sparse points a view "
        "sees: textureless far surfaces (floor, walls) have no sparse points of their own",
    )
    default_range_m: tuple[float, float] = Field(
        default=(0.3, 8.0), description="depth range when too few sparse points see a view"
    )
    max_features: int = Field(default=2000, ge=50, description="SIFT keypoints per image")
    feature_width: int = Field(
        default=0, ge=0, description="SIFT runs on the image downscaled to this width when wider (0: full size)"
    )
    ratio: float = Field(default=0.8, gt=0, lt=1, description="Lowe ratio test threshold")
    max_pair_angle_deg: float = Field(default=80.0, description="skip matching prior views further apart")
    max_pair_rotation_deg: float = Field(
        default=10.0, gt=0,
        description="a pair whose essential-matrix rotation differs from the priors' relative rotation by more is "
        "dropped (wrong matches on repetitive texture); allows for the priors' error and the essential matrix's own",
    )
    refine_poses: bool = Field(default=True, description="bundle-adjust the pose priors before the sweep")
    sigma_rot_deg: float = Field(default=2.0, gt=0, description="pose prior std-dev, rotation (deg)")
    sigma_trans_m: float = Field(default=0.05, gt=0, description="pose prior std-dev, camera centre (m)")
    sigma_rel_rot_deg: float = Field(
        default=0.05, gt=0,
        description="std-dev of the priors' relative rotation between two views of one source (odometry between-"
        "factor, gyro / tracking grade). Rotation error between frames is what turns into depth error at small "
        "baselines; with ``rel_huber`` priors that the images contradict are let go",
    )
    sigma_rel_trans_m: float = Field(
        default=0.005, gt=0, description="std-dev floor of the priors' relative translation between two views (m)"
    )
    rel_trans_frac: float = Field(
        default=0.05, ge=0, description="relative-translation std-dev grows by this fraction of the distance moved"
    )
    rel_huber: float | None = Field(
        default=3.0, gt=0,
        description="Huber threshold (in sigmas) on the between-factors; None: Gaussian (priors always trusted)",
    )
    min_parallax_deg: float = Field(
        default=1.0, ge=0,
        description="median track triangulation angle under which the images cannot correct the priors (kept)",
    )
    max_scale_change: float = Field(
        default=0.05, ge=0,
        description="an adjustment that asks for a larger scale change than this is refused (priors kept); within "
        "it the result is rescaled to the priors' scale exactly: images carry no metric scale",
    )
    prior_match_px: float = Field(
        default=40.0, gt=0, description="matches farther than this from the prior's epipolar segment are dropped"
    )
    static_px: float = Field(
        default=2.0, ge=0, description="matches moving less than this while the camera moved are dropped"
    )
    holdout_every: int = Field(
        default=5, ge=0,
        description="every n-th track is held out of the adjustment and triangulated afresh with the priors and "
        "with the refined poses (0: none); the refined poses replace the priors only when they explain these tracks "
        "better (``holdout_min_gain``, ``holdout_min_px``). Not for surveyed calibrations nor for priors declared "
        "to have independent per-frame errors (+inf relative accuracy)",
    )
    holdout_min_gain: float = Field(
        default=0.15, ge=0, lt=1,
        description="the refined poses' held-out median error must be this fraction below the "
        "priors'",
    )
    holdout_min_px: float = Field(
        default=0.3, ge=0, description="... and at least this many pixels below it (accurate priors stay as they are)"
    )
    holdout_min_obs: int = Field(
        default=20, ge=1, description="held-out observations needed to judge; with fewer, the priors are kept"
    )
    max_depth_rescale: float = Field(
        default=0.10, ge=0,
        description="a refinement changes the scene's depth scale against the priors' by at most "
        "what their own held-out error explains at the tracks' parallax, and never by more than this fraction",
    )
    max_ba_rms_px: float = Field(default=4.0, gt=0, description="reject an adjustment whose RMS stays above")
    max_ba_sigmas: float = Field(
        default=5.0, gt=0, description="reject an adjustment that moves a prior by more than this many sigmas"
    )
    min_triangulation_deg: float = Field(default=1.0, ge=0, description="sparse points need this ray angle")
    max_tracks: int = Field(default=3000, ge=10, description="cap on tracks in the bundle adjustment")
    consistency_tol: float = Field(default=0.10, gt=0, description="relative depth tolerance of the check")
    consistency_px: float = Field(default=2.5, gt=0, description="reprojection tolerance (sweep pixels)")
    consistency_search_px: int = Field(
        default=0, ge=0, le=3, description="neighbour pixels within this radius of the projection may agree"
    )
    consistency_views: int = Field(default=2, ge=1, description="agreeing neighbours for full confidence")
    fill_neighbours: bool = Field(
        default=True, description="sweep neighbours without a depth map so targets can be cross-checked"
    )
    min_texture: float = Field(
        default=0.004, ge=0, description="grey std-dev (0-1) under which confidence fades out (to 0 at half of it)"
    )
    default_hfov_deg: float = Field(default=70.0, description="guessed field of view for views without intrinsics")
    cache_size: int = Field(default=64, ge=1, description="views whose features/depth/pose are cached")
    min_pnp_inliers: int = Field(default=25, ge=6, description="PnP inliers needed to accept an unposed view")
    threads: int = Field(
        default=1, ge=1, le=2,
        description="torch CPU threads while reconstructing (restored after). 1 by default: the sweep is many small "
        "ops and on a busy 2-core machine a second thread measured 2-3x slower from synchronisation",
    )


@dataclass
class _Prepared:
    view: View
    K: F64  # full resolution
    intr: Intrinsics
    T_prior: F64 | None
    feats: features.Features


def _relative_prior(v: View) -> bool:
    """Whether ``v``'s prior carries information relative to its source's other priors (undeclared, or declared
    with a finite relative accuracy), which a refinement could lose."""
    return v.prior_rel_rot_deg is None or bool(np.isfinite(v.prior_rel_rot_deg))


def _drift_variance(a: View, b: View, axes: slice) -> float:
    """Variance the pose error of one source accrued between views ``a`` and ``b`` along ``axes`` of the declared
    covariances (0:3 position, m^2; 3:6 rotation, rad^2): the largest growth of the diagonal between them
    (0 unless both declared a covariance; ``mapper.inbox.PriorAccuracy`` says why)."""
    if a.pose_covariance is None or b.pose_covariance is None:
        return 0.0
    grown = np.abs(np.diag(b.pose_covariance)[axes] - np.diag(a.pose_covariance)[axes])
    return float(grown.max())


def _guess_intrinsics(v: View, hfov_deg: float) -> Intrinsics:
    h, w = v.image.shape[:2]
    return Intrinsics.from_fov(w, h, hfov_deg)


def _resize_gray(image: np.ndarray, width: int, height: int) -> torch.Tensor:
    small = cv2.resize(features.to_gray(image), (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(small.astype(np.float32) / 255.0)


def _resize_rgb(image: np.ndarray, width: int, height: int) -> torch.Tensor:
    im = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(im.astype(np.float32) / 255.0).permute(2, 0, 1).contiguous()


def local_std(gray: torch.Tensor, radius: int) -> torch.Tensor:
    """Standard deviation of grey values in a (2r+1)^2 window."""
    k = 2 * radius + 1
    x = gray.view(1, 1, *gray.shape)
    m = torch.nn.functional.avg_pool2d(x, k, 1, radius, count_include_pad=False)
    m2 = torch.nn.functional.avg_pool2d(x * x, k, 1, radius, count_include_pad=False)
    return (m2 - m * m).clamp(min=0).sqrt()[0, 0]


@contextmanager
def compute_threads(n: int) -> Iterator[None]:
    """Limit torch, OpenCV and BLAS to ``n`` threads for the duration, then restore the caller's settings.

    The work here is many small operations; on a busy 2-core machine worker threads of each library spin
    waiting for each other and measured 3-10x slower than one thread.
    """
    torch_before, cv_before = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    blas = blas_controller()
    try:
        if blas is not None:
            with blas.limit(limits=n):
                yield
        else:
            yield
    finally:
        torch.set_num_threads(torch_before)
        cv2.setNumThreads(cv_before)


@functools.cache
def blas_controller() -> Any:
    """The process's ``threadpoolctl.ThreadpoolController``, looked up once (~10 ms in a worker: not per call; the
    BLAS libraries are loaded with numpy and torch, which this module imports); None without threadpoolctl
    (optional: BLAS then keeps its own thread count)."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    return ThreadpoolController()


def one_blas_thread() -> Any:
    """A context manager limiting BLAS to one thread (restored after); a no-op without threadpoolctl. For the
    small numeric products around the heavy work (composing, decoding a result, fusion): with BLAS's default pool
    (a thread per core) the idle thread spins after each product, and on a busy machine that costs more CPU than
    the products."""
    blas = blas_controller()
    return blas.limit(limits=1) if blas is not None else nullcontext()


class StageClock:
    """CPU seconds (this process, all threads) spent per named stage of one reconstruction: ``with clock("sweep"):``
    adds the block's CPU time to that stage. ``seconds()`` gives them with ``other`` for what no stage covered."""

    STAGES = ("features", "matching", "poses", "sweep", "consistency", "upsample")

    def __init__(self) -> None:
        self.start = time.process_time()
        self.spent = dict.fromkeys(self.STAGES, 0.0)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t = time.process_time()
        try:
            yield
        finally:
            self.spent[stage] += time.process_time() - t

    def seconds(self) -> dict[str, float]:
        total = time.process_time() - self.start
        return {**self.spent, "other": max(0.0, total - sum(self.spent.values())), "total": total}


class MvsReconstructor:
    """Classical RGB-only reconstruction: pose refinement then plane-sweep depth (see module docstring)."""

    name = "mvs"

    def __init__(self, **opts: Any) -> None:
        self.config = MvsConfig(**opts)
        self._feats = features.LruCache(self.config.cache_size)
        self._matches = features.LruCache(self.config.cache_size * 8)
        self._pair_rot = features.LruCache(self.config.cache_size * 16)  # (key a, key b) -> R_b_a, both orders
        self._depth = features.LruCache(self.config.cache_size)  # key -> (depth at sweep res, K sweep)
        self._reg_feats = features.LruCache(self.config.cache_size)  # registration features of map keyframes
        # (key, width, height) -> grey image at sweep size: a keyframe is a source of several later sweeps
        self._grays = features.LruCache(self.config.cache_size)

    def thread_limit(self) -> Any:
        """Context manager: torch, OpenCV and BLAS limited to this reconstructor's ``threads`` (restored after). A
        keyframe job runs the work around the reconstruction under it too (``mapper.work.compute``)."""
        return compute_threads(self.config.threads)

    def register(self, view: View, map_keyframes: Sequence[Any], config: Any = None) -> Any:
        """Pose of a view without extrinsics against mapped keyframes (``register.register_view``), reusing
        this reconstructor's feature cache across calls. Returns a ``PoseEstimate`` (check ``ok``)."""
        from mapper.geometry.register import register_view

        with self.thread_limit():
            return register_view(view, map_keyframes, config, cache=self._reg_feats)

    # ---- features -------------------------------------------------------------------------------------
    def features_of(self, v: View) -> features.Features:
        """SIFT features of a view, cached by (source_id, seq)."""
        f = self._feats.get(v.key)
        if f is None:
            img, scale = v.image, 1.0
            fw = self.config.feature_width
            if fw and img.shape[1] > fw:
                scale = img.shape[1] / fw
                img = np.asarray(cv2.resize(img, (fw, round(img.shape[0] / scale)), interpolation=cv2.INTER_AREA),
                                 dtype=np.uint8)
            f = features.extract_features(img, self.config.max_features)
            if scale != 1.0:  # keypoints back in full-image pixels (pixel centres scale about -0.5)
                f = features.Features((f.uv + 0.5) * scale - 0.5, f.desc)
            self._feats.put(v.key, f)
        return f  # type: ignore[return-value]

    def _verified_matches(self, a: _Prepared, b: _Prepared) -> np.ndarray:
        key = (a.view.key, b.view.key)
        m = self._matches.get(key)
        if m is None:
            swapped = self._matches.get((b.view.key, a.view.key))
            if swapped is not None:  # matches are symmetric: reuse the other order's
                return swapped[:, ::-1].copy()  # type: ignore[index]
        if m is None:
            m = features.match_features(a.feats, b.feats, self.config.ratio)
            if len(m) and a.T_prior is not None and b.T_prior is not None:
                T_b_a = invert(b.T_prior) @ a.T_prior
                ok = np.ones(len(m), bool)
                if rotation_angle_deg(np.eye(4), T_b_a) > 1.0 or np.linalg.norm(T_b_a[:3, 3]) > 0.01:
                    # The camera moved, so features that did not move in the image are fixed to the camera
                    # (robot body, gripper) and would drag the bundle adjustment to a degenerate answer.
                    flow = np.linalg.norm(a.feats.uv[m[:, 0]] - b.feats.uv[m[:, 1]], axis=1)
                    ok = flow > self.config.static_px
                ok &= features.prior_consistent(
                    a.feats.uv[m[:, 0]], b.feats.uv[m[:, 1]], a.K, b.K, T_b_a,
                    (self.config.depth_min_m, self.config.depth_max_m), self.config.prior_match_px,
                )
                m = m[ok]
            if len(m):
                ok, R_b_a = features.essential_geometry(a.feats.uv[m[:, 0]], b.feats.uv[m[:, 1]], a.K, b.K, 2.0)
                m = m[ok]
                if R_b_a is None or self._contradicts_priors(a, b, R_b_a):
                    # Too few inliers to verify, or a relative rotation no prior error explains: on repetitive
                    # texture (tiles, planks, wallpaper) the few matches of a wide-baseline pair are mostly
                    # wrong yet lie on epipolar lines, and their tracks pull the adjustment by degrees.
                    m = m[:0]
                else:  # both orders, so a lookup never needs to know which was matched
                    self._pair_rot.put(key, R_b_a)
                    self._pair_rot.put((b.view.key, a.view.key), R_b_a.T)
            self._matches.put(key, m)
        return m  # type: ignore[return-value]

    @staticmethod
    def _prior_disagreement_deg(a: _Prepared, b: _Prepared, R_b_a: F64) -> float | None:
        """Angle between the images' relative rotation ``R_b_a`` and the priors' (None without both priors)."""
        if a.T_prior is None or b.T_prior is None:
            return None
        return rotation_angle_deg(np.asarray(R_b_a), (invert(b.T_prior) @ a.T_prior)[:3, :3])

    def _contradicts_priors(self, a: _Prepared, b: _Prepared, R_b_a: F64) -> bool:
        """Whether the images' relative rotation is further from the priors' than ``max_pair_rotation_deg``."""
        disagree = self._prior_disagreement_deg(a, b, R_b_a)
        return disagree is not None and disagree > self.config.max_pair_rotation_deg

    # ---- poses ----------------------------------------------------------------------------------------
    def _prepare(self, views: Sequence[View]) -> list[_Prepared]:
        out = []
        for v in views:
            intr = v.intrinsics or _guess_intrinsics(v, self.config.default_hfov_deg)
            # Always the view's own prior: feeding refined poses back as priors would let one bad
            # adjustment drift every later window.
            out.append(_Prepared(v, intr.K(), intr, v.T_world_cam, self.features_of(v)))
        return out

    def _pairs(self, prep: list[_Prepared]) -> list[tuple[int, int]]:
        pairs = []
        for i in range(len(prep)):
            for j in range(i + 1, len(prep)):
                Ti, Tj = prep[i].T_prior, prep[j].T_prior
                if Ti is not None and Tj is not None:
                    ang = np.degrees(np.arccos(np.clip(Ti[:3, 2] @ Tj[:3, 2], -1, 1)))
                    if ang > self.config.max_pair_angle_deg:
                        continue
                pairs.append((i, j))
        return pairs

    def refine_poses(self, prep: list[_Prepared], info: dict[str, Any], clock: StageClock | None = None
                     ) -> tuple[list[F64 | None], np.ndarray]:
        """Bundle-adjust the priors; register unposed views. Returns poses (None = failed) and sparse
        world points with their observing views (for depth ranges): (P, 3) points, list per point.
        ``clock``: where the matching's CPU time is counted (the rest is the caller's "poses")."""
        clock = clock or StageClock()
        t0 = time.perf_counter()
        n = len(prep)
        with clock("matching"):
            pair_m = {p: self._verified_matches(prep[p[0]], prep[p[1]]) for p in self._pairs(prep)}
        info["pair_matches"] = {f"{i}-{j}": int(len(m)) for (i, j), m in pair_m.items()}
        posed = [i for i in range(n) if prep[i].T_prior is not None]
        poses: list[F64 | None] = [p.T_prior for p in prep]
        posed_pairs = {k: m for k, m in pair_m.items() if k[0] in posed and k[1] in posed}
        tracks = bundle.build_tracks([len(p.feats) for p in prep], posed_pairs)
        pts, obs = self._triangulate(prep, poses, tracks)
        info["n_tracks"] = len(pts)
        unposed = [i for i in range(n) if poses[i] is None]
        if self.config.refine_poses and len(pts) >= 8 and len(posed) >= 2:
            pts, obs = self._bundle(prep, poses, pts, obs, info, has_prior=[True] * n)
        for i in unposed:
            T, inl = self._register_against_tracks(i, prep, poses, pts, obs, pair_m)
            info.setdefault("registered", {})[prep[i].view.source_id] = {"inliers": inl, "ok": T is not None}
            poses[i] = T
        if any(poses[i] is not None for i in unposed) and len(pts) >= 8:
            has_prior = [i not in unposed for i in range(n)]
            pts, obs = self._bundle(prep, poses, pts, obs, info, has_prior=has_prior)
        info["t_poses_s"] = time.perf_counter() - t0
        return poses, pts

    def _triangulate(
        self, prep: list[_Prepared], poses: list[F64 | None], tracks: list[np.ndarray]
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        if not tracks:
            return np.zeros((0, 3)), []
        tracks = sorted(tracks, key=len, reverse=True)[: self.config.max_tracks]
        posed = np.array([T is not None for T in poses])
        # Every view's projection (zeros where unposed: no posed track reads them) and keypoints, indexed at once.
        P_all = np.stack([bundle.projection_matrix(p.K, T) if T is not None else np.zeros((3, 4))
                          for p, T in zip(prep, poses, strict=True)])
        uv_all = np.concatenate([p.feats.uv.reshape(-1, 2) for p in prep])
        uv_start = np.concatenate([[0], np.cumsum([len(p.feats) for p in prep])[:-1]]).astype(np.int64)
        posed_tracks = [tr[posed[tr[:, 0]]] for tr in tracks]
        posed_tracks = [tr for tr in posed_tracks if len(tr) >= 2]
        # Batched DLT: tracks of the same length share one stacked SVD.
        cand, cand_obs = [], []
        by_len: dict[int, list[np.ndarray]] = {}
        for tr in posed_tracks:
            by_len.setdefault(len(tr), []).append(tr)
        for group in by_len.values():
            obs_g = np.stack(group)  # (T, L, 2): view, keypoint
            Pg = P_all[obs_g[..., 0]]  # (T, L, 3, 4)
            uv = uv_all[uv_start[obs_g[..., 0]] + obs_g[..., 1]]  # (T, L, 2)
            Xg = bundle.triangulate_many(Pg, uv)
            for X, tr in zip(Xg, group, strict=True):
                if np.all(np.isfinite(X)):
                    cand.append(X)
                    cand_obs.append(tr)
        if not cand:
            return np.zeros((0, 3)), []
        # Keep points in front of every observing camera and within 25 px of every observation (the priors
        # can be off by ~10 px; the bundle adjustment tightens this afterwards).
        Xs = np.array(cand)
        pid = np.concatenate([np.full(len(t), i) for i, t in enumerate(cand_obs)])
        allobs = np.concatenate(cand_obs)
        bad = np.zeros(len(cand), bool)
        # Rays of a well-triangulated point meet at >= 1 deg somewhere; pure rotations give junk depths.
        min_cos = np.ones(len(cand))
        first_dir = np.zeros((len(cand), 3))
        seen = np.zeros(len(cand), bool)
        for v in np.unique(allobs[:, 0]):
            sel = allobs[:, 0] == v
            T_v = cast(F64, poses[v])
            pr, z = bundle.reproject(prep[v].K, T_v, Xs[pid[sel]])
            err = np.linalg.norm(pr - prep[v].feats.uv[allobs[sel, 1]], axis=1)
            bad[pid[sel][(z <= 0) | ~(err <= 25.0)]] = True
            ray = Xs[pid[sel]] - T_v[:3, 3]
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
            ids = pid[sel]
            new = ~seen[ids]
            first_dir[ids[new]] = ray[new]
            seen[ids] = True
            min_cos[ids] = np.minimum(min_cos[ids], np.sum(first_dir[ids] * ray, axis=1))
        bad |= min_cos > np.cos(np.radians(self.config.min_triangulation_deg))
        keep = np.flatnonzero(~bad)
        return Xs[keep].reshape(-1, 3), [cand_obs[i] for i in keep]

    def _bundle(
        self,
        prep: list[_Prepared],
        poses: list[F64 | None],
        pts: np.ndarray,
        obs: list[np.ndarray],
        info: dict[str, Any],
        has_prior: list[bool],
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        idx = [i for i in range(len(prep)) if poses[i] is not None]
        slot = {c: k for k, c in enumerate(idx)}
        oc, op, ouv, orig = [], [], [], []
        for p, tr in enumerate(obs):
            for o in tr:
                v, k = int(o[0]), int(o[1])
                if v in slot:
                    oc.append(slot[v])
                    op.append(p)
                    ouv.append(prep[v].feats.uv[k])
                    orig.append(o)
        c = self.config
        # A share of the tracks is held out to judge the result wherever a prior could be made worse by it: any
        # prior but a surveyed calibration and priors declared to have independent per-frame errors (no relative
        # information to lose: +inf accuracy).
        judged = any(has_prior[i] and not prep[i].view.pose_trusted and _relative_prior(prep[i].view) for i in idx)
        sources = sorted({prep[i].view.source_id for i in idx})
        group = [sources.index(prep[i].view.source_id) for i in idx]
        prob = bundle.BundleProblem(
            Ks=[prep[i].K for i in idx],
            T_world_cam=[poses[i] for i in idx],  # type: ignore[misc]
            points_world=pts,
            obs_cam=np.array(oc, np.int64),
            obs_pt=np.array(op, np.int64),
            obs_uv=np.array(ouv, np.float64).reshape(-1, 2),
            fixed=[prep[i].view.pose_trusted for i in idx],
            has_prior=[has_prior[i] for i in idx],
            prior_group=group,
            rel_rot_sigma_deg=self._relative_rotation_sigmas(prep, idx, group, has_prior),
            rel_trans_sigma_m=self._declared_translation_sigmas(prep, idx, group, has_prior),
            holdout=(np.arange(len(pts)) % c.holdout_every == c.holdout_every - 1
                     if judged and c.holdout_every > 1 else None),
        )
        res = bundle.bundle_adjust(
            prob, c.sigma_rot_deg, c.sigma_trans_m, sigma_rel_rot_deg=c.sigma_rel_rot_deg,
            sigma_rel_trans_m=c.sigma_rel_trans_m, rel_trans_frac=c.rel_trans_frac, min_parallax_deg=c.min_parallax_deg,
            max_scale_change=c.max_scale_change, rel_huber=c.rel_huber,
        )
        # A sane adjustment moves priors by a few sigma at most and fits the tracks; otherwise (repetitive
        # texture, wrong matches) keep the priors rather than poison the dense step.
        moved = [
            (rotation_angle_deg(res.T_world_cam[k], poses[i]) / self.config.sigma_rot_deg,  # type: ignore[arg-type]
             float(np.linalg.norm(res.T_world_cam[k][:3, 3] - poses[i][:3, 3])) / self.config.sigma_trans_m)  # type: ignore[index]
            for k, i in enumerate(idx) if has_prior[i]
        ]
        worst = max((max(a, b) for a, b in moved), default=0.0)
        accepted = (
            res.status == "ok" and res.rms_px_after <= self.config.max_ba_rms_px and worst <= self.config.max_ba_sigmas
        )
        status = res.status if res.status != "ok" or accepted else "moved_too_far"
        if accepted and judged and not self._holdout_says_better(res):
            # Tracks the solve did not see are explained no better by the refined poses: keep the priors (a
            # refinement of good priors over a short baseline can trade rotation against depth and rescale the
            # scene while fitting its own tracks as well as they do).
            accepted, status = False, "holdout_not_better"
        depth_ratio = 1.0
        if accepted and judged:
            depth_ratio = self._hold_depth_scale(prob, res, [has_prior[i] or prep[i].view.pose_trusted for i in idx],
                                                 c.max_depth_rescale)
        if accepted:
            for k, i in enumerate(idx):
                poses[i] = res.T_world_cam[k]
        info.setdefault("ba", []).append(
            {"rms_px_before": res.rms_px_before, "rms_px_after": res.rms_px_after, "nfev": res.n_iterations,
             "n_obs": len(oc), "n_points": len(pts), "max_move_sigmas": worst, "accepted": accepted,
             "status": status, "scale_correction": res.scale_correction,
             "median_parallax_deg": res.median_parallax_deg, "holdout_px_prior": res.holdout_px_prior,
             "holdout_px_refined": res.holdout_px_refined, "n_holdout_obs": res.n_holdout_obs,
             "depth_ratio": depth_ratio}
        )
        if not accepted:
            # Keep only the points that the priors themselves explain.
            keep_pts = np.ones(len(pts), bool)
            errs = np.zeros(len(oc))
            for k, i in enumerate(idx):
                sel = prob.obs_cam == k
                pr, z = bundle.reproject(prep[i].K, cast(F64, poses[i]), pts[prob.obs_pt[sel]])
                errs[sel] = np.where(z > 0, np.linalg.norm(pr - prob.obs_uv[sel], axis=1), np.inf)
            np.logical_and.at(keep_pts, prob.obs_pt, errs < 10.0)
            kept = np.flatnonzero(keep_pts)
            return pts[kept].reshape(-1, 3), [obs[j] for j in kept]
        # Drop observations that stayed far off, and points left with fewer than two views.
        per_point: dict[int, list[np.ndarray]] = {}
        for p, ok, o in zip(op, res.inlier_obs, orig, strict=True):
            if ok:
                per_point.setdefault(p, []).append(o)
        keep = [p for p, lst in per_point.items() if len(lst) >= 2]
        return res.points_world[keep].reshape(-1, 3), [np.array(per_point[p]) for p in keep]

    @staticmethod
    def _hold_depth_scale(prob: bundle.BundleProblem, res: bundle.BundleResult, anchored: list[bool],
                          max_change: float) -> float:
        """Keep the refined solution's scene scale (in place) within what the images can have measured, and
        return the depth ratio kept (refined / prior median depth of the same tracks).

        The adjustment keeps the priors' camera-centre scale, but freed relative rotations change where rays
        meet (vergence), so the scene's depth scale moves with them. Part of that is real: priors whose
        rotations are off by ~e/f rad (e: their held-out reprojection error, px; f: focal length, px) put the
        tracks' depths off by up to ~(e/f) / parallax, and the images correct it. A larger change is not
        something the images measure: unmodelled lens distortion or intrinsics errors pull the rotations and
        scale the scene by a few percent while the reprojections improve; and never more than ``max_change``
        (a larger change is a degenerate solve, not a measurement). That excess is taken out: camera
        centres and points are scaled about a surveyed camera's centre or else the anchored cameras' centroid
        (rotations and every reprojection unchanged); two surveyed cameras pin the scale themselves."""
        obs = (prob.obs_cam, prob.obs_pt, prob.obs_uv)
        with np.errstate(invalid="ignore"):
            _, z_prior = bundle.observation_errors(prob.Ks, prob.T_world_cam, prob.points_world, *obs)
            _, z_ref = bundle.observation_errors(prob.Ks, res.T_world_cam, res.points_world, *obs)
        good = res.inlier_obs & np.isfinite(z_prior) & np.isfinite(z_ref) & (z_prior > 0) & (z_ref > 0)
        if good.sum() < 10:
            return 1.0
        ratio = float(np.median(z_ref[good] / z_prior[good]))
        if not (np.isfinite(ratio) and ratio > 0):
            return 1.0
        # What the priors' own inconsistency explains: rotation errors of ~e/f rad (e: their held-out error, px)
        # move depth by ~(e/f) / parallax. A scale change within that the images measured; beyond it, not.
        f = float(np.mean([K[0, 0] for K in prob.Ks]))
        parallax = np.radians(max(res.median_parallax_deg, 1e-3))
        e = res.holdout_px_prior if np.isfinite(res.holdout_px_prior) else res.rms_px_before
        explained = float(min(np.log1p((e / f) / parallax), np.log1p(max_change)))
        kept = float(np.exp(np.clip(np.log(ratio), -explained, explained)))
        ratio = ratio / kept
        if abs(ratio - 1.0) < 1e-12:
            return kept
        centres = np.stack([T[:3, 3] for T in res.T_world_cam])
        fixed = np.flatnonzero(np.asarray(prob.fixed or [False] * len(centres), bool))
        if len(fixed) >= 2 and np.ptp(centres[fixed], axis=0).max() > 1e-9:
            return kept * ratio  # two surveyed cameras pin the scale themselves
        a = np.asarray(anchored, bool)
        # About a surveyed camera when there is one (it must not move), else the anchored cameras' centroid.
        c = centres[fixed[0]].copy() if len(fixed) else centres[a].mean(axis=0) if a.any() else centres.mean(axis=0)
        for T in res.T_world_cam:
            T[:3, 3] = c + (T[:3, 3] - c) / ratio
        res.points_world = c + (res.points_world - c) / ratio
        return kept

    def _holdout_says_better(self, res: bundle.BundleResult) -> bool:
        """Whether the refined poses explain the held-out tracks clearly better than the priors."""
        c = self.config
        if res.n_holdout_obs < c.holdout_min_obs:
            return False
        prior, refined = res.holdout_px_prior, res.holdout_px_refined
        return bool(refined <= (1.0 - c.holdout_min_gain) * prior and prior - refined >= c.holdout_min_px)

    @staticmethod
    def _chain_pairs(
        prep: list[_Prepared], idx: list[int], group: list[int], has_prior: list[bool]
    ) -> list[tuple[int, int]]:
        """Consecutive (camera a, camera b) of the bundle's odometry chain (prior-having, not fixed, one source)."""
        chain = [k for k, i in enumerate(idx) if has_prior[i] and not prep[i].view.pose_trusted]
        return [(a, b) for a, b in zip(chain[:-1], chain[1:], strict=False) if group[a] == group[b]]

    def _declared_translation_sigmas(
        self, prep: list[_Prepared], idx: list[int], group: list[int], has_prior: list[bool]
    ) -> dict[tuple[int, int], float]:
        """Translation std-dev floor of each between-factor where both views declare one (else the default)."""
        out = {}
        for ka, kb in self._chain_pairs(prep, idx, group, has_prior):
            va, vb = prep[idx[ka]].view, prep[idx[kb]].view
            da, db = va.prior_rel_trans_m, vb.prior_rel_trans_m
            if da is not None and db is not None:
                out[(ka, kb)] = float(np.sqrt(max(da, db) ** 2 + _drift_variance(va, vb, slice(0, 3))))
        return out

    def _relative_rotation_sigmas(
        self, prep: list[_Prepared], idx: list[int], group: list[int], has_prior: list[bool]
    ) -> dict[tuple[int, int], float]:
        """Std-dev of each odometry between-factor's rotation: what the views declare (``View.prior_rel_rot_deg``),
        else ``sigma_rel_rot_deg`` where the images agree with the priors' relative rotation and as loose as
        they disagree where they do not. Tracking-grade priors (video, VIO,
        mocap) then hold the rotation that small baselines cannot, while priors with independent per-frame
        errors cannot pin a wrong relative rotation on the tracks."""
        c = self.config
        out: dict[tuple[int, int], float] = {}
        for ka, kb in self._chain_pairs(prep, idx, group, has_prior):
            a, b = prep[idx[ka]], prep[idx[kb]]
            declared = [v.prior_rel_rot_deg for v in (a.view, b.view)]
            if declared[0] is not None and declared[1] is not None:  # the source knows its accuracy
                drift_deg2 = float(np.degrees(np.sqrt(_drift_variance(a.view, b.view, slice(3, 6))))) ** 2
                out[(ka, kb)] = float(np.sqrt(max(declared[0], declared[1]) ** 2 + drift_deg2))
                continue
            R_img = self._pair_rot.get((a.view.key, b.view.key))
            disagree = None if R_img is None else self._prior_disagreement_deg(a, b, cast(F64, R_img))
            if disagree is None:
                out[(ka, kb)] = c.sigma_rot_deg  # no image evidence: do not hold the pair tighter than alone
                continue
            out[(ka, kb)] = float(max(c.sigma_rel_rot_deg, disagree))
        return out

    def _register_against_tracks(
        self,
        i: int,
        prep: list[_Prepared],
        poses: list[F64 | None],
        pts: np.ndarray,
        obs: list[np.ndarray],
        pair_m: dict[tuple[int, int], np.ndarray],
    ) -> tuple[F64 | None, int]:
        lookup: dict[tuple[int, int], int] = {}
        for p, tr in enumerate(obs):
            for v, k in tr:
                lookup[(int(v), int(k))] = p
        corr: dict[int, int] = {}  # query keypoint -> point
        for (a, b), m in pair_m.items():
            if i not in (a, b):
                continue
            other = b if a == i else a
            for ka, kb in m:
                kq, ko = (ka, kb) if a == i else (kb, ka)
                pt = lookup.get((other, int(ko)))
                if pt is not None:
                    corr.setdefault(int(kq), pt)
        from mapper.geometry.register import pnp_pose

        if len(corr) < 6:
            return None, 0
        kq = np.array(list(corr.keys()))
        T, inl = pnp_pose(prep[i].feats.uv[kq], pts[np.array(list(corr.values()))], prep[i].K)
        if T is None or inl < self.config.min_pnp_inliers:
            return None, inl
        return T, inl

    # ---- dense ----------------------------------------------------------------------------------------
    def _seen_depths(self, r: int, prep: list[_Prepared], poses: list[F64 | None], pts: np.ndarray) -> np.ndarray:
        """Camera z of the sparse points that land inside view ``r``."""
        T_r = poses[r]
        assert T_r is not None
        if not len(pts):
            return np.zeros(0)
        uv, z = bundle.reproject(prep[r].K, T_r, pts)
        w, h = prep[r].intr.width, prep[r].intr.height
        return z[(z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]

    def _select_sources(self, r: int, prep: list[_Prepared], poses: list[F64 | None], seen: np.ndarray) -> list[int]:
        """Best sources for view ``r`` among the window's posed views; ``seen``: depths of the sparse points it sees."""
        T_r = poses[r]
        assert T_r is not None
        cands = [
            viewselect.Candidate(s, cast(F64, poses[s]), prep[s].intr)
            for s in range(len(prep)) if s != r and poses[s] is not None
        ]
        params = viewselect.ViewSelectParams(min_triangulation_deg=self.config.source_min_triangulation_deg)
        med = float(np.median(seen)) if len(seen) >= 5 else 2.0  # typical depth of what the view sees
        chosen = viewselect.select_sources(T_r, prep[r].intr, med, cands, self.config.n_sources, params)
        return [c.index for c in chosen]

    def _gray(self, v: View, width: int, height: int) -> torch.Tensor:
        """The grey image of a view at sweep size (:func:`_resize_gray`), cached by (source_id, seq) and size like
        its features: ~1.4 ms each time a view is a sweep's reference or source. Read only."""
        key = (v.key, width, height)
        g = self._grays.get(key)
        if g is None:
            g = _resize_gray(v.image, width, height)
            self._grays.put(key, g)
        return g  # type: ignore[return-value]

    def _depth_range(self, seen: np.ndarray) -> tuple[float, float]:
        """Sweep range fitted to the depths of the sparse points a view sees (``default_range_m`` if too few)."""
        c = self.config
        if len(seen) >= 10:
            lo, hi = np.percentile(seen, [2, 98])
            lo, hi = 0.7 * lo, c.range_far_factor * hi
            return float(max(c.depth_min_m, lo)), float(min(c.depth_max_m, max(hi, lo * 1.5)))
        return c.default_range_m

    def _sweep(
        self, r: int, prep: list[_Prepared], poses: list[F64 | None], pts: np.ndarray, sw: int, sh: int,
    ) -> tuple[np.ndarray, list[int]]:
        c = self.config
        seen = self._seen_depths(r, prep, poses, pts)
        srcs = self._select_sources(r, prep, poses, seen)
        if not srcs:
            return np.zeros((sh, sw), np.float32), []
        K_r = prep[r].intr.scaled(sw, sh).K()
        T_r = poses[r]
        assert T_r is not None
        lo, hi = self._depth_range(seen)
        params = planesweep.SweepParams(
            c.n_planes, c.census_radius, c.census_stride, c.sgm_p1, c.sgm_p2, c.best_k_sources
        )
        depth = planesweep.plane_sweep_depth(
            self._gray(prep[r].view, sw, sh), [self._gray(prep[s].view, sw, sh) for s in srcs], K_r,
            [prep[s].intr.scaled(sw, sh).K() for s in srcs],
            [invert(poses[s]) @ T_r for s in srcs], lo, hi, params,  # type: ignore[arg-type]
        )
        return depth.numpy().astype(np.float32), srcs

    def reconstruct(self, views: Sequence[View], targets: Sequence[int] | None = None) -> FactoredReconstruction:
        if not views:
            raise ValueError("reconstruct needs at least one view")
        with self.thread_limit():
            return self._reconstruct(views, targets)

    def _reconstruct(self, views: Sequence[View], targets: Sequence[int] | None) -> FactoredReconstruction:
        t_start = time.perf_counter()
        cpu_start = time.process_time()
        c = self.config
        clock = StageClock()
        info: dict[str, Any] = {"backend": self.name}
        with clock("features"):
            prep = self._prepare(views)
        if all(p.T_prior is None for p in prep):
            raise ValueError(
                "no view has a pose prior or calibration: the metric frame is undefined "
                "(give one view a pose, or use mapper.geometry.register.two_view_pose with a known baseline)"
            )
        t_m = clock.spent["matching"]
        with clock("poses"):
            poses, pts = self.refine_poses(prep, info, clock)
        clock.spent["poses"] -= clock.spent["matching"] - t_m  # the matching inside it is its own stage
        n = len(views)
        target_list = list(range(n)) if targets is None else sorted(set(targets))
        for t in target_list:
            if not 0 <= t < n:
                raise ValueError(f"target {t} out of range for {n} views")
        # Views that could not be posed get the first view's pose and no depth (confidence 0).
        failed = [i for i in range(n) if poses[i] is None]
        info["unposed"] = failed
        info["pose_ok"] = [poses[i] is not None for i in range(n)]
        T0 = poses[0] if poses[0] is not None else np.eye(4)
        t_dense = time.perf_counter()
        sw = c.sweep_width
        depth_lo: dict[int, np.ndarray] = {}
        sources: dict[int, list[int]] = {}
        shapes = {}
        for i in range(n):
            h, w = views[i].image.shape[:2]
            shapes[i] = (sw, max(8, round(h * sw / w)))
        for r in target_list:
            if poses[r] is None:
                continue
            with clock("sweep"):
                depth_lo[r], sources[r] = self._sweep(r, prep, poses, pts, *shapes[r])
        # Neighbour depth maps for the consistency check: this call's, else cached, else swept now.
        neigh_depth: dict[int, tuple[np.ndarray, F64]] = {}
        for r in list(depth_lo):
            for s in sources[r]:
                if s in depth_lo or s in neigh_depth:
                    continue
                cached = self._depth.get(prep[s].view.key)
                if cached is not None and cached[0].shape == (shapes[s][1], shapes[s][0]):  # type: ignore[index]
                    neigh_depth[s] = cached  # type: ignore[assignment]
        if c.fill_neighbours:
            for r in list(depth_lo):
                have = sum(1 for s in sources[r] if s in depth_lo or s in neigh_depth)
                for s in sources[r]:
                    if have >= c.consistency_views:
                        break
                    if s in depth_lo or s in neigh_depth:
                        continue
                    with clock("sweep"):
                        d, _ = self._sweep(s, prep, poses, pts, *shapes[s])
                    # Not cached for later jobs: swept again there with their own poses and sparse points, it
                    # agrees with their target better (cached, the sim's early keyframes lost up to 0.64 of
                    # their confident pixels: a map swept in a two-view window with refined odometry priors).
                    neigh_depth[s] = (d, prep[s].intr.scaled(*shapes[s]).K())
                    have += 1
        info["t_dense_s"] = time.perf_counter() - t_dense
        out_depth, out_conf, out_intr = [], [], []
        for i in range(n):
            h, w = views[i].image.shape[:2]
            ow = c.output_width
            oh = max(8, round(h * ow / w))
            intr_o = prep[i].intr.scaled(ow, oh)
            out_intr.append(intr_o)
            if i not in depth_lo or not sources[i]:
                out_depth.append(np.zeros((oh, ow), np.float32))
                out_conf.append(np.zeros((oh, ow), np.float32))
                continue
            d = depth_lo[i]
            K_lo = prep[i].intr.scaled(*shapes[i]).K()
            nbs = []
            for s in sources[i]:
                if s in depth_lo:
                    nbs.append((depth_lo[s], prep[s].intr.scaled(*shapes[s]).K(), poses[s]))
                elif s in neigh_depth:
                    nbs.append((neigh_depth[s][0], neigh_depth[s][1], poses[s]))
            with clock("consistency"):
                cnt = planesweep.consistency_count(
                    d, K_lo, cast(F64, poses[i]), cast(Any, nbs),
                    c.consistency_tol, c.consistency_px, c.consistency_search_px,
                )
                need = max(1, min(c.consistency_views, len(nbs)))
                conf = np.clip(cnt / need, 0.0, 1.0).astype(np.float32)
                tex = local_std(self._gray(views[i], *shapes[i]), c.census_radius).numpy()
                # Where the image is flat the cost has no minimum of its own: SGM fills it from the edges, and
                # neighbours may agree on the same guess, so consistency alone is not enough there.
                conf *= np.clip(2.0 * tex / max(c.min_texture, 1e-6) - 1.0, 0.0, 1.0)
                conf[d <= 0] = 0.0
            self._depth.put(prep[i].view.key, (d, K_lo))
            with clock("upsample"):
                dh, ch = planesweep.joint_bilateral_upsample(
                    torch.from_numpy(d), torch.from_numpy(conf),
                    _resize_rgb(views[i].image, *shapes[i]), _resize_rgb(views[i].image, ow, oh),
                )
            out_depth.append(dh.numpy().astype(np.float32))
            out_conf.append(ch.numpy().astype(np.float32))
        world: list[F64] = [cast(F64, poses[i]) if poses[i] is not None else T0 for i in range(n)]
        info["sources"] = {int(k): [int(s) for s in v] for k, v in sources.items()}
        info["T_world_cam"] = [None if p is None else np.asarray(p) for p in poses]
        info["t_total_s"] = time.perf_counter() - t_start
        info["cpu_total_s"] = time.process_time() - cpu_start
        info["cpu_stage_s"] = clock.seconds()
        recon = factored_from_metric(out_depth, world, out_conf, out_intr, info=info)
        recon.info["T_world_first"] = world[0]
        return recon
