"""Bundle adjustment on a GTSAM factor graph: refinement, scale kept from the priors, degeneracy statuses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapper.geometry import bundle
from protocol.poses import look_at

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _pose(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c
    return T


def _rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude()))


def _rig(n_cam: int, step_m: float, yaw_deg: float = 1.0) -> list[np.ndarray]:
    """Cameras along x, looking down +z, turning slightly: a robot or hand-held camera at video rate."""
    return [
        _pose(Rotation.from_euler("yx", [yaw_deg * (i - n_cam // 2), 0.5 * i], degrees=True).as_matrix(),
              np.array([step_m * (i - n_cam // 2), 0.002 * i, 0.0]))
        for i in range(n_cam)
    ]


def _points(n: int, z_range: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    z = rng.uniform(*z_range, n)
    return np.stack([rng.uniform(-0.4, 0.4, n) * z, rng.uniform(-0.3, 0.3, n) * z, z], axis=1)


def _observe(truth: list[np.ndarray], X: np.ndarray, noise_px: float, rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    oc, op, ouv = [], [], []
    for c, T in enumerate(truth):
        uv, z = bundle.reproject(K, T, X)
        assert (z > 0).all()
        oc.append(np.full(len(X), c))
        op.append(np.arange(len(X)))
        ouv.append(uv + rng.normal(0.0, noise_px, uv.shape) if noise_px else uv)
    return np.concatenate(oc), np.concatenate(op), np.concatenate(ouv)


def _perturb(truth: list[np.ndarray], trans_m: float, rot_deg: float, rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for T in truth:
        axis = rng.normal(size=3)
        d = rng.normal(size=3)
        R = Rotation.from_rotvec(np.radians(rot_deg) * axis / np.linalg.norm(axis)).as_matrix() @ T[:3, :3]
        out.append(_pose(R, T[:3, 3] + trans_m * d / np.linalg.norm(d)))
    return out


def _triangulate_all(priors: list[np.ndarray], oc: np.ndarray, op: np.ndarray, ouv: np.ndarray) -> np.ndarray:
    Ps = [bundle.projection_matrix(K, T) for T in priors]
    return np.array([bundle.triangulate([Ps[c] for c in oc[op == j]], ouv[op == j]) for j in range(op.max() + 1)])


def _problem(priors: list[np.ndarray], oc: np.ndarray, op: np.ndarray, ouv: np.ndarray, **kw: list[bool]
             ) -> bundle.BundleProblem:
    return bundle.BundleProblem([K] * len(priors), priors, _triangulate_all(priors, oc, op, ouv), oc, op, ouv, **kw)


def _errors(poses: list[np.ndarray], truth: list[np.ndarray]) -> tuple[float, float]:
    """Mean rotation error (deg) and mean camera-centre error (m)."""
    rot = np.mean([_rot_err_deg(P, T) for P, T in zip(poses, truth, strict=True)])
    ctr = np.mean([np.linalg.norm(P[:3, 3] - T[:3, 3]) for P, T in zip(poses, truth, strict=True)])
    return float(rot), float(ctr)


def _spread(poses: list[np.ndarray]) -> float:
    C = np.stack([T[:3, 3] for T in poses])
    return float(np.sqrt(np.mean(np.sum((C - C.mean(0)) ** 2, axis=1))))


def _median_depth(T_world_cam: np.ndarray, X: np.ndarray) -> float:
    return float(np.median((X - T_world_cam[:3, 3]) @ T_world_cam[:3, 2]))


def _assert_priors_returned(res: bundle.BundleResult, prob: bundle.BundleProblem) -> None:
    for out, prior in zip(res.T_world_cam, prob.T_world_cam, strict=True):
        np.testing.assert_array_equal(out, prior)
    np.testing.assert_array_equal(res.points_world, prob.points_world)


@pytest.fixture(scope="module")
def wide_scene() -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """5 cameras 10 cm apart, 300 points 1-3 m away, exact pixels; priors off by 1 cm and 0.5 deg."""
    rng = np.random.default_rng(7)
    truth = _rig(5, 0.10)
    X = _points(300, (1.0, 3.0), rng)
    oc, op, ouv = _observe(truth, X, 0.0, rng)
    priors = _perturb(truth, 0.01, 0.5, rng)
    return truth, priors, oc, op, ouv


class TestBundleAdjust:
    def test_refines_perturbed_priors(self, wide_scene: tuple) -> None:
        truth, priors, oc, op, ouv = wide_scene
        res = bundle.bundle_adjust(_problem(priors, oc, op, ouv), sigma_rot_deg=0.5, sigma_trans_m=0.01)
        assert res.status == "ok"
        rot0, ctr0 = _errors(priors, truth)
        rot1, ctr1 = _errors(res.T_world_cam, truth)
        assert rot1 < 0.6 * rot0, (rot1, rot0)
        assert ctr1 < 0.8 * ctr0, (ctr1, ctr0)
        assert res.rms_px_after < 0.05 < 1.0 < res.rms_px_before
        assert res.inlier_obs.all() and res.n_inliers == len(oc)
        assert res.n_iterations > 0 and res.median_parallax_deg > 1.0

    def test_one_cm_baseline_keeps_the_priors_scale(self) -> None:
        # Video rate: steps far below the absolute prior sigma. The priors are the truth scaled by 1.3,
        # which the pixels cannot tell apart from the truth: the answer must keep the priors' scale.
        rng = np.random.default_rng(3)
        truth = _rig(5, 0.01, yaw_deg=0.5)
        X = _points(400, (1.0, 2.0), rng)
        oc, op, ouv = _observe(truth, X, 0.5, rng)
        priors = [_pose(T[:3, :3], 1.3 * T[:3, 3]) for T in truth]
        prob = _problem(priors, oc, op, ouv)
        # At 1 cm baselines a 0.04 deg yaw trades against a uniform shift of inverse depth (~8 % depth), so
        # point depth needs gyro-grade relative rotation; the camera-centre scale does not (checked below).
        res = bundle.bundle_adjust(prob, sigma_rot_deg=2.0, sigma_trans_m=0.05, sigma_rel_rot_deg=0.02)
        assert res.status == "ok"
        assert abs(_spread(res.T_world_cam) / _spread(priors) - 1.0) < 0.01
        z_prior = _median_depth(priors[0], prob.points_world)
        z_ref = _median_depth(res.T_world_cam[0], res.points_world)
        assert abs(z_ref / z_prior - 1.0) < 0.01, z_ref / z_prior
        # The scale fix makes the least-squares scale of the priors against the centres exactly 1, whatever
        # the relative-rotation sigma.
        for kw in ({"sigma_rel_rot_deg": 0.02}, {}):
            res = bundle.bundle_adjust(prob, sigma_rot_deg=2.0, sigma_trans_m=0.05, **kw)
            C = np.stack([T[:3, 3] for T in res.T_world_cam])
            P = np.stack([T[:3, 3] for T in priors])
            dC, dP = C - C.mean(0), P - P.mean(0)
            assert np.sum(dC * dP) / np.sum(dC**2) == pytest.approx(1.0, abs=1e-12)
            np.testing.assert_allclose(C.mean(0), P.mean(0), atol=1e-12)
            assert abs(_spread(res.T_world_cam) / _spread(priors) - 1.0) < 0.01

    def test_pure_rotation_is_low_parallax_and_keeps_priors(self) -> None:
        rng = np.random.default_rng(4)
        truth = [_pose(Rotation.from_euler("y", a, degrees=True).as_matrix(), np.array([0.2, 0.0, 0.1]))
                 for a in (-6, -3, 0, 3, 6)]
        X = _points(200, (1.0, 3.0), rng) + np.array([0.2, 0.0, 0.1])
        oc, op, ouv = _observe(truth, X, 0.3, rng)
        priors = [_pose(P[:3, :3], T[:3, 3]) for P, T in zip(_perturb(truth, 0.0, 0.3, rng), truth, strict=True)]
        prob = bundle.BundleProblem([K] * 5, priors, X, oc, op, ouv)
        res = bundle.bundle_adjust(prob)
        assert res.status == "low_parallax"
        assert res.median_parallax_deg < 1e-3
        assert res.n_iterations == 0
        _assert_priors_returned(res, prob)

    def test_fixed_camera_does_not_move(self, wide_scene: tuple) -> None:
        truth, priors, oc, op, ouv = wide_scene
        priors = list(priors)
        priors[2] = truth[2]
        prob = _problem(priors, oc, op, ouv, fixed=[False, False, True, False, False])
        res = bundle.bundle_adjust(prob, sigma_rot_deg=0.5, sigma_trans_m=0.01)
        assert res.status == "ok"
        np.testing.assert_array_equal(res.T_world_cam[2], truth[2])
        # The others moved (towards the truth, which the fixed camera anchors).
        assert _errors(res.T_world_cam, truth)[0] < 0.5 * _errors(priors, truth)[0]

    def test_gross_outliers_do_not_break_refinement(self, wide_scene: tuple) -> None:
        truth, priors, oc, op, ouv = wide_scene
        rng = np.random.default_rng(11)
        # 10 % of the observations, at most one per point (a point with a majority of outliers is lost).
        n_pt = op.max() + 1
        bad = rng.permutation(n_pt)[: len(oc) // 10] + n_pt * rng.integers(0, 5, len(oc) // 10)
        assert len(np.unique(op[bad])) == len(bad)
        ouv = ouv.copy()
        direction = rng.normal(size=(len(bad), 2))
        ouv[bad] += 50.0 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
        # Triangulate from the clean pixels so that only the adjustment sees the outliers.
        prob = _problem(priors, oc, op, wide_scene[4])
        prob.obs_uv = ouv
        res = bundle.bundle_adjust(prob, sigma_rot_deg=0.5, sigma_trans_m=0.01)
        assert res.status == "ok"
        rot0, ctr0 = _errors(priors, truth)
        rot1, ctr1 = _errors(res.T_world_cam, truth)
        assert rot1 < 0.6 * rot0 and ctr1 < 0.8 * ctr0, (rot1, rot0, ctr1, ctr0)
        assert not res.inlier_obs[bad].any()
        assert np.delete(res.inlier_obs, bad).all()

    def test_consistent_wrong_matches_are_rejected_not_averaged(self, wide_scene: tuple) -> None:
        # Wrong matches on repetitive texture are not random: a third of the points are seen by the last
        # camera 6 px off the same way (the next repetition of the pattern). A single Huber pass lets them pull
        # that camera's rotation by a fraction of a degree; the robust pass finds them and the re-solve drops them.
        truth, priors, oc, op, ouv = wide_scene
        n_pt = op.max() + 1
        bad = np.flatnonzero((oc == 4) & (op % 3 == 0))
        ouv = ouv.copy()
        ouv[bad, 0] += 6.0
        prob = _problem(priors, oc, op, wide_scene[4])
        prob.obs_uv = ouv
        res = bundle.bundle_adjust(prob, sigma_rot_deg=0.5, sigma_trans_m=0.01)
        clean = bundle.bundle_adjust(_problem(priors, oc, op, wide_scene[4]), sigma_rot_deg=0.5, sigma_trans_m=0.01)
        assert res.status == clean.status == "ok"
        # The priors fix the gauge, so compare with the answer on clean pixels (relative pose of camera 4).
        rel = [np.linalg.inv(r.T_world_cam[0]) @ r.T_world_cam[4] for r in (res, clean)]
        assert _rot_err_deg(*rel) < 0.01, _rot_err_deg(*rel)
        # Along the cameras' baseline a few shifted pixels stay explainable by a point's depth: most are found.
        assert res.inlier_obs[bad].mean() < 0.1, res.inlier_obs[bad].mean()
        assert np.delete(res.inlier_obs, bad).mean() > 0.99 and n_pt == 300

    def test_few_points_keep_priors(self, wide_scene: tuple) -> None:
        truth, priors, oc, op, ouv = wide_scene
        few = op < 5  # 5 points x 5 cameras = 25 observations < 30
        prob = _problem(priors, oc[few], op[few], ouv[few])
        res = bundle.bundle_adjust(prob)
        assert res.status == "few_inliers" and res.n_iterations == 0
        _assert_priors_returned(res, prob)

    def test_few_inliers_after_optimisation_keep_priors(self, wide_scene: tuple) -> None:
        truth, priors, oc, op, ouv = wide_scene
        sel = op < 12  # 60 observations, of which 36 are garbage: 24 inliers at most
        oc, op, ouv = oc[sel], op[sel], ouv[sel].copy()
        prob = _problem(priors, oc, op, ouv)
        garbage = oc >= 2
        prob.obs_uv = ouv
        ouv[garbage] += np.random.default_rng(5).uniform(80, 200, (garbage.sum(), 2))
        res = bundle.bundle_adjust(prob)
        assert res.status == "few_inliers" and res.n_iterations > 0
        assert res.n_inliers < 30
        _assert_priors_returned(res, prob)

    def test_scale_change_asked_by_the_images_keeps_priors(self) -> None:
        # The priors say 5 cm steps; the pixels say the last camera moved 15 cm. No similarity maps one
        # onto the other, and the images pull the least-squares scale far from the priors'.
        rng = np.random.default_rng(6)
        truth = _rig(5, 0.05)
        truth[4][:3, 3] += np.array([0.10, 0.0, 0.0])
        X = _points(300, (1.0, 3.0), rng)
        oc, op, ouv = _observe(truth, X, 0.0, rng)
        priors = _rig(5, 0.05)
        prob = bundle.BundleProblem([K] * 5, priors, X, oc, op, ouv)
        res = bundle.bundle_adjust(prob, sigma_rot_deg=1.0, sigma_trans_m=0.05, sigma_rel_trans_m=0.05)
        assert res.status == "scale_change", (res.status, res.scale_correction)
        assert abs(1.0 / res.scale_correction - 1.0) > 0.05
        _assert_priors_returned(res, prob)

    def test_nothing_free_or_nothing_metric(self, wide_scene: tuple) -> None:
        truth, priors, oc, op, ouv = wide_scene
        prob = _problem(priors, oc, op, ouv, fixed=[True] * 5)
        assert bundle.bundle_adjust(prob).status == "no_cameras"
        prob = _problem(priors, oc, op, ouv, has_prior=[True] + [False] * 4)
        assert bundle.bundle_adjust(prob).status == "no_prior"
        empty = bundle.BundleProblem([], [], np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                                     np.zeros((0, 2)))
        res = bundle.bundle_adjust(empty)
        assert res.status == "no_cameras" and res.T_world_cam == [] and res.inlier_obs.shape == (0,)


class TestTracksAndTriangulation:
    def test_build_tracks_joins_chains_and_drops_inconsistent(self) -> None:
        # 0:0-1:1-2:0 is a chain of two pairs; 0:1-1:2-2:1 plus 1:2-2:2 hits view 2 twice.
        tracks = bundle.build_tracks(
            [3, 3, 3], {(0, 1): np.array([[0, 1], [1, 2]]), (1, 2): np.array([[1, 0], [2, 2], [2, 1]])}
        )
        as_sets = sorted(tuple(map(tuple, t)) for t in tracks)
        assert as_sets == [((0, 0), (1, 1), (2, 0))]

    def test_build_tracks_empty(self) -> None:
        assert bundle.build_tracks([4, 4], {}) == []

    def test_project_then_triangulate_round_trip(self) -> None:
        rng = np.random.default_rng(2)
        poses = _perturb(_rig(3, 0.2), 0.05, 5.0, rng)
        X = _points(20, (1.0, 4.0), rng)
        Ps = [bundle.projection_matrix(K, T) for T in poses]
        uvs = [bundle.reproject(K, T, X)[0] for T in poses]
        for j in range(len(X)):
            x = bundle.triangulate(Ps, np.stack([uv[j] for uv in uvs]))
            np.testing.assert_allclose(x, X[j], atol=1e-9)
        # projection_matrix and reproject agree.
        h = np.c_[X, np.ones(len(X))] @ Ps[1].T
        np.testing.assert_allclose(h[:, :2] / h[:, 2:], uvs[1], atol=1e-9)

    def test_point_behind_and_point_at_infinity(self) -> None:
        _, z = bundle.reproject(K, np.eye(4), np.array([[0.0, 0.0, -2.0]]))
        assert z[0] == -2.0
        # Two cameras side by side see the same pixel: parallel rays meet at infinity, reported as NaN.
        Ps = [bundle.projection_matrix(K, _pose(np.eye(3), np.array([x, 0.0, 0.0]))) for x in (0.0, 0.1)]
        assert np.isnan(bundle.triangulate(Ps, np.array([[320.0, 240.0], [320.0, 240.0]]))).all()


def test_triangulation_does_not_depend_on_where_the_world_origin_lies() -> None:
    """Noisy tracks seen by the same cameras in a world moved 1 km away (and turned): the same points, moved.
    The DLT solved in world coordinates gave points centimetres apart in such a world, which changed the tracks
    kept and the depth of a recording replayed in a z-up frame (issue 36)."""
    rng = np.random.default_rng(3)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    Ts = [look_at([0.1 * i, 0.0, 0.0], [0.0, 3.0, 0.0]) for i in range(3)]
    X = rng.uniform([-1, 2, -1], [1, 4, 1], (7, 3))
    uv = np.stack([bundle.reproject(K, T, X)[0] for T in Ts], axis=1) + rng.normal(0, 0.5, (7, 3, 2))
    W = _pose(Rotation.from_euler("zx", [40.0, 90.0], degrees=True).as_matrix(), np.array([1000.0, -500.0, 2.0]))
    got = []
    for M in (np.eye(4), W):
        Ps = np.stack([bundle.projection_matrix(K, M @ T) for T in Ts])
        got.append(bundle.triangulate_many(np.broadcast_to(Ps, (7, 3, 3, 4)), uv))
        one = np.stack([bundle.triangulate(list(Ps), uv[i]) for i in range(7)])
        np.testing.assert_allclose(got[-1], one, atol=1e-9)
    np.testing.assert_allclose(got[1], got[0] @ W[:3, :3].T + W[:3, 3], atol=1e-6)
