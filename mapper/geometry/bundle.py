"""Feature tracks, triangulation and bundle adjustment with pose priors, on a GTSAM factor graph.

Odometry and recorded poses are priors, not truth: a bundle adjustment over feature tracks moves them to
agree with the images. Images carry no metric scale at all (scaling every camera centre and point about
one point leaves every reprojection unchanged), so the metric scale must come from the priors alone.

The factor graph (``bundle_adjust``), one ``Pose3`` per camera (key ``X(i)``, ``T_world_cam``: gtsam's
camera axes are OpenCV's) and one ``Point3`` per track point (key ``L(j)``):

* ``GenericProjectionFactorCal3_S2`` per observation, with a Huber loss: wrong matches that survived the
  match filters cost linearly, not quadratically.
* ``PriorFactorPose3`` on every free camera with a prior: it holds the world frame (gauge) and keeps
  the solution near the odometry.
* ``BetweenFactorPose3`` between consecutive prior-having cameras (list order, within a
  ``prior_group``), from their prior relative pose. Odometry drifts absolutely but is good relatively:
  at video rate consecutive cameras are 1-3 cm apart while the absolute prior sigma is ~5 cm, so an
  absolute prior alone lets the cameras slide together and the scene shrinks (seen as ~0.6x depth on
  real frames). The translation sigma grows with the step length (``rel_trans_frac``). The rotation
  sigma is per pair when the problem gives one (``BundleProblem.rel_rot_sigma_deg``: ``mvs`` sets it from
  the source's declared accuracy or from how far the images' own relative rotation is from the priors'),
  else ``sigma_rel_rot_deg`` (default: the absolute one, because priors with independent per-frame
  errors must not be held together). Tracking-grade priors want ~0.05 deg: at 1 cm steps and 1-2 m
  depth a 0.04 deg yaw trades against a uniform shift of inverse depth, i.e. ~8 % of point depth, which
  the pixels barely see. ``rel_huber`` makes these factors robust (linear cost beyond that many sigmas).
* Cameras marked ``fixed`` (surveyed calibrations) enter as ``NonlinearEqualityPose3`` and come back
  bit-identical.

It is solved twice from the priors (Levenberg-Marquardt): first with a Cauchy loss on the reprojections,
which all but ignores wrong matches (on repetitive texture they agree with each other and with the
epipolar lines, and pulled a single Huber solution by degrees on the sim scan walks, even from exact
priors); observations still off by more than ``outlier_px`` there are dropped, and the rest is solved
again with the Huber loss.

Scale safety by construction: after optimisation the scale ``s`` of the refined camera centres relative
to the prior centres is measured (least squares, prior = refined / s, over the cameras with a prior or
fixed, about their centroid or about the fixed camera's centre) and the solution is rescaled by
``1 / s`` about that point (centres and points; rotations and every reprojection unchanged), then
translated so the centroids coincide when no camera is fixed. The result therefore has the priors'
scale exactly, whatever the images pulled towards. Two fixed cameras at different places pin the scale
themselves and nothing is rescaled.

Degeneracies keep the priors unchanged and say why in ``BundleResult.status`` ("ok" otherwise):

* ``no_cameras``: no camera is free to refine.
* ``no_prior``: fewer than two cameras carry a prior or are fixed, or they all sit at one place (with
  parallax from the others): nothing holds the metric scale.
* ``few_inliers``: fewer than ``min_inliers`` observations (before) or inlier observations (after the
  optimisation): too little evidence to move the odometry.
* ``low_parallax``: the median over points of the largest angle between observing rays (prior poses)
  is below ``min_parallax_deg``: a (near) pure rotation, depth and translation are unobservable.
* ``scale_change``: the images asked for a scale change ``|1 - s|`` above ``max_scale_change``; that
  is a sign of wrong matches (static overlays, a moving object), since odometry does not allow it.
* ``solver_failed``: the linear solver gave up (an indeterminate system).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


MIN_REL_ROT_RAD = np.radians(0.001)
"""Smallest rotation std-dev of a between-factor (a declared 0 would be an infinite weight)."""
MIN_REL_TRANS_M = 1e-5
"""Smallest translation std-dev of a between-factor, metres."""


def build_tracks(n_kp: list[int], pair_matches: dict[tuple[int, int], I64]) -> list[I64]:
    """Join pairwise matches into tracks with union-find.

    n_kp: keypoint count per view; pair_matches[(i, j)]: (M, 2) keypoint indices in views i and j.
    Returns tracks as (L, 2) arrays of (view, keypoint) with L >= 2 and at most one keypoint per view
    (tracks that hit a view twice are inconsistent and dropped).
    """
    offsets = np.concatenate([[0], np.cumsum(n_kp)]).astype(np.int64)
    # Plain Python ints and lists: the union-find touches single elements, where numpy scalars cost ~10x.
    parent = list(range(int(offsets[-1])))
    pairs = [(int(offsets[i]), int(offsets[j]), m.tolist()) for (i, j), m in pair_matches.items()]

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for oi, oj, m in pairs:
        for a, b in m:
            ra, rb = find(oi + a), find(oj + b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    used = set()
    for oi, oj, m in pairs:
        for a, b in m:
            used.add(oi + a)
            used.add(oj + b)
    for node in used:
        groups.setdefault(find(node), []).append(node)
    multi = [sorted(nodes) for nodes in groups.values() if len(nodes) >= 2]
    if not multi:
        return []
    # All tracks at once: (view, keypoint) rows, then cut into one (L, 2) array per track.
    nodes_a = np.fromiter((n for nodes in multi for n in nodes), np.int64)
    views = np.searchsorted(offsets, nodes_a, side="right") - 1
    rows = np.stack([views, nodes_a - offsets[views]], axis=1)
    ends = np.cumsum([len(nodes) for nodes in multi])
    # Nodes are sorted within a track, so a view seen twice shows up as two equal neighbours.
    same_view = np.flatnonzero(views[1:] == views[:-1])
    twice = np.zeros(len(multi), bool)
    twice[np.searchsorted(ends, same_view + 1, side="right")[np.isin(same_view + 1, ends, invert=True)]] = True
    return [t.copy() for t, bad in zip(np.split(rows, ends[:-1]), twice, strict=True) if not bad]


def projection_matrix(K: F64, T_world_cam: F64) -> F64:
    """3x4 matrix mapping homogeneous world points to homogeneous pixels."""
    T_cam_world = np.linalg.inv(T_world_cam)
    return K @ T_cam_world[:3, :]


def triangulate(Ps: list[F64], uvs: F64) -> F64:
    """Linear (DLT) triangulation of one point from L >= 2 views: Ps 3x4 matrices, uvs (L, 2) (see
    :func:`triangulate_many`)."""
    return triangulate_many(np.stack(Ps)[None], np.asarray(uvs, np.float64)[None])[0]


def triangulate_many(Ps: F64, uvs: F64) -> F64:
    """Linear (DLT) triangulation of T points each seen in the same number L of views: Ps (T, L, 3, 4),
    uvs (T, L, 2) -> (T, 3); NaN where the solution is at infinity.

    Each point is solved about the mean centre of its cameras, then moved back: the DLT's algebraic error is not
    invariant to where the world's origin lies, so solving in world coordinates gave other points (and, through
    the checks on them, other tracks and depth) for the same cameras in a shifted world frame, and lost precision
    for cameras far from the origin."""
    Ps = np.asarray(Ps, np.float64)
    M, p4 = Ps[..., :3], Ps[..., 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        centres = -np.linalg.solve(M, p4[..., None])[..., 0]  # (T, L, 3): C with M C + p4 = 0
    c = centres.mean(axis=1)  # (T, 3)
    c = np.where(np.isfinite(c), c, 0.0)
    local = Ps.copy()
    local[..., 3] += np.einsum("tlij,tj->tli", M, c)  # P [I c; 0 1]: the same projection of X_local = X - c
    A = np.concatenate([uvs[..., 0:1] * local[:, :, 2] - local[:, :, 0],
                        uvs[..., 1:2] * local[:, :, 2] - local[:, :, 1]], axis=1)
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1]
    w = X[:, 3:4]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = X[:, :3] / w + c
    out[np.abs(w[:, 0]) <= 1e-12] = np.nan
    return np.asarray(out, np.float64)


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
    """3x3 intrinsics per camera."""
    T_world_cam: list[F64]
    """4x4 pose priors (camera to world, OpenCV axes); also the starting point."""
    points_world: F64
    """(P, 3) starting points, usually triangulated with the priors."""
    obs_cam: I64
    obs_pt: I64
    obs_uv: F64
    fixed: list[bool] = field(default_factory=list)
    """Per camera: held exactly (surveyed). Empty: none fixed."""
    has_prior: list[bool] = field(default_factory=list)
    """Per camera: its pose is a prior (odometry, recorded). Empty: all. Without a prior a camera is only
    a starting guess (e.g. a PnP registration) and is free."""
    prior_group: list[int] = field(default_factory=list)
    # Per between-factor rotation std-dev (deg), keyed by (camera a, camera b) of consecutive chain members;
    # pairs not listed use ``sigma_rel_rot_deg``.
    rel_rot_sigma_deg: dict[tuple[int, int], float] = field(default_factory=dict)
    # The same for the translation std-dev floor (m); pairs not listed use ``sigma_rel_trans_m``.
    rel_trans_sigma_m: dict[tuple[int, int], float] = field(default_factory=dict)
    """Per camera: odometry source. Between-factors link consecutive cameras of one group only (two
    robots, or a robot and a hand-held phone, share no odometry). Empty: one group."""
    holdout: NDArray[np.bool_] | None = None
    """Per point: held out of the solve, to judge it (``BundleResult.holdout_px_*``). None: none."""


@dataclass
class BundleResult:
    T_world_cam: list[F64]
    """Refined poses; the input priors themselves when ``status`` is not "ok"."""
    points_world: F64
    """(P, 3) refined points; the input points when ``status`` is not "ok"."""
    inlier_obs: NDArray[np.bool_]
    """Per observation: kept by the robust pass, in front of its camera and reprojected within 3 * huber_px
    (returned solution)."""
    rms_px_before: float
    """RMS reprojection error of the priors and input points (observations in front of their camera)."""
    rms_px_after: float
    """The same for the returned solution."""
    n_iterations: int
    """Levenberg-Marquardt iterations (0 when it did not run)."""
    status: str = "ok"
    """"ok" or why the priors were kept: no_cameras, no_prior, few_inliers, low_parallax, scale_change,
    solver_failed (see the module docstring)."""
    scale_correction: float = 1.0
    """1 / s, the factor applied to bring the refined scale back to the priors' (reported, not applied,
    when the status is scale_change or few_inliers after the optimisation)."""
    median_parallax_deg: float = 0.0
    """Median over points of the largest angle between their observing rays, with the prior poses."""
    n_inliers: int = 0
    """Number of True entries of ``inlier_obs``."""
    holdout_px_prior: float = float("nan")
    """Median reprojection error (px) of the held-out tracks (``BundleProblem.holdout``), each triangulated
    afresh with the prior poses; NaN without held-out tracks."""
    holdout_px_refined: float = float("nan")
    """The same with the refined poses (the priors' when ``status`` is not "ok")."""
    n_holdout_obs: int = 0
    """Observations of held-out tracks both errors are measured on."""


def observation_errors(Ks: list[F64], T_world_cam: list[F64], X_world: F64, oc: I64, op: I64, uv: F64
                       ) -> tuple[F64, F64]:
    """Reprojection error (px) and camera z of every observation (camera ``oc[k]`` sees point ``op[k]`` of
    ``X_world`` at ``uv[k]``); vectorised over observations."""
    T_cw = np.stack([np.linalg.inv(T) for T in T_world_cam]) if T_world_cam else np.zeros((0, 4, 4))
    Kst = np.stack(Ks) if Ks else np.zeros((0, 3, 3))
    p = np.einsum("nij,nj->ni", T_cw[oc, :3, :3], X_world[op]) + T_cw[oc, :3, 3]
    q = np.einsum("nij,nj->ni", Kst[oc], p)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(q[:, :2] / q[:, 2:3] - uv, axis=1)
    return err, z


def _rms(err: F64, z: F64) -> float:
    ok = (z > 0) & np.isfinite(err)
    return float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else 0.0


def _median_parallax_deg(centres: F64, X_world: F64, oc: I64, op: I64) -> float:
    """Median over points (with >= 2 observations) of the largest angle between observing rays."""
    order = np.argsort(op, kind="stable")
    pt, cam = op[order], oc[order]
    rays = X_world[pt] - centres[cam]
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
    min_cos = np.full(X_world.shape[0], np.inf)
    # Observations of one point are contiguous after the sort, so comparing every observation with the
    # d-th next one for d = 1 .. (longest track - 1) visits every pair of rays of every point.
    longest = int(np.bincount(pt).max()) if len(pt) else 0
    for d in range(1, longest):
        same = pt[:-d] == pt[d:]
        cos = np.sum(rays[:-d][same] * rays[d:][same], axis=1)
        np.minimum.at(min_cos, pt[:-d][same], cos)
    seen = np.isfinite(min_cos)
    if not seen.any():
        return 0.0
    return float(np.degrees(np.median(np.arccos(np.clip(min_cos[seen], -1.0, 1.0)))))


def holdout_error_px(Ks: list[F64], T_world_cam: list[F64], oc: I64, op: I64, uv: F64) -> tuple[float, int]:
    """Median reprojection error (px) of tracks triangulated afresh (linear DLT) with ``T_world_cam``: how well
    the poses explain tracks the solve did not see. ``oc``/``op``/``uv``: the tracks' observations (camera,
    point id, pixel); points with fewer than two observations are skipped. An observation behind its camera
    counts as off by 100 px. Returns (median, observations measured); (NaN, 0) when there are none."""
    order = np.argsort(op, kind="stable")
    oc, op, uv = oc[order], op[order], uv[order]
    _, start, count = np.unique(op, return_index=True, return_counts=True)
    Ps = np.stack([projection_matrix(K, T) for K, T in zip(Ks, T_world_cam, strict=True)]) if Ks else None
    errs: list[F64] = []
    for n in np.unique(count[count >= 2]).tolist():
        sel = np.flatnonzero(count == n)
        rows = (start[sel][:, None] + np.arange(n)[None, :])  # (T, n) observation rows per point
        assert Ps is not None
        X = triangulate_many(Ps[oc[rows]], uv[rows])
        ok = np.all(np.isfinite(X), axis=1)
        if not ok.any():
            continue
        rows, X = rows[ok], X[ok]
        flat = rows.reshape(-1)
        e, z = observation_errors(Ks, T_world_cam, np.repeat(X, n, axis=0), oc[flat], np.arange(len(flat)), uv[flat])
        errs.append(np.where((z > 0) & np.isfinite(e), e, 100.0))
    if not errs:
        return float("nan"), 0
    allerr = np.concatenate(errs)
    return float(np.median(allerr)), int(len(allerr))


def _pose_noise(rot_rad: float, trans_m: float) -> gtsam.noiseModel.Base:
    # gtsam orders Pose3 tangent vectors (rotation, translation), both in the pose's local frame.
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([rot_rad] * 3 + [trans_m] * 3))


