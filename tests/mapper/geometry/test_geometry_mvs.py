"""The mvs backend: bundle adjustment, tracks, plane-sweep depth and confidence on synthetic and sim images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapper.geometry import bundle, features
from mapper.geometry.contract import CONFIDENT, View, anchor_pose, compose
from mapper.geometry.registry import make_reconstructor
from protocol.messages import Intrinsics
from protocol.poses import make_pose, rotation_angle_deg

INTR = Intrinsics.from_fov(320, 240, 70.0)


def _texture(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 255, (size // 4, size // 4)).astype(np.float32)
    t = cv2.resize(t, (size, size), interpolation=cv2.INTER_CUBIC)
    t = cv2.GaussianBlur(t, (0, 0), 2.0)
    return np.clip(t, 0, 255).astype(np.uint8)


def render_plane(tex: np.ndarray, plane_z_m: float, m_per_texel: float, T_world_cam: np.ndarray) -> np.ndarray:
    """RGB image of the textured plane z = plane_z_m (world frame, facing the cameras) seen from a camera."""
    K = INTR.K()
    vv, uu = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)
    d_w = rays @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    s = (plane_z_m - o[2]) / d_w[..., 2]
    X = o[0] + s * d_w[..., 0]
    Y = o[1] + s * d_w[..., 1]
    h = tex.shape[0]
    mx = (X / m_per_texel + h / 2).astype(np.float32)
    my = (Y / m_per_texel + h / 2).astype(np.float32)
    g = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.repeat(g[..., None], 3, axis=2)


def _plane_views(tex: np.ndarray, trusted: bool = True) -> list[View]:
    poses = [make_pose(np.eye(3), [x, y, 0.0]) for x, y in ((0.0, 0.0), (0.12, 0.0), (-0.12, 0.0), (0.0, 0.1),
                                                             (0.0, -0.1))]
    return [View(render_plane(tex, 2.0, 0.004, T), "cam", INTR, T, trusted, seq=i) for i, T in enumerate(poses)]


class TestPlaneSweep:
    def test_textured_plane_depth_and_flat_patch_low_confidence(self) -> None:
        tex = _texture(1200, 0)
        flat = np.zeros(tex.shape, bool)
        flat[450:750, 450:750] = True  # a 1.2 m square with no texture at all
        tex[flat] = 128
        views = _plane_views(tex)
        rec = make_reconstructor("mvs", output_width=160)
        r = rec.reconstruct(views, targets=[0])
        g = compose(r, anchor_pose(r, views))
        depth, conf = g.depth_m[0], g.confidence[0]
        # Which output pixels see the flat square (plane at 2 m, camera 0 at the origin).
        K = g.intrinsics[0]
        vv, uu = np.mgrid[0:K.height, 0:K.width]
        X = (uu - K.cx) / K.fx * 2.0
        Y = (vv - K.cy) / K.fy * 2.0
        in_flat = (np.abs(X) < 0.55) & (np.abs(Y) < 0.55)
        textured = (np.abs(X) > 0.7) | (np.abs(Y) > 0.7)
        good = textured & (conf >= CONFIDENT)
        assert good.sum() > 0.5 * textured.sum(), f"confident textured fraction {good.sum() / textured.sum():.2f}"
        assert np.median(np.abs(depth[good] - 2.0) / 2.0) < 0.03
        # The flat square: low confidence, and whatever is confident there is still right.
        flat_conf = (conf >= CONFIDENT) & in_flat
        assert flat_conf.sum() < 0.1 * in_flat.sum(), f"confident flat fraction {flat_conf.sum() / in_flat.sum():.2f}"
        if flat_conf.any():
            assert np.median(np.abs(depth[flat_conf] - 2.0) / 2.0) < 0.05
        assert r.confidence[1:].max() == 0.0  # non-targets carry no depth
        # Where the CPU went: every stage ran, and the stages with "other" add up to the call's CPU time.
        st = r.info["cpu_stage_s"]
        assert set(st) == {"features", "matching", "poses", "sweep", "consistency", "upsample", "other", "total"}
        assert all(st[k] > 0 for k in ("features", "sweep", "consistency", "upsample"))
        assert sum(v for k, v in st.items() if k != "total") == pytest.approx(st["total"], rel=1e-6)
        assert st["total"] == pytest.approx(r.info["cpu_total_s"], rel=0.05, abs=0.02)

    def test_unposed_view_is_registered_inside_reconstruct(self) -> None:
        views = _plane_views(_texture(1200, 2))
        truth = views[3].T_world_cam
        views[3] = View(views[3].image, "external", INTR, None, seq=3)
        r = make_reconstructor("mvs", output_width=80).reconstruct(views, targets=[])
        assert r.info["registered"]["external"]["ok"] and all(r.info["pose_ok"])
        g = compose(r, anchor_pose(r, views))
        assert rotation_angle_deg(g.T_world_cam[3], truth) < 0.5
        assert np.linalg.norm(g.T_world_cam[3][:3, 3] - truth[:3, 3]) < 0.02

    def test_unregistrable_view_is_flagged(self) -> None:
        views = _plane_views(_texture(1200, 3))[:3]
        blank = np.full_like(views[0].image, 90)
        views.append(View(blank, "external", INTR, None, seq=9))
        r = make_reconstructor("mvs", output_width=80).reconstruct(views, targets=[3])
        assert r.info["pose_ok"] == [True, True, True, False]
        assert r.confidence[3].max() == 0.0

    def test_needs_some_pose(self) -> None:
        tex = _texture(600, 1)
        views = [View(v.image, v.source_id, v.intrinsics, None, seq=v.seq) for v in _plane_views(tex)[:2]]
        with pytest.raises(ValueError, match="pose"):
            make_reconstructor("mvs").reconstruct(views)


class TestBundle:
    def test_tracks_union_find(self) -> None:
        m01 = np.array([[0, 1], [1, 2]])
        m12 = np.array([[1, 0], [2, 2]])
        m02 = np.array([[1, 1]])  # joins view-0 kp 1 with view-2 kp 1 -> track 0:1,1:2,2:1 stays consistent
        tracks = bundle.build_tracks([3, 3, 3], {(0, 1): m01, (1, 2): m12, (0, 2): m02})
        as_sets = sorted(tuple(map(tuple, t)) for t in tracks)
        assert ((0, 0), (1, 1), (2, 0)) in as_sets
        assert ((0, 1), (1, 2), (2, 1), ) not in as_sets  # view 2 appears twice (kp 1 and kp 2): dropped
        assert all(len({v for v, _ in t}) == len(t) for t in tracks)

    def test_refines_perturbed_poses(self) -> None:
        rng = np.random.default_rng(0)
        K = INTR.K()
        X = rng.uniform([-1.0, -0.8, 2.0], [1.0, 0.8, 4.0], (200, 3))
        truth = [make_pose(Rotation.from_euler("y", a, degrees=True).as_matrix(), [x, 0.05 * x, 0.0])
                 for a, x in ((0, 0.0), (3, 0.15), (-3, -0.15), (5, 0.3))]
        oc, op, ouv = [], [], []
        for c, T in enumerate(truth):
            uv, _ = bundle.reproject(K, T, X)
            oc += [c] * len(X)
            op += list(range(len(X)))
            ouv.append(uv + rng.normal(0, 0.3, uv.shape))
        noisy = []
        for T in truth:
            N = T.copy()
            N[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(2.0), 3)).as_matrix() @ T[:3, :3]
            N[:3, 3] += rng.normal(0, 0.01, 3)
            noisy.append(N)
        noisy[0] = truth[0]
        prob = bundle.BundleProblem([K] * 4, noisy, X + rng.normal(0, 0.05, X.shape), np.array(oc), np.array(op),
                                    np.concatenate(ouv), fixed=[True, False, False, False])
        res = bundle.bundle_adjust(prob, sigma_rot_deg=2.0, sigma_trans_m=0.05)
        assert res.rms_px_after < 0.6 < res.rms_px_before
        err_est, err_noisy = [], []
        for i in range(1, 4):
            rel_true = np.linalg.inv(truth[0]) @ truth[i]
            err_est.append(rotation_angle_deg(rel_true, np.linalg.inv(res.T_world_cam[0]) @ res.T_world_cam[i]))
            err_noisy.append(rotation_angle_deg(rel_true, np.linalg.inv(noisy[0]) @ noisy[i]))
        # Rotation about y trades against translation along x (bas-relief), so allow some residual.
        assert max(err_est) < 1.5 and sum(err_est) < 0.5 * sum(err_noisy), (err_est, err_noisy)
        np.testing.assert_allclose(res.T_world_cam[0], truth[0])  # fixed stays fixed

    def test_static_features_are_rejected_when_camera_moves(self) -> None:
        # Matches that do not move while the prior says the camera turned 10 deg cannot be scene points.
        K = INTR.K()
        T_b_a = make_pose(Rotation.from_euler("y", 10, degrees=True).as_matrix(), [0.05, 0, 0])
        rng = np.random.default_rng(1)
        X = rng.uniform([-1, -1, 1.5], [1, 1, 3.0], (30, 3))
        uv_a, _ = bundle.reproject(K, np.eye(4), X)
        uv_b, _ = bundle.reproject(K, np.linalg.inv(T_b_a), X)
        ok_true = features.prior_consistent(uv_a, uv_b, K, K, T_b_a, (0.2, 20.0), 10.0)
        assert ok_true.all()
        ok_static = features.prior_consistent(uv_a, uv_a + 0.3, K, K, T_b_a, (0.2, 20.0), 10.0)
        assert not ok_static.any()


@pytest.fixture(scope="module")
def sim_room() -> tuple:
    pytest.importorskip("sim.scene")
    from sim.render import Renderer
    from sim.scene import generate_scene

    scene = generate_scene("furnished_room", 1)
    return scene, Renderer(scene)


def test_mvs_on_rendered_sim_views(sim_room: tuple) -> None:
    from protocol.poses import camera_pose_from_base

    scene, renderer = sim_room
    intr = Intrinsics.from_fov(640, 480, 90.0)
    cx, cy = (scene.bounds_min[:2] + scene.bounds_max[:2]) / 2
    # A robot backing along x, looking towards +y-ish, with small turns: three keyframes.
    base = [(cx - 0.15, cy - 1.0, 1.45), (cx, cy - 1.0, 1.57), (cx + 0.15, cy - 1.0, 1.69)]
    views, gts = [], []
    for i, (x, y, yaw) in enumerate(base):
        T = camera_pose_from_base(x, y, yaw, 1.0, -15.0)
        out = renderer.render(intr, T)
        views.append(View(out.rgb, "robot", intr, T, seq=i))
        gts.append(out.depth_m)
    rec = make_reconstructor("mvs")
    r = rec.reconstruct(views, targets=[1])
    g = compose(r, anchor_pose(r, views))
    h, w = g.depth_m.shape[1:]
    gt = cv2.resize(gts[1], (w, h), interpolation=cv2.INTER_NEAREST)
    sel = (g.confidence[1] >= CONFIDENT) & (gt > 0)
    assert sel.sum() > 0.3 * (gt > 0).sum(), f"confident fraction {sel.sum() / (gt > 0).sum():.2f}"
    absrel = np.abs(g.depth_m[1][sel] - gt[sel]) / gt[sel]
    assert np.median(absrel) < 0.05
    assert np.mean(absrel < 0.25) > 0.9


def test_pair_whose_image_rotation_contradicts_the_priors_is_dropped() -> None:
    """Wrong matches on repetitive texture can agree on an essential matrix; its rotation then differs from the
    priors' relative rotation by far more than any prior error, and the pair contributes no tracks."""
    from mapper.geometry.mvs import MvsReconstructor, _Prepared

    rec = MvsReconstructor(max_pair_rotation_deg=10.0)
    intr = Intrinsics.from_fov(64, 48, 70.0)
    img = np.zeros((48, 64, 3), np.uint8)
    no_feats = features.Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    T_a = make_pose(np.eye(3), [0.0, 0.0, 0.0])
    T_b = make_pose(Rotation.from_euler("y", 5.0, degrees=True).as_matrix(), [0.3, 0.0, 0.0])

    def prep(T: np.ndarray | None, seq: int) -> _Prepared:
        return _Prepared(View(image=img, source_id="r", seq=seq, intrinsics=intr, T_world_cam=T), intr.K(), intr, T,
                         no_feats)

    a, b = prep(T_a, 0), prep(T_b, 1)
    R_prior = (np.linalg.inv(T_b) @ T_a)[:3, :3]
    assert not rec._contradicts_priors(a, b, R_prior)
    off_by = Rotation.from_euler("x", 8.0, degrees=True).as_matrix()
    assert not rec._contradicts_priors(a, b, off_by @ R_prior)  # within what prior errors explain
    wrong = Rotation.from_euler("x", 25.0, degrees=True).as_matrix()
    assert rec._contradicts_priors(a, b, wrong @ R_prior)
    assert not rec._contradicts_priors(prep(None, 2), b, wrong @ R_prior)  # nothing to contradict
