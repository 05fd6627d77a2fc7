"""Loop closure for moving cameras: a planar pose graph over each robot's keyframes (GTSAM).

Odometry drifts: a robot that comes back to a room after 20 m is 0.5 m and several degrees off, and what it
maps there lands beside what it mapped the first time (duplicates, misplaced nodes). The fix is the classical
one: a pose graph per moving source whose nodes are its keyframes, joined by

* odometry between-factors from consecutive pose priors, with the sigmas of a random-walk drift model
  (variance grows with the distance driven and the angle turned: ``PoseGraphConfig.odom_*``);
* loop-closure between-factors from a new keyframe to OLD keyframes of the same place (candidates by the
  corrected pose: near, similar heading, far back along the path), measured by PnP of the new image's SIFT
  features against the old keyframe's features lifted with its own reconstructed depth, refused unless the
  geometry agrees (inliers, camera height and tilt, a bounded correction) and confirmed by a second,
  independent measurement (another old keyframe, or the next keyframe); robust (Huber) noise.

* optionally (``manhattan``: a site whose walls follow the world's x and y axes, like the simulated
  apartments) a unary heading factor per keyframe from its horizontal image lines (:func:`line_heading`):
  the heading modulo 90 deg, measured afresh at every keyframe, so heading drift cannot build up between
  loops. On the recorded demo runs it took the robot's heading error from 3.4-4.0 deg to 0.4-0.5 deg
  (median) and its position error from 0.25 to 0.07 m on two of three runs.

Robots drive on a floor, so the graph is planar (``Pose2``: camera centre x, y and optical-axis heading);
height, pitch and roll stay the prior's. The graph is small (a few hundred keyframes) and solved in batch
(Levenberg-Marquardt) whenever a keyframe brings a loop or a heading; otherwise a new keyframe takes the last
correction.

The correction of keyframe ``i`` is the planar world transform ``D_i`` with ``pose_i = D_i @ odom_i``
(:func:`lift` makes it 4x4). The mapper applies the newest correction to the source's incoming frames and,
when a solution moves older keyframes, moves them and what they fused (:func:`node_move`).

Pure apart from the keyframe store it owns (features and sparse depth of past keyframes, bounded).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import cv2
import gtsam
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry import features
from mapper.geometry.register import pnp_pose
from protocol.poses import rotation_angle_deg, wrap_angle, yaw_of

F64 = NDArray[np.float64]
Key = tuple[str, int]


class PoseGraphConfig(BaseModel):
    """Loop closure of moving sources' odometry (``mapper.posegraph``)."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(default=False, description="build a pose graph per moving source and close loops")
    odom_trans_std_per_sqrt_m: float = Field(
        default=0.02, gt=0, description="odometry position random walk: std-dev (m) after 1 m driven, grows with sqrt"
    )
    odom_rot_std_deg_per_sqrt_m: float = Field(
        default=0.75, gt=0, description="odometry heading random walk per driven metre (deg after 1 m, sqrt growth)"
    )
    odom_rot_std_deg_per_sqrt_rad: float = Field(
        default=0.3, ge=0, description="odometry heading random walk per radian turned (deg, sqrt growth)"
    )
    odom_floor_trans_m: float = Field(default=0.005, gt=0, description="smallest odometry translation std-dev (m)")
    odom_floor_rot_deg: float = Field(default=0.05, gt=0, description="smallest odometry heading std-dev (deg)")
    loop_sigma_trans_m: float = Field(default=0.05, gt=0, description="loop measurement std-dev, translation (m)")
    loop_sigma_rot_deg: float = Field(default=1.0, gt=0, description="loop measurement std-dev, heading (deg)")
    loop_min_travel_m: float = Field(
        default=2.0, ge=0, description="an old keyframe is a loop candidate only this far back along the path (m)"
    )
    loop_max_distance_m: float = Field(default=1.5, gt=0, description="candidate camera centres within (m)")
    loop_max_angle_deg: float = Field(default=35.0, gt=0, description="candidate headings within (deg)")
    loop_candidates: int = Field(default=3, ge=1, le=8, description="old keyframes measured per new keyframe")
    loop_min_inliers: int = Field(
        default=20, ge=6,
        description="PnP inliers needed for a loop measurement (also checked against the epipolar geometry and "
        "confirmed by a second one; 20 on the recorded demo runs: all confirmed loops within 1 cm)",
    )
    loop_min_inlier_ratio: float = Field(default=0.3, ge=0, le=1, description="PnP inliers / 2D-3D matches needed")
    loop_reproj_px: float = Field(default=3.0, gt=0, description="PnP RANSAC reprojection threshold (px)")
    loop_max_rotation_disagreement_deg: float = Field(
        default=1.0, gt=0, description="a PnP rotation this far from the essential matrix's refutes the loop (deg)"
    )
    loop_max_direction_disagreement_deg: float = Field(
        default=20.0, gt=0,
        description="a PnP direction of travel this far from the essential matrix's refutes the loop (deg); checked "
        "when the cameras are at least ``loop_min_baseline_m`` apart",
    )
    loop_min_baseline_m: float = Field(default=0.2, ge=0, description="see loop_max_direction_disagreement_deg")
    loop_max_height_m: float = Field(
        default=0.1, gt=0, description="a measured camera height this far from the prior's refutes the loop (m)"
    )
    loop_max_tilt_deg: float = Field(
        default=3.0, gt=0, description="a measured camera tilt (pitch, roll) this far from the prior's refutes it"
    )
    loop_max_correction_m: float = Field(
        default=1.2, gt=0, description="a loop that moves the new keyframe farther than this is refused (m)"
    )
    loop_max_correction_deg: float = Field(default=15.0, gt=0, description="... or turns it more than this (deg)")
    confirm_m: float = Field(
        default=0.15, gt=0, description="two loop measurements confirm each other when their corrections agree (m)"
    )
    confirm_deg: float = Field(default=2.0, gt=0, description="... and within this heading (deg)")
    confirm_keyframes: int = Field(
        default=3, ge=0, description="a loop measurement waits this many keyframes for its confirmation"
    )
    loop_huber: float = Field(
        default=3.0, gt=0,
        description="Huber threshold on loop factors (sigmas). Convex on purpose: a redescending kernel (Cauchy) "
        "keeps a many-sigma loop from pulling the path off the odometry at all, and loops are verified first",
    )
    manhattan: bool = Field(
        default=False,
        description="the site's walls run along the world's x and y axes (a Manhattan world, like the simulated "
        "apartments): each keyframe's horizontal image lines then measure its absolute heading modulo 90 deg, a "
        "unary factor that stops heading drift between loops. Off for sites without that structure",
    )
    manhattan_sigma_deg: float = Field(default=1.5, gt=0, description="std-dev of one keyframe's line heading (deg)")
    manhattan_min_concentration: float = Field(
        default=0.6, ge=0, le=1,
        description="the lines' directions must agree this well (resultant length of 4x their angles, 0..1)",
    )
    manhattan_min_lines: int = Field(default=6, ge=2, description="horizontal line segments needed")
    manhattan_max_correction_deg: float = Field(
        default=12.0, gt=0, description="a line heading farther than this from the current estimate is refused (deg)"
    )
    max_features: int = Field(default=2000, ge=50, description="SIFT features per keyframe")
    min_confidence: float = Field(default=0.5, ge=0, le=1, description="depth confidence to lift a feature")
    max_keyframes: int = Field(default=600, ge=10, description="keyframes per source in the graph (oldest dropped)")
    min_move_m: float = Field(
        default=0.02, ge=0, description="stored keyframes and nodes are moved when their correction changes more"
    )