def _pose_factors(
    T_prior: list[F64], fixed: NDArray[np.bool_], has_prior: NDArray[np.bool_], group: I64, prob: BundleProblem,
    sigma_rot_deg: float, sigma_trans_m: float, sigma_rel_rot_deg: float | None, sigma_rel_trans_m: float,
    rel_trans_frac: float, rel_huber: float | None,
) -> gtsam.NonlinearFactorGraph:
    """The factors on the cameras alone: equalities for fixed ones, absolute priors, odometry between-factors."""
    graph = gtsam.NonlinearFactorGraph()
    poses = [gtsam.Pose3(T) for T in T_prior]
    for i in np.flatnonzero(fixed).tolist():
        graph.add(gtsam.NonlinearEqualityPose3(X(i), poses[i]))
    prior_noise = _pose_noise(np.radians(sigma_rot_deg), sigma_trans_m)
    chain = np.flatnonzero(has_prior & ~fixed)
    for i in chain.tolist():
        graph.add(gtsam.PriorFactorPose3(X(i), poses[i], prior_noise))
    # Rotation carries no scale, so by default the relative rotation is trusted no more than the absolute
    # one: priors with independent rotation errors (no odometry) must not be held together more tightly.
    rel_rot_rad = np.radians(sigma_rot_deg if sigma_rel_rot_deg is None else sigma_rel_rot_deg)
    for g in np.unique(group[chain]):
        members = chain[group[chain] == g]
        for a, b in zip(members[:-1], members[1:], strict=True):
            rel = poses[a].between(poses[b])
            step_m = float(np.linalg.norm(rel.translation()))
            pair_rot = prob.rel_rot_sigma_deg.get((int(a), int(b)))
            pair_trans = prob.rel_trans_sigma_m.get((int(a), int(b)), sigma_rel_trans_m)
            if not (np.isfinite(pair_trans) and (pair_rot is None or np.isfinite(pair_rot))):
                continue  # independent per-frame errors: the absolute priors already say all there is
            # Floors: a declared accuracy of 0 (a perfect prior) must not become an infinite weight.
            noise = _pose_noise(max(rel_rot_rad if pair_rot is None else np.radians(pair_rot), MIN_REL_ROT_RAD),
                                max(pair_trans + rel_trans_frac * step_m, MIN_REL_TRANS_M))
            if rel_huber is not None:
                # Robust odometry: tight where the priors agree with the images (video-grade tracking), but a
                # prior that the images contradict by many sigmas (independent per-frame errors) costs
                # linearly and the tracks win.
                noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(rel_huber), noise)
            graph.add(gtsam.BetweenFactorPose3(X(int(a)), X(int(b)), rel, noise))
    return graph


