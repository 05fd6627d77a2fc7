"""Refinement that does no harm: priors that declare no accuracy are replaced only when held-out tracks say the
refined poses are better; accurate priors come out unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry import bundle
from mapper.geometry.contract import View
from mapper.geometry.registry import make_reconstructor
from protocol.messages import Intrinsics
from protocol.poses import camera_pose_from_base, make_pose, rotation_angle_deg

INTR = Intrinsics.from_fov(640, 480, 90.0)


@pytest.fixture(scope="module")
def sim_room() -> tuple:
    pytest.importorskip("sim.scene")
    from sim.render import Renderer
    from sim.scene import generate_scene

    scene = generate_scene("furnished_room", 1)
    return scene, Renderer(scene)


def _views(sim_room: tuple, poses: list[np.ndarray], priors: list[np.ndarray] | None = None) -> list[View]:
    _, renderer = sim_room
    priors = priors or poses
    return [View(renderer.render(INTR, T).rgb, "cam", INTR, P, seq=i)
            for i, (T, P) in enumerate(zip(poses, priors, strict=True))]


def _room_pose(sim_room: tuple, dx: float, dyaw_deg: float = 0.0) -> np.ndarray:
    scene, _ = sim_room
    cx, cy = (scene.bounds_min[:2] + scene.bounds_max[:2]) / 2
    return camera_pose_from_base(cx + dx, cy - 1.0, 1.57 + np.radians(dyaw_deg), 1.0, -15.0)


def _refined(views: list[View]) -> tuple[list[np.ndarray], dict]:
    rec = make_reconstructor("mvs")
    r = rec.reconstruct(views, targets=[0])
    return [np.asarray(T) for T in r.info["T_world_cam"]], r.info


def _scale(refined: list[np.ndarray], priors: list[np.ndarray]) -> float:
    d_ref = [np.linalg.norm(refined[i][:3, 3] - refined[0][:3, 3]) for i in range(1, len(refined))]
    d_pri = [np.linalg.norm(priors[i][:3, 3] - priors[0][:3, 3]) for i in range(1, len(priors))]
    return float(np.sum(d_ref) / np.sum(d_pri))


def test_accurate_priors_with_a_1cm_baseline_come_out_unchanged(sim_room: tuple) -> None:
    poses = [_room_pose(sim_room, 0.01 * k) for k in range(3)]
    refined, info = _refined(_views(sim_room, poses))
    for T, P in zip(refined, poses, strict=True):
        assert rotation_angle_deg(T, P) < 0.1
    assert abs(_scale(refined, poses) - 1.0) < 0.01


def test_accurate_priors_under_a_pure_rotation_come_out_unchanged(sim_room: tuple) -> None:
    poses = [_room_pose(sim_room, 0.0, dyaw) for dyaw in (0.0, 3.0, 6.0)]
    refined, info = _refined(_views(sim_room, poses))
    for T, P in zip(refined, poses, strict=True):
        assert rotation_angle_deg(T, P) < 0.1
        assert np.linalg.norm(T[:3, 3] - P[:3, 3]) < 1e-3


def test_held_out_tracks_let_a_wrong_undeclared_prior_be_corrected(sim_room: tuple) -> None:
    """A 1.5 deg error in one undeclared prior: the refined poses explain the held-out tracks clearly better,
    so they replace the priors."""
    poses = [_room_pose(sim_room, 0.15 * k) for k in range(3)]
    err = make_pose(np.array([[np.cos(0.026), 0, np.sin(0.026)], [0, 1, 0], [-np.sin(0.026), 0, np.cos(0.026)]]),
                    [0, 0, 0])
    priors = [poses[0], poses[1] @ err, poses[2]]
    refined, info = _refined(_views(sim_room, poses, priors))
    ba = info["ba"][0]
    assert ba["status"] == "ok", ba
    assert ba["holdout_px_refined"] < ba["holdout_px_prior"]
    # Most of the error is gone (the absolute priors, 2 deg each, still pull a little).
    assert rotation_angle_deg(refined[1], poses[1]) < 0.5 * rotation_angle_deg(priors[1], poses[1])


def test_holdout_error_is_zero_for_exact_poses_and_grows_with_a_rotation_error() -> None:
    K = INTR.K()
    rng = np.random.default_rng(0)
    X = rng.uniform([-1, -1, 2], [1, 1, 4], (40, 3))
    Ts = [make_pose(np.eye(3), [0.2 * i, 0, 0]) for i in range(3)]
    oc, op, uv = [], [], []
    for c, T in enumerate(Ts):
        p, _ = bundle.reproject(K, T, X)
        oc += [c] * len(X)
        op += list(range(len(X)))
        uv.append(p)
    oc_a, op_a, uv_a = np.array(oc), np.array(op), np.concatenate(uv)
    med, n = bundle.holdout_error_px([K] * 3, Ts, oc_a, op_a, uv_a)
    assert n == 120 and med == pytest.approx(0.0, abs=1e-6)
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    wrong = [Ts[0], Ts[1] @ make_pose(np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), [0, 0, 0]), Ts[2]]
    med_wrong, _ = bundle.holdout_error_px([K] * 3, wrong, oc_a, op_a, uv_a)
    assert med_wrong > 1.0
    empty = bundle.holdout_error_px([K] * 3, Ts, oc_a[:0], op_a[:0], uv_a[:0])
    assert np.isnan(empty[0]) and empty[1] == 0


def _scaled_solution(factor: float, holdout_px: float) -> tuple[bundle.BundleProblem, bundle.BundleResult]:
    """Two cameras 0.2 m apart and points 2-4 m away; the 'refined' points lie ``factor`` times farther."""
    K = INTR.K()
    rng = np.random.default_rng(2)
    X = rng.uniform([-1, -1, 2], [1, 1, 4], (30, 3))
    Ts = [make_pose(np.eye(3), [0.0, 0, 0]), make_pose(np.eye(3), [0.2, 0, 0])]
    oc = np.repeat([0, 1], len(X))
    op = np.tile(np.arange(len(X)), 2)
    uv = np.concatenate([bundle.reproject(K, T, X)[0] for T in Ts])
    prob = bundle.BundleProblem(Ks=[K, K], T_world_cam=Ts, points_world=X, obs_cam=oc, obs_pt=op, obs_uv=uv)
    c = np.array([0.1, 0, 0])
    res = bundle.BundleResult(T_world_cam=[T.copy() for T in Ts], points_world=c + factor * (X - c),
                              inlier_obs=np.ones(len(oc), bool), rms_px_before=0.0, rms_px_after=0.0,
                              n_iterations=1, median_parallax_deg=4.0, holdout_px_prior=holdout_px)
    return prob, res


def test_the_depth_scale_moves_only_as_far_as_the_priors_error_explains() -> None:
    from mapper.geometry.mvs import MvsReconstructor

    prob, res = _scaled_solution(1.2, holdout_px=0.0)  # exact priors: nothing explains a 20 % change
    kept = MvsReconstructor._hold_depth_scale(prob, res, [True, True], 0.10)
    assert kept == pytest.approx(1.0)
    z = [bundle.reproject(INTR.K(), T, res.points_world)[1] for T in res.T_world_cam]
    z0 = [bundle.reproject(INTR.K(), T, prob.points_world)[1] for T in prob.T_world_cam]
    assert np.median(np.concatenate(z) / np.concatenate(z0)) == pytest.approx(1.0, abs=0.02)
    # Priors off by a lot (held-out error 50 px): the change is explained, but capped at 10 %.
    prob, res = _scaled_solution(1.2, holdout_px=50.0)
    assert MvsReconstructor._hold_depth_scale(prob, res, [True, True], 0.10) == pytest.approx(1.1, abs=0.01)
    # A small change the priors' error explains stays.
    prob, res = _scaled_solution(1.02, holdout_px=50.0)
    before = [T.copy() for T in res.T_world_cam]
    assert MvsReconstructor._hold_depth_scale(prob, res, [True, True], 0.10) == pytest.approx(1.02, abs=0.005)
    assert all(np.allclose(a, b) for a, b in zip(before, res.T_world_cam, strict=True))