# -- planar poses -------------------------------------------------------------------------------------
def planar(T_world_cam: F64) -> F64:
    """(x, y, heading) of a camera: its centre on the floor plane and its optical axis' heading (rad)."""
    return np.array([T_world_cam[0, 3], T_world_cam[1, 3], yaw_of(T_world_cam)])


def se2(p: F64) -> F64:
    """3x3 homogeneous matrix of a planar pose (x, y, theta)."""
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]])


def from_se2(M: F64) -> F64:
    """(x, y, theta) of a 3x3 homogeneous planar matrix."""
    return np.array([M[0, 2], M[1, 2], math.atan2(M[1, 0], M[0, 0])])


def lift(D: F64) -> F64:
    """The 4x4 world transform of a planar one: a rotation about the vertical axis and a floor translation."""
    T = np.eye(4)
    T[:2, :2] = D[:2, :2]
    T[:2, 3] = D[:2, 2]
    return T


def odometry_sigmas(rel: F64, cfg: PoseGraphConfig) -> F64:
    """Std-devs (x, y, theta) of an odometry step ``rel`` (x, y, theta) under the random-walk drift model."""
    d = float(np.hypot(rel[0], rel[1]))
    st = max(cfg.odom_floor_trans_m, cfg.odom_trans_std_per_sqrt_m * math.sqrt(d))
    var_th = (math.radians(cfg.odom_rot_std_deg_per_sqrt_m) ** 2 * d
              + math.radians(cfg.odom_rot_std_deg_per_sqrt_rad) ** 2 * abs(rel[2]))
    sth = max(math.radians(cfg.odom_floor_rot_deg), math.sqrt(var_th))
    # Heading error times the distance driven shows up as sideways error within the step.
    return np.array([st, st + sth * d, sth])


