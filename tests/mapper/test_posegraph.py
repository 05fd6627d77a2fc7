"""Loop closure (mapper.posegraph): planar pose algebra, the pose graph, PnP loop measurements, and a
synthetic robot that drives a loop with drifting odometry in a box room and comes back within centimetres."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapper.geometry.features import Features
from mapper.posegraph import (
    LoopCloser,
    LoopKeyframe,
    PoseGraphConfig,
    SourceGraph,
    from_se2,
    lift,
    measure,
    node_move,
    odometry_sigmas,
    planar,
    se2,
    tilt_deg,
)
from protocol.poses import wrap_angle

W, H = 320, 240
K = np.array([[200.0, 0.0, (W - 1) / 2], [0.0, 200.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
ROOM = (np.array([-4.0, -4.0, 0.0]), np.array([4.0, 4.0, 3.0]))  # the box the robot drives in
CAM_Z = 1.0


def camera(x: float, y: float, yaw: float, pitch_deg: float = -10.0) -> np.ndarray:
    """T_world_cam of a robot camera (OpenCV axes) at (x, y, CAM_Z) looking along ``yaw``, tilted down."""
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    p = math.radians(pitch_deg)
    fwd, down = math.cos(p) * fwd + math.sin(p) * down * -1.0, math.cos(p) * down - math.sin(p) * fwd * -1.0
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)
    T[:3, 3] = [x, y, CAM_Z]
    return T


def depth_map(T: np.ndarray) -> np.ndarray:
    """z-depth of every pixel of a camera inside the box room (ray cast against its six faces)."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    rays = rays_cam @ T[:3, :3].T
    o = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (ROOM[1] - o) / rays
        t_lo = (ROOM[0] - o) / rays
    t = np.where(rays > 0, t_hi, t_lo)
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf).min(axis=-1)
    return t.astype(np.float32)  # the ray's z component in the camera is 1: t is the z-depth