def bundle_adjust(
    prob: BundleProblem,
    sigma_rot_deg: float = 1.0,
    sigma_trans_m: float = 0.03,
    huber_px: float = 2.0,
    max_iterations: int = 50,
    *,
    outlier_px: float = 2.0,
    sigma_px: float = 1.0,
    sigma_rel_rot_deg: float | None = None,
    sigma_rel_trans_m: float = 0.005,
    rel_trans_frac: float = 0.05,
    min_parallax_deg: float = 1.0,
    min_inliers: int = 30,
    max_scale_change: float = 0.05,
    rel_huber: float | None = None,
) -> BundleResult:
    """Refine camera poses and points against the pose priors (see the module docstring).

    sigma_rot_deg / sigma_trans_m: absolute prior per free camera with ``has_prior``. huber_px: Huber
    threshold of the reprojection error (and the Cauchy scale of the first pass); outlier_px: observations
    off by more after the first pass are dropped; sigma_px: the reprojection standard deviation (weight of
    the images against the priors); max_iterations: per pass. sigma_rel_rot_deg (None: sigma_rot_deg),
    sigma_rel_trans_m + rel_trans_frac * step length: between-factors on consecutive prior-having cameras
    (``prob.rel_rot_sigma_deg`` overrides the rotation sigma per pair; ``rel_huber``: robust kernel on them,
    in sigmas). min_parallax_deg, min_inliers, max_scale_change: the degeneracy checks. Returns the refined
    solution, or the priors with a status saying why.
    """
    n_cam = len(prob.Ks)
    fixed = np.array(prob.fixed or [False] * n_cam, bool)
    has_prior = np.array(prob.has_prior or [True] * n_cam, bool)
    group = np.array(prob.prior_group or [0] * n_cam, np.int64)
    anchored = fixed | has_prior  # cameras whose pose carries metric information
    T_prior = [np.asarray(T, np.float64) for T in prob.T_world_cam]
    C_prior = np.stack([T[:3, 3] for T in T_prior]) if n_cam else np.zeros((0, 3))
    pts0 = np.asarray(prob.points_world, np.float64).reshape(-1, 3)
    oc = np.asarray(prob.obs_cam, np.int64)
    op = np.asarray(prob.obs_pt, np.int64)
    ouv = np.asarray(prob.obs_uv, np.float64).reshape(-1, 2)

    err0, z0 = observation_errors(prob.Ks, T_prior, pts0, oc, op, ouv)
    rms0 = _rms(err0, z0)

    # Points seen by one camera only, or not finite, add nothing but an unobservable depth: leave them out.
    finite = np.all(np.isfinite(pts0), axis=1)
    n_views = np.zeros(len(pts0), np.int64)
    for c in range(n_cam):
        seen = np.zeros(len(pts0), bool)
        seen[op[oc == c]] = True
        n_views += seen
    in_graph_pt = finite & (n_views >= 2)
    held_pt = np.zeros(len(pts0), bool) if prob.holdout is None else np.asarray(prob.holdout, bool) & in_graph_pt
    held_obs = held_pt[op] if len(op) else np.zeros(0, bool)
    in_graph_pt &= ~held_pt
    in_graph_obs = in_graph_pt[op] if len(op) else np.zeros(0, bool)
    parallax = _median_parallax_deg(C_prior, pts0, oc[in_graph_obs], op[in_graph_obs])

    def holdout(T: list[F64]) -> tuple[float, int]:
        return holdout_error_px(prob.Ks, T, oc[held_obs], op[held_obs], ouv[held_obs])

    def keep_priors(status: str, scale_correction: float = 1.0, n_iterations: int = 0) -> BundleResult:
        inl = (err0 < 3.0 * huber_px) & (z0 > 0)
        h_prior, n_h = holdout(T_prior)
        return BundleResult(
            T_world_cam=[T.copy() for T in T_prior], points_world=pts0.copy(), inlier_obs=inl,
            rms_px_before=rms0, rms_px_after=rms0, n_iterations=n_iterations, status=status,
            scale_correction=scale_correction, median_parallax_deg=parallax, n_inliers=int(inl.sum()),
            holdout_px_prior=h_prior, holdout_px_refined=h_prior, n_holdout_obs=n_h,
        )

    if not np.any(~fixed):
        return keep_priors("no_cameras")
    # Anchors all at one place hold no scale either; under a pure rotation, though, low_parallax says more.
    anchors_coincide = np.ptp(C_prior[anchored], axis=0).max() <= 1e-9 if anchored.any() else True
    if anchored.sum() < 2 or (anchors_coincide and parallax >= min_parallax_deg):
        return keep_priors("no_prior")
    if in_graph_obs.sum() < min_inliers:
        return keep_priors("few_inliers")
    if parallax < min_parallax_deg:
        return keep_priors("low_parallax")

    pose_graph = _pose_factors(
        T_prior, fixed, has_prior, group, prob, sigma_rot_deg, sigma_trans_m, sigma_rel_rot_deg, sigma_rel_trans_m,
        rel_trans_frac, rel_huber,
    )
    cals = [gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]) for K in prob.Ks]

    def solve(use_obs: NDArray[np.bool_], kernel: gtsam.noiseModel.mEstimator.Base
              ) -> tuple[list[F64], F64, NDArray[np.bool_], int]:
        """One Levenberg-Marquardt run from the priors over the observations ``use_obs`` (a point needs two).
        Returns the poses, the points (the input ones where not solved), which points were solved, iterations."""
        counts = np.bincount(op[use_obs], minlength=len(pts0))
        obs_sel = np.flatnonzero(use_obs & (counts[op] >= 2))
        held = np.zeros(len(pts0), bool)
        held[op[obs_sel]] = True
        graph = gtsam.NonlinearFactorGraph(pose_graph)
        values = gtsam.Values()
        for i in range(n_cam):
            values.insert(X(i), gtsam.Pose3(T_prior[i]))
        for j in np.flatnonzero(held).tolist():
            values.insert(L(j), pts0[j])
        pix_noise = gtsam.noiseModel.Robust.Create(kernel, gtsam.noiseModel.Isotropic.Sigma(2, sigma_px))
        for c, j, uv in zip(oc[obs_sel].tolist(), op[obs_sel].tolist(), ouv[obs_sel], strict=True):
            graph.add(gtsam.GenericProjectionFactorCal3_S2(uv, pix_noise, X(c), L(j), cals[c]))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        out = optimizer.optimize()
        T = [T_prior[i].copy() if fixed[i] else out.atPose3(X(i)).matrix() for i in range(n_cam)]
        pts = pts0.copy()
        if held.any():
            pts[held] = gtsam.utilities.extractPoint3(out)  # sorted by key, i.e. by point index
        return T, pts, held, optimizer.iterations()

    # Two passes, as SfM systems do: a redescending (Cauchy) loss finds the solution that most tracks agree on
    # even when wrong matches of repetitive texture survived the match filters (they pull a Huber solution
    # by degrees); observations still off by more than ``outlier_px`` there are dropped, and the inliers are
    # solved again from the priors with the Huber loss.
    m_est = gtsam.noiseModel.mEstimator
    try:
        T_first, pts_first, _, n_it = solve(in_graph_obs, m_est.Cauchy.Create(huber_px / sigma_px))
        err1, z1 = observation_errors(prob.Ks, T_first, pts_first, oc, op, ouv)
        keep_obs = in_graph_obs & (err1 <= outlier_px) & (z1 > 0)
        if keep_obs.sum() < min_inliers:
            return keep_priors("few_inliers", n_iterations=n_it)
        T_ref, pts, solved_pt, n_it2 = solve(keep_obs, m_est.Huber.Create(huber_px / sigma_px))
        n_it += n_it2
    except RuntimeError:
        return keep_priors("solver_failed")
    C_ref = np.stack([T[:3, 3] for T in T_ref])

    # Scale about a fixed camera when there is one (it must not move), else about the centroid of the
    # anchored cameras; two fixed cameras at different places pin the scale by themselves.
    fixed_ids = np.flatnonzero(fixed)
    if len(fixed_ids) and np.ptp(C_prior[fixed_ids], axis=0).max() > 1e-9:
        s = 1.0
        c_ref = c_pri = C_prior[fixed_ids[0]]
    else:
        c_pri = C_prior[fixed_ids[0]] if len(fixed_ids) else C_prior[anchored].mean(0)
        c_ref = C_ref[fixed_ids[0]] if len(fixed_ids) else C_ref[anchored].mean(0)
        # Regress the priors on the refined centres (prior = s_inv * refined): the images fix the shape far
        # better than the priors do, and regressing the other way would inflate the scale by the priors'
        # own noise (regression dilution). Multiplying by s_inv makes that scale exactly 1.
        d_ref, d_pri = C_ref[anchored] - c_ref, C_prior[anchored] - c_pri
        den = float(np.sum(d_ref**2))
        s_inv = float(np.sum(d_ref * d_pri)) / den if den > 1e-18 else 1.0
        s = 1.0 / s_inv if s_inv > 0 else 0.0
    if not s > 0:
        return keep_priors("scale_change", n_iterations=n_it)
    for T in T_ref:
        T[:3, 3] = c_pri + (T[:3, 3] - c_ref) / s
    pts = np.where(solved_pt[:, None], c_pri + (pts - c_ref) / s, pts)
    for i in fixed_ids.tolist():
        T_ref[i] = T_prior[i].copy()  # exact, not merely to rounding

    err, z = observation_errors(prob.Ks, T_ref, pts, oc, op, ouv)
    inl = keep_obs & (err < 3.0 * huber_px) & (z > 0)
    if inl.sum() < min_inliers:
        return keep_priors("few_inliers", 1.0 / s, n_it)
    if abs(1.0 - s) > max_scale_change:
        return keep_priors("scale_change", 1.0 / s, n_it)
    h_prior, n_h = holdout(T_prior)
    h_ref, _ = holdout(T_ref)
    return BundleResult(
        T_world_cam=T_ref, points_world=pts, inlier_obs=inl, rms_px_before=rms0, rms_px_after=_rms(err, z),
        n_iterations=n_it, status="ok", scale_correction=1.0 / s, median_parallax_deg=parallax,
        n_inliers=int(inl.sum()), holdout_px_prior=h_prior, holdout_px_refined=h_ref, n_holdout_obs=n_h,
    )