def tilt_deg(A: F64, B: F64) -> float:
    """Angle between two cameras' rotations once their headings are taken out (pitch and roll difference)."""
    ya, yb = planar(A)[2], planar(B)[2]
    Ra = lift(se2(np.array([0.0, 0.0, -ya])))[:3, :3] @ A[:3, :3]
    Rb = lift(se2(np.array([0.0, 0.0, -yb])))[:3, :3] @ B[:3, :3]
    return rotation_angle_deg(Ra, Rb)


def line_heading(image: NDArray[np.uint8], K: F64, T_world_cam: F64, min_length_px: int = 20,
                 min_plane_tilt_deg: float = 20.0) -> tuple[float, float, int] | None:
    """How far the horizontal lines an image shows are turned from the world's x / y axes, given the camera
    pose ``T_world_cam``: (offset in (-45, 45] deg as radians, concentration 0..1, lines used), None with
    fewer than 2 lines. In a Manhattan world the offset is the pose's heading error (modulo 90 deg).

    Each segment (Canny + probabilistic Hough) spans a plane through the camera centre; a horizontal world
    line lies along the horizontal direction of that plane. Planes close to vertical are skipped (they hold
    vertical edges, whose horizontal direction means nothing). Directions are averaged as 4x their angle,
    weighted by segment length."""
    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    segs = cv2.HoughLinesP(cv2.Canny(grey, 50, 150), 1, np.pi / 360, 25, minLineLength=min_length_px, maxLineGap=3)
    if segs is None:
        return None
    s = np.asarray(segs, np.float64).reshape(-1, 4)
    Kinv = np.linalg.inv(K)
    a = np.concatenate([s[:, :2], np.ones((len(s), 1))], axis=1) @ Kinv.T
    b = np.concatenate([s[:, 2:], np.ones((len(s), 1))], axis=1) @ Kinv.T
    n = np.cross(a, b) @ T_world_cam[:3, :3].T  # plane normals in the world
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    keep = np.abs(n[:, 2]) >= math.sin(math.radians(min_plane_tilt_deg))
    if keep.sum() < 2:
        return None
    d = np.cross(n[keep], np.array([0.0, 0.0, 1.0]))  # the plane's horizontal direction
    ang = np.arctan2(d[:, 1], d[:, 0])
    w = np.hypot(s[keep, 2] - s[keep, 0], s[keep, 3] - s[keep, 1])
    c, sn = float(np.sum(w * np.cos(4 * ang))), float(np.sum(w * np.sin(4 * ang)))
    return math.atan2(sn, c) / 4.0, math.hypot(c, sn) / float(w.sum()), int(keep.sum())