def landmarks(n: int = 5000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on the room's walls and floor (a scene that is no single plane) with distinct non-negative unit
    descriptors (RootSIFT-like)."""
    rng = np.random.default_rng(seed)
    face = rng.integers(0, 5, n)
    s, r = rng.uniform(-4.0, 4.0, n), rng.uniform(-4.0, 4.0, n)
    z = np.where(face == 4, 0.0, rng.uniform(0.0, 3.0, n))
    x = np.where(face == 0, -4.0, np.where(face == 1, 4.0, s))
    y = np.where(face == 2, -4.0, np.where(face == 3, 4.0, np.where(face == 4, r, s)))
    X = np.stack([x, y, z], axis=1)
    d = np.abs(rng.normal(size=(n, 128))) ** 4
    return X, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def observe(T: np.ndarray, X: np.ndarray, desc: np.ndarray, noise_px: float = 0.3, seed: int = 0) -> Features:
    """The landmarks a camera sees, as features at their (noisy) pixels."""
    Tcw = np.linalg.inv(T)
    p = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / p[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    ok = (p[:, 2] > 0.1) & (uv[:, 0] >= 2) & (uv[:, 0] < W - 3) & (uv[:, 1] >= 2) & (uv[:, 1] < H - 3)
    rng = np.random.default_rng(seed)
    return Features(uv[ok] + rng.normal(0.0, noise_px, (int(ok.sum()), 2)), desc[ok])


# -- planar algebra --------------------------------------------------------------------------------
def test_planar_lift_round_trip() -> None:
    T = camera(1.0, -2.0, 0.7)
    p = planar(T)
    assert p == pytest.approx([1.0, -2.0, 0.7])
    D = se2(np.array([0.3, -0.2, 0.1]))
    assert planar(lift(D) @ T) == pytest.approx(from_se2(D @ se2(p)))
    assert from_se2(se2(np.array([0.5, 0.25, -3.0]))) == pytest.approx([0.5, 0.25, -3.0])
    assert tilt_deg(lift(D) @ T, T) == pytest.approx(0.0, abs=1e-6)  # a planar correction keeps the tilt
    assert tilt_deg(camera(0, 0, 0.3, -15.0), camera(0, 0, 1.0, -10.0)) == pytest.approx(5.0, abs=1e-6)


def test_odometry_sigmas_grow_with_distance_and_turn() -> None:
    cfg = PoseGraphConfig()
    a = odometry_sigmas(np.array([0.3, 0.0, 0.0]), cfg)
    b = odometry_sigmas(np.array([1.2, 0.0, 0.0]), cfg)
    c = odometry_sigmas(np.array([0.3, 0.0, 1.0]), cfg)
    assert b[0] == pytest.approx(2 * a[0]) and b[2] == pytest.approx(2 * a[2])
    assert c[2] > a[2]
    still = odometry_sigmas(np.zeros(3), cfg)
    floor = [cfg.odom_floor_trans_m, cfg.odom_floor_trans_m, math.radians(cfg.odom_floor_rot_deg)]
    assert still == pytest.approx(floor)


def test_node_move() -> None:
    D = lift(se2(np.array([0.4, 0.0, 0.0])))
    c = np.array([1.0, 1.0, 0.5])
    T = node_move(c, [D, np.eye(4)])  # half the keyframes moved 0.4 m: the node moves 0.2 m
    assert T[:3, :3] @ c + T[:3, 3] == pytest.approx([1.2, 1.0, 0.5])
    R = lift(se2(np.array([0.0, 0.0, 0.2])))
    T = node_move(c, [R])  # a turn about the origin moves the centre along the arc
    assert T[:3, :3] @ c + T[:3, 3] == pytest.approx(R[:3, :3] @ c)


# -- the graph ---------------------------------------------------------------------------------------
def drive(n: int = 40, radius: float = 2.0) -> list[np.ndarray]:
    """Planar true poses around a circle, facing along the path, ending where it started."""
    return [np.array([radius * math.cos(a), radius * math.sin(a), a + math.pi / 2])
            for a in np.linspace(0.0, 2 * math.pi, n)]


def drifted(truth: list[np.ndarray], deg_per_step: float = 0.25) -> list[np.ndarray]:
    """Odometry that turns ``deg_per_step`` too much at each step (heading drift) from the first pose."""
    odom = [truth[0]]
    for a, b in zip(truth[:-1], truth[1:], strict=True):
        step = np.linalg.inv(se2(a)) @ se2(b)
        step = step @ se2(np.array([0.0, 0.0, math.radians(deg_per_step)]))
        odom.append(from_se2(se2(odom[-1]) @ step))
    return odom


def test_a_closed_loop_brings_the_path_back() -> None:
    truth = drive()
    odom = drifted(truth, 0.5)
    g = SourceGraph(PoseGraphConfig())
    for i, p in enumerate(odom):
        g.add(("r", i), p)
    end_err0 = float(np.hypot(*(g.est[-1][:2] - truth[-1][:2])))
    assert end_err0 > 0.5  # 20 deg of heading drift over 12.6 m
    from mapper.posegraph import Loop
    for old, new in ((0, 39), (1, 38), (1, 39)):
        rel = from_se2(np.linalg.inv(se2(truth[old])) @ se2(truth[new]))
        g.loops.append(Loop(("r", old), ("r", new), rel, 100, np.eye(3), confirmed=True))
    g.solve()
    errs = [float(np.hypot(*(e[:2] - t[:2]))) for e, t in zip(g.est, truth, strict=True)]
    assert errs[-1] < 0.03
    assert max(errs) < 0.35 * end_err0  # the middle of the loop, where no loop measures, is halved or better
    assert g.est[0] == pytest.approx(odom[0], abs=1e-6)  # the first keyframe holds the frame


def test_an_unconfirmed_loop_changes_nothing() -> None:
    truth = drive()
    odom = drifted(truth)
    g = SourceGraph(PoseGraphConfig())
    for i, p in enumerate(odom):
        g.add(("r", i), p)
    from mapper.posegraph import Loop
    g.loops.append(Loop(("r", 0), ("r", 39), np.zeros(3), 100, np.eye(3)))
    before = [e.copy() for e in g.est]
    g.solve()
    assert all(np.allclose(a, b, atol=1e-6) for a, b in zip(before, g.est, strict=True))


def test_graph_is_bounded() -> None:
    g = SourceGraph(PoseGraphConfig(max_keyframes=10))
    for i in range(25):
        g.add(("r", i), np.array([0.1 * i, 0.0, 0.0]))
    assert len(g.keys) == 10 and g.keys[0] == ("r", 15)
    g.solve()  # still solvable once the first keyframes are gone


# -- measurements ------------------------------------------------------------------------------------
def test_measure_recovers_the_pose_and_refuses_a_wrong_place() -> None:
    X, desc = landmarks()
    cfg = PoseGraphConfig()
    T_old = camera(0.0, 0.0, 0.3)
    old = LoopKeyframe.build(observe(T_old, X, desc), depth_map(T_old), np.ones((H, W), np.float32), K, K, (W, H),
                             T_old, 0.5)
    assert len(old.desc) > 100
    T_new = camera(0.4, -0.3, 0.5)
    m = measure(observe(T_new, X, desc, seed=1), K, old, cfg)
    assert m.reason == "ok" and m.inliers >= cfg.loop_min_inliers
    assert m.T_world_cam is not None
    assert np.linalg.norm(m.T_world_cam[:3, 3] - T_new[:3, 3]) < 0.02
    # A different place: the same descriptors on other points (repetitive texture) cannot be explained.
    rng = np.random.default_rng(3)
    scrambled = LoopKeyframe(old.uv, old.desc, rng.permutation(old.points_cam), old.T_world_cam, K)
    bad = measure(observe(T_new, X, desc, seed=1), K, scrambled, cfg)
    assert bad.T_world_cam is None and bad.reason == "loops_refused_few_inliers"
    other = measure(observe(camera(0.0, 0.0, 0.3 + math.pi), X, desc), K, old, cfg)  # looking the other way
    assert other.T_world_cam is None and other.reason in ("loops_refused_few_matches", "loops_refused_few_inliers")


def run_robot(cfg: PoseGraphConfig, truth: list[np.ndarray], odom: list[np.ndarray],
              scramble: set[int] = frozenset()) -> tuple[LoopCloser, list[np.ndarray]]:  # type: ignore[assignment]
    """Drive ``truth`` with odometry ``odom`` through a LoopCloser as the mapper does: correct the prior,
    remember each keyframe with its (true-camera) depth at the corrected pose, move stored keyframes when
    a loop closes. ``scramble``: keyframes whose remembered depth is garbage (a stereo failure)."""
    X, desc = landmarks()
    lc = LoopCloser(cfg)
    rng = np.random.default_rng(5)
    z_cam = camera(0, 0, 0)  # height and tilt of every camera
    for i, (t, o) in enumerate(zip(truth, odom, strict=True)):
        T_true, T_odom = lift(se2(t)) @ z_cam, lift(se2(o)) @ z_cam
        key = ("robot", i)
        for k, d in lc.keyframe(key, T_odom, observe(T_true, X, desc, seed=i), K).items():
            lc.move_memory(k, d)
        T_est = lc.correction("robot") @ T_odom
        depth = depth_map(T_true)
        if i in scramble:
            # Stereo gone wrong: blocks of random depth where the room has walls.
            depth = np.kron(rng.uniform(1.0, 5.0, (H // 40, W // 40)), np.ones((40, 40))).astype(np.float32)
        lc.remember(key, depth, np.ones((H, W), np.float32), K, K, (W, H), T_est)
    return lc, [lift(se2(e)) @ z_cam for e in lc.graphs["robot"].est]


def test_robot_loop_is_closed_within_centimetres() -> None:
    truth = drive(n=48, radius=2.5)
    odom = drifted(truth, 0.25)  # ~12 deg of heading drift around the loop
    lc, est = run_robot(PoseGraphConfig(), truth, odom)
    err_odom = float(np.hypot(*(odom[-1][:2] - truth[-1][:2])))
    err = float(np.linalg.norm(est[-1][:2, 3] - truth[-1][:2]))
    assert err_odom > 0.4
    assert err < 0.05, lc.counters
    assert lc.counters.get("loops_confirmed", 0) >= 2
    assert abs(math.degrees(wrap_angle(planar(est[-1])[2] - truth[-1][2]))) < 0.5


def test_robot_loops_against_broken_depth_are_refused_or_harmless() -> None:
    truth = drive(n=48, radius=2.5)
    odom = drifted(truth, 0.25)
    lc, est = run_robot(PoseGraphConfig(), truth, odom, scramble=set(range(48)))
    # Random depth blocks: the PnP pose contradicts the images' own epipolar geometry and is refused...
    assert lc.counters.get("loops_refused_epipolar", 0) >= lc.counters["loop_candidates"] / 2
    # ... except where the cameras nearly coincide and depth hardly matters: the path still closes.
    assert float(np.linalg.norm(est[-1][:2, 3] - truth[-1][:2])) < 0.1


def test_no_loop_without_confirmation() -> None:
    truth = drive(n=48, radius=2.5)
    odom = drifted(truth, 0.25)
    lc, est = run_robot(PoseGraphConfig(loop_candidates=1, confirm_keyframes=0), truth, odom)
    assert lc.counters.get("loop_measurements", 0) > 0 and lc.counters.get("loops_confirmed", 0) == 0
    assert np.allclose(planar(est[-1]), odom[-1], atol=1e-6)  # nothing moved: the odometry stands


# -- Manhattan headings -----------------------------------------------------------------------------
def grid_image(T: np.ndarray) -> np.ndarray:
    """A camera's view of floor tiles along the world axes (0.5 m) as white lines on grey."""
    img = np.full((H, W, 3), 60, np.uint8)
    Tcw = np.linalg.inv(T)
    ends = []
    for c in np.arange(-4.0, 4.01, 0.5):
        ends += [((c, -4.0, 0.0), (c, 4.0, 0.0)), ((-4.0, c, 0.0), (4.0, c, 0.0))]
    for a, b in ends:
        P = np.linspace(a, b, 200) @ Tcw[:3, :3].T + Tcw[:3, 3]
        P = P[P[:, 2] > 0.2]
        if len(P) < 2:
            continue
        uv = P[:, :2] / P[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
        import cv2

        cv2.polylines(img, [np.round(uv).astype(np.int32)], False, (230, 230, 230), 2)
    return img


def test_line_heading_measures_the_heading_error() -> None:
    from mapper.posegraph import line_heading

    T_true = camera(0.3, -0.5, 0.4, pitch_deg=-30.0)
    img = grid_image(T_true)
    for err_deg in (0.0, 3.0, -7.0):
        T_odom = lift(se2(np.array([0.0, 0.0, math.radians(err_deg)]))) @ T_true
        got = line_heading(img, K, T_odom)
        assert got is not None
        offset, concentration, n = got
        assert math.degrees(offset) == pytest.approx(err_deg, abs=0.5)
        assert concentration > 0.9 and n >= 6
    assert line_heading(np.full((H, W, 3), 60, np.uint8), K, T_true) is None  # no lines, no heading


def test_manhattan_headings_hold_the_heading_between_loops() -> None:
    truth = drive(n=40, radius=2.0)
    odom = drifted(truth, 0.3)
    lc = LoopCloser(PoseGraphConfig(manhattan=True))
    empty = Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    tilt = camera(0, 0, 0, pitch_deg=-30.0)
    errs = []
    for i, (t, o) in enumerate(zip(truth, odom, strict=True)):
        T_true, T_odom = lift(se2(t)) @ tilt, lift(se2(o)) @ tilt
        lc.keyframe(("robot", i), T_odom, empty, K, grid_image(T_true))
        est = lc.correction("robot") @ T_odom
        errs.append(abs(math.degrees(wrap_angle(planar(est)[2] - t[2]))))
    assert abs(math.degrees(wrap_angle(odom[-1][2] - truth[-1][2]))) > 10.0
    # 0.3 deg of drift at every step, always the same way: the estimate lags the lines a little, never more.
    assert max(errs) < 2.0
    assert lc.counters["headings_measured"] >= 30