# -- the graph --------------------------------------------------------------------------------------
@dataclass
class Loop:
    """A loop-closure measurement: keyframe ``new`` seen from keyframe ``old`` at planar ``rel``."""

    old: Key
    new: Key
    rel: F64  # (x, y, theta) of new in old's planar frame
    inliers: int
    correction: F64  # 3x3 planar world transform from ``new``'s odometry to where the loop puts it
    confirmed: bool = False


@dataclass
class SourceGraph:
    """One moving source's keyframes, odometry and loops; ``est`` is the current solution."""

    cfg: PoseGraphConfig
    keys: list[Key] = field(default_factory=list)
    odom: list[F64] = field(default_factory=list)  # planar odometry pose per keyframe
    est: list[F64] = field(default_factory=list)  # planar corrected pose per keyframe
    path_m: list[float] = field(default_factory=list)  # distance driven up to each keyframe
    loops: list[Loop] = field(default_factory=list)
    headings: dict[Key, float] = field(default_factory=dict)  # absolute heading measurements (rad), by keyframe

    def index(self, key: Key) -> int | None:
        try:
            return self.keys.index(key)
        except ValueError:
            return None

    def correction(self, i: int = -1) -> F64:
        """The 3x3 world transform D with est_i = D @ odom_i (identity before any keyframe)."""
        if not self.keys:
            return np.eye(3)
        return se2(self.est[i]) @ np.linalg.inv(se2(self.odom[i]))

    def add(self, key: Key, odom: F64) -> F64:
        """Append a keyframe by its planar odometry pose; returns its predicted corrected pose (the last
        keyframe's correction carried over). Drops the oldest keyframe beyond ``max_keyframes``."""
        D = self.correction()
        prev_path = self.path_m[-1] if self.path_m else 0.0
        step = float(np.hypot(*(odom[:2] - self.odom[-1][:2]))) if self.odom else 0.0
        self.keys.append(key)
        self.odom.append(np.asarray(odom, np.float64))
        self.est.append(from_se2(D @ se2(odom)))
        self.path_m.append(prev_path + step)
        if len(self.keys) > self.cfg.max_keyframes:
            gone = self.keys[0]
            del self.keys[0], self.odom[0], self.est[0], self.path_m[0]
            self.loops = [lp for lp in self.loops if lp.old != gone]
            self.headings.pop(gone, None)
        return self.est[-1]

    def predicted_rel(self, old: int, new: int) -> F64:
        return from_se2(np.linalg.inv(se2(self.est[old])) @ se2(self.est[new]))

    def solve(self) -> None:
        """Batch Levenberg-Marquardt over odometry and confirmed loops; the first keyframe is held."""
        if len(self.keys) < 2:
            return
        X = gtsam.symbol_shorthand.X
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*self.est[0]),
                                         gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-4, 1e-4, 1e-5]))))
        for i, p in enumerate(self.est):
            values.insert(X(i), gtsam.Pose2(*p))
        for i in range(1, len(self.keys)):
            rel = from_se2(np.linalg.inv(se2(self.odom[i - 1])) @ se2(self.odom[i]))
            noise = gtsam.noiseModel.Diagonal.Sigmas(odometry_sigmas(rel, self.cfg))
            graph.add(gtsam.BetweenFactorPose2(X(i - 1), X(i), gtsam.Pose2(*rel), noise))
        c = self.cfg
        loop_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(c.loop_huber),
            gtsam.noiseModel.Diagonal.Sigmas(np.array([c.loop_sigma_trans_m, c.loop_sigma_trans_m,
                                                       math.radians(c.loop_sigma_rot_deg)])))
        for lp in self.loops:
            a, b = self.index(lp.old), self.index(lp.new)
            if lp.confirmed and a is not None and b is not None:
                graph.add(gtsam.BetweenFactorPose2(X(a), X(b), gtsam.Pose2(*lp.rel), loop_noise))
        if self.headings:
            # Heading only: the position sigmas are so wide that the factor holds nothing else.
            head_noise = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Huber.Create(c.loop_huber),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([1e3, 1e3, math.radians(c.manhattan_sigma_deg)])))
            for i, k in enumerate(self.keys):
                th = self.headings.get(k)
                if th is not None:
                    graph.add(gtsam.PriorFactorPose2(X(i), gtsam.Pose2(self.est[i][0], self.est[i][1], th), head_noise))
        out = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        self.est = [np.array([out.atPose2(X(i)).x(), out.atPose2(X(i)).y(), out.atPose2(X(i)).theta()])
                    for i in range(len(self.keys))]


def candidates(g: SourceGraph, new: int, cfg: PoseGraphConfig, have: set[Key]) -> list[int]:
    """Old keyframes of ``g`` (indices, best first) that may see what keyframe ``new`` sees: near its
    corrected pose, similar heading, at least ``loop_min_travel_m`` back along the path, with stored
    features (``have``); at most ``loop_candidates``, no two consecutive."""
    p = g.est[new]
    scored = []
    for i in range(new):
        if g.keys[i] not in have or g.path_m[new] - g.path_m[i] < cfg.loop_min_travel_m:
            continue
        d = float(np.hypot(*(g.est[i][:2] - p[:2])))
        a = abs(math.degrees(wrap_angle(float(g.est[i][2] - p[2]))))
        if d <= cfg.loop_max_distance_m and a <= cfg.loop_max_angle_deg:
            scored.append((d + a / 45.0, i))
    chosen: list[int] = []
    for _, i in sorted(scored):
        if all(abs(i - j) > 1 for j in chosen):
            chosen.append(i)
        if len(chosen) == cfg.loop_candidates:
            break
    return chosen


# -- keyframe memory and measurement ----------------------------------------------------------------
@dataclass(frozen=True)
class LoopKeyframe:
    """What a past keyframe keeps for loop closure: features with a depth (pixels, descriptors and points in
    its camera frame) and the pose (camera to world) they were measured at, with its intrinsics."""

    uv: NDArray[np.float32]  # (n, 2) full-image pixels
    desc: NDArray[np.uint8]  # (n, 128) RootSIFT descriptors scaled to 0..255
    points_cam: NDArray[np.float32]  # (n, 3)
    T_world_cam: F64
    K: F64

    @staticmethod
    def build(feats: features.Features, depth_m: NDArray[np.floating], confidence: NDArray[np.floating],
              K_depth: F64, K: F64, image_size: tuple[int, int], T_world_cam: F64,
              min_confidence: float) -> LoopKeyframe:
        """Lift ``feats`` (pixels of an image ``image_size`` = (w, h) with intrinsics ``K``) with a depth map
        at its own intrinsics ``K_depth``; features without confident depth, or on a depth edge, are left out."""
        h, w = depth_m.shape
        sx, sy = w / image_size[0], h / image_size[1]
        u = np.round((feats.uv[:, 0] + 0.5) * sx - 0.5).astype(np.int64)
        v = np.round((feats.uv[:, 1] + 0.5) * sy - 0.5).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
        d = depth_m[v, u].astype(np.float64)
        ok = inside & np.isfinite(d) & (d > 0) & (confidence[v, u] >= min_confidence)
        for du, dv in ((1, 0), (-1, 0), (0, 1), (0, -1)):  # a sample straddling an edge has no single depth
            dn = depth_m[np.clip(v + dv, 0, h - 1), np.clip(u + du, 0, w - 1)]
            ok &= np.abs(dn - d) <= 0.05 * np.maximum(d, 1e-6)
        X = np.stack([(u - K_depth[0, 2]) / K_depth[0, 0] * d, (v - K_depth[1, 2]) / K_depth[1, 1] * d, d], axis=1)
        desc = np.clip(np.round(feats.desc[ok] * 255.0), 0, 255).astype(np.uint8)
        return LoopKeyframe(feats.uv[ok].astype(np.float32), desc, X[ok].astype(np.float32),
                            np.asarray(T_world_cam, np.float64), np.asarray(K, np.float64))

    def features(self) -> features.Features:
        return features.Features(self.uv.astype(np.float64), self.desc.astype(np.float32) / 255.0)


@dataclass(frozen=True)
class Measurement:
    """A loop measurement: the new camera's pose in the old keyframe's world frame, or why there is none."""

    T_world_cam: F64 | None
    inliers: int
    reason: str


def measure(query: features.Features, K: F64, old: LoopKeyframe, cfg: PoseGraphConfig) -> Measurement:
    """PnP of the new keyframe's features ``query`` (intrinsics ``K``) against an old keyframe's lifted ones,
    on the matches the epipolar geometry keeps, and checked against it: the old keyframe's depth may be wrong
    (stereo failures), the images' own relative rotation and direction of travel are not."""
    m = features.match_features(query, old.features())
    if len(m) < cfg.loop_min_inliers:
        return Measurement(None, 0, "loops_refused_few_matches")
    uv_new, uv_old = query.uv[m[:, 0]], old.uv[m[:, 1]].astype(np.float64)
    # The images' own geometry; USAC with local optimisation: a plain RANSAC minimal-sample E is off by degrees
    # at a few pixels of tolerance.
    inl_e, R_e, t_e = features.essential_pose(uv_old, uv_new, old.K, K, cfg.loop_reproj_px,
                                              method=cv2.USAC_ACCURATE, min_inliers=8)
    if R_e is None or t_e is None or inl_e.sum() < cfg.loop_min_inliers:
        return Measurement(None, int(inl_e.sum()), "loops_refused_few_inliers")
    X_world = old.points_cam[m[inl_e, 1]].astype(np.float64) @ old.T_world_cam[:3, :3].T + old.T_world_cam[:3, 3]
    T, inl = pnp_pose(uv_new[inl_e], X_world, K, cfg.loop_reproj_px)
    if T is None or inl < cfg.loop_min_inliers or inl < cfg.loop_min_inlier_ratio * len(m):
        return Measurement(None, inl, "loops_refused_few_inliers")
    T_new_old = np.linalg.inv(T) @ old.T_world_cam  # old camera coordinates into the new camera's
    R_pnp, t_pnp = T_new_old[:3, :3], T_new_old[:3, 3]
    rot_deg = rotation_angle_deg(R_pnp, R_e)
    baseline = float(np.linalg.norm(t_pnp))
    dir_deg = math.degrees(math.acos(np.clip(t_pnp @ t_e / max(baseline, 1e-12), -1.0, 1.0)))
    if rot_deg > cfg.loop_max_rotation_disagreement_deg or (
            baseline >= cfg.loop_min_baseline_m and dir_deg > cfg.loop_max_direction_disagreement_deg):
        return Measurement(None, inl, "loops_refused_epipolar")
    return Measurement(T, inl, "ok")


class LoopCloser:
    """The pose graphs of all moving sources and their keyframes' loop features (bounded)."""

    def __init__(self, cfg: PoseGraphConfig) -> None:
        self.cfg = cfg
        self.graphs: dict[str, SourceGraph] = {}
        self.memory: collections.OrderedDict[Key, LoopKeyframe] = collections.OrderedDict()
        self.counters: dict[str, float] = {}
        self.history: collections.deque[Loop] = collections.deque(maxlen=256)  # the last loop measurements
        # Features of the keyframes being processed (a worker may finish a few of them late).
        self._query = features.LruCache(16)

    def _count(self, name: str, n: float = 1.0) -> None:
        self.counters[name] = self.counters.get(name, 0.0) + n

    def correction(self, source_id: str) -> F64:
        """The source's newest correction as a 4x4 world transform (identity for unknown sources)."""
        g = self.graphs.get(source_id)
        return lift(g.correction()) if g is not None else np.eye(4)

    def keyframe(self, key: Key, T_odom: F64, query: features.Features, K: F64,
                 image: NDArray[np.uint8] | None = None) -> dict[Key, F64]:
        """Add a keyframe of a moving source (its odometry prior ``T_odom``, its image's features ``query`` at
        intrinsics ``K``: :func:`mapper.geometry.features.extract_features`), measure loops to old keyframes
        and re-solve when one is confirmed. Returns, per keyframe whose correction changed by more than
        ``min_move_m`` (the new one excluded), the 4x4 world transform that moves its old corrected pose to
        the new one."""
        cfg = self.cfg
        g = self.graphs.setdefault(key[0], SourceGraph(cfg))
        if g.index(key) is not None:  # the same keyframe again (a forced re-ingest): nothing new to add
            return {}
        g.add(key, planar(T_odom))
        new = len(g.keys) - 1
        self._query.put(key, query)
        before = [se2(e) for e in g.est]
        T_pred = lift(g.correction()) @ T_odom
        # Unconfirmed measurements wait ``confirm_keyframes`` keyframes for a second opinion.
        g.loops = [lp for lp in g.loops if lp.confirmed or _at_least(g.index(lp.new), new - cfg.confirm_keyframes)]
        added = False
        for i in candidates(g, new, cfg, set(self.memory)):
            lp = self._measure(g, i, new, query, K, T_pred)
            if lp is not None:
                added |= self._confirm(g, lp)
        if cfg.manhattan and image is not None:
            added |= self._heading(g, key, image, K, T_odom)
        if not added:
            return {}
        g.solve()
        self._count("pose_graph_solves")
        moved = {}
        for k, e, b in zip(g.keys[:-1], g.est[:-1], before[:-1], strict=True):
            # A turn counts by what it does 1 m in front of the camera.
            if float(np.hypot(*(e[:2] - b[:2, 2]))) + abs(wrap_angle(float(e[2] - from_se2(b)[2]))) > cfg.min_move_m:
                moved[k] = lift(se2(e) @ np.linalg.inv(b))
        return moved

    def _heading(self, g: SourceGraph, key: Key, image: NDArray[np.uint8], K: F64, T_odom: F64) -> bool:
        """Measure the new keyframe's absolute heading from its lines (``manhattan``); True when kept."""
        cfg = self.cfg
        got = line_heading(image, K, T_odom)
        if got is None or got[1] < cfg.manhattan_min_concentration or got[2] < cfg.manhattan_min_lines:
            self._count("headings_unclear")
            return False
        # The true heading is the odometry's minus the offset, modulo 90 deg: take the one nearest the estimate.
        th = planar(T_odom)[2] - got[0]
        est = float(g.est[-1][2])
        th = est + wrap_angle(4.0 * (th - est)) / 4.0
        if abs(math.degrees(wrap_angle(th - est))) > cfg.manhattan_max_correction_deg:
            self._count("headings_refused_too_far")
            return False
        g.headings[key] = th
        self._count("headings_measured")
        return True

    def _measure(self, g: SourceGraph, old: int, new: int, query: features.Features, K: F64,
                 T_pred: F64) -> Loop | None:
        cfg = self.cfg
        self._count("loop_candidates")
        lk = self.memory[g.keys[old]]
        m = measure(query, K, lk, cfg)
        if m.T_world_cam is None:
            self._count(m.reason)
            return None
        # The old keyframe's features sit where the map has it now (moved with every solution), so the PnP pose
        # is the new keyframe's pose in the map's frame.
        T_new = m.T_world_cam
        if abs(T_new[2, 3] - T_pred[2, 3]) > cfg.loop_max_height_m or tilt_deg(T_new, T_pred) > cfg.loop_max_tilt_deg:
            self._count("loops_refused_off_floor")
            return None
        corr = se2(planar(T_new)) @ np.linalg.inv(se2(g.est[new]))
        shift = corr @ np.array([*g.est[new][:2], 1.0]) - np.array([*g.est[new][:2], 1.0])
        if (float(np.hypot(shift[0], shift[1])) > cfg.loop_max_correction_m
                or abs(math.degrees(math.atan2(corr[1, 0], corr[0, 0]))) > cfg.loop_max_correction_deg):
            self._count("loops_refused_too_far")
            return None
        # Relative to the old keyframe's refined camera: the image geometry between the two cameras.
        rel = from_se2(np.linalg.inv(se2(planar(lk.T_world_cam))) @ se2(planar(T_new)))
        self._count("loop_measurements")
        # Confirmation compares what measurements say about the odometry (drift is slow, and unlike the estimate
        # the odometry does not change when the graph is solved between two measurements).
        lp = Loop(g.keys[old], g.keys[new], rel, m.inliers, se2(planar(T_new)) @ np.linalg.inv(se2(g.odom[new])))
        self.history.append(lp)
        return lp

    def _confirm(self, g: SourceGraph, lp: Loop) -> bool:
        """Keep ``lp``; confirm it (and the pending ones it agrees with) when another measurement from a
        different old keyframe implies the same correction. True when something was confirmed."""
        cfg = self.cfg
        agreed = False
        for other in g.loops:
            if other.old == lp.old:
                continue
            # Compared by what they do to the newest keyframe's odometry centre (a heading change about the world
            # origin shifts far points more) and by their heading change.
            p = np.array([*g.odom[-1][:2], 1.0])
            d = lp.correction @ p - other.correction @ p
            dth = math.atan2(lp.correction[1, 0], lp.correction[0, 0]) - math.atan2(other.correction[1, 0],
                                                                                    other.correction[0, 0])
            if float(np.hypot(d[0], d[1])) <= cfg.confirm_m and abs(math.degrees(wrap_angle(dth))) <= cfg.confirm_deg:
                if not other.confirmed:
                    other.confirmed = True
                    self._count("loops_confirmed")
                agreed = True
        if agreed:
            lp.confirmed = True
            self._count("loops_confirmed")
        g.loops.append(lp)
        return agreed

    def remember(self, key: Key, depth_m: NDArray[np.floating], confidence: NDArray[np.floating], K_depth: F64,
                 K: F64, image_size: tuple[int, int], T_world_cam: F64) -> None:
        """Keep a processed keyframe's features (extracted by :meth:`keyframe`) with its reconstructed depth and
        refined pose, as a future loop candidate. Bounded by ``max_keyframes`` per source overall."""
        query = self._query.get(key)
        if not isinstance(query, features.Features):
            return
        self.memory[key] = LoopKeyframe.build(query, depth_m, confidence, K_depth, K, image_size, T_world_cam,
                                              self.cfg.min_confidence)
        while len(self.memory) > self.cfg.max_keyframes * max(1, len(self.graphs)):
            self.memory.popitem(last=False)

    def move_memory(self, key: Key, delta: F64) -> None:
        """A stored keyframe's pose moved by ``delta`` (4x4, world frame): its loop features follow."""
        lk = self.memory.get(key)
        if lk is not None:
            self.memory[key] = LoopKeyframe(lk.uv, lk.desc, lk.points_cam, delta @ lk.T_world_cam, lk.K)


def _at_least(i: int | None, lowest: int) -> bool:
    return i is not None and i >= lowest


def node_move(centre: F64, deltas: list[F64]) -> F64:
    """One rigid 4x4 world transform for a node fused from keyframes whose poses moved by ``deltas``: its
    centre goes to the mean of where the deltas take it, turned by their mean heading change about it."""
    c = np.asarray(centre, np.float64)
    target = np.mean([D[:3, :3] @ c + D[:3, 3] for D in deltas], axis=0)
    ang = float(np.mean([math.atan2(D[1, 0], D[0, 0]) for D in deltas]))
    R = lift(se2(np.array([0.0, 0.0, ang])))
    T = R.copy()
    T[:3, 3] = target - R[:3, :3] @ c
    return T
