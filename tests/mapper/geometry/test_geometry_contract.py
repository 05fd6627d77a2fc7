"""The geometry contract: compose() on hand-made inputs, pose round trips, oracle backend, registry."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry.contract import (
    FactoredReconstruction,
    OracleData,
    Reconstructor,
    View,
    anchor_pose,
    compose,
    factored_from_metric,
    pixel_rays,
)
from mapper.geometry.registry import make_reconstructor
from protocol.messages import Intrinsics
from protocol.poses import look_at, make_pose, rot_z


def _rz90() -> np.ndarray:
    return rot_z(np.pi / 2)


class TestCompose:
    def test_exact_points_two_views(self) -> None:
        # Two 1x2 views; view 1 sits 1 unit (scaled by m=2 -> 2 m) along x of the first view's frame.
        rays = np.zeros((2, 1, 2, 3), np.float32)
        rays[:, 0, 0] = [0, 0, 1]
        rays[:, 0, 1] = [0.6, 0, 0.8]
        depth = np.array([[[1.0, 2.0]], [[0.5, 1.0]]], np.float32)
        T_first = np.stack([np.eye(4), make_pose(np.eye(3), [1.0, 0.0, 0.0])])
        intr = [Intrinsics(width=2, height=1, fx=1, fy=1, cx=0, cy=0)] * 2
        recon = FactoredReconstruction(rays, depth, T_first, 2.0, np.ones((2, 1, 2), np.float32), intr)
        T_world_first = make_pose(_rz90(), [10.0, 0.0, 1.0])
        g = compose(recon, T_world_first)
        # view 0: cam points (0,0,2) and (2.4,0,3.2); world = Rz90 p + (10,0,1)
        np.testing.assert_allclose(g.points_world[0, 0, 0], [10.0, 0.0, 3.0], atol=1e-6)
        np.testing.assert_allclose(g.points_world[0, 0, 1], [10.0, 2.4, 4.2], atol=1e-6)
        # view 1: cam points (0,0,1) and (1.2,0,1.6), camera at (2,0,0) in the first frame -> world (10,2,1)
        np.testing.assert_allclose(g.points_world[1, 0, 0], [10.0, 2.0, 2.0], atol=1e-6)
        np.testing.assert_allclose(g.points_world[1, 0, 1], [10.0, 3.2, 2.6], atol=1e-6)
        np.testing.assert_allclose(g.depth_m, [[[2.0, 3.2]], [[1.0, 1.6]]], atol=1e-6)
        np.testing.assert_allclose(g.T_world_cam[1][:3, 3], [10.0, 2.0, 1.0], atol=1e-12)
        np.testing.assert_allclose(g.T_world_cam[0], T_world_first, atol=1e-12)

    def test_some_views_only(self) -> None:
        # A keyframe job composes its target alone: the same numbers as that view of the whole window.
        intr = Intrinsics.from_fov(16, 12, 70.0)
        rng = np.random.default_rng(3)
        depth = [rng.uniform(0.5, 4, (12, 16)).astype(np.float32) for _ in range(3)]
        poses = [look_at([x, 0.0, 1.0], [x + 1.0, 2.0, 0.8]) for x in (0.0, 0.5, 1.0)]
        recon = factored_from_metric(depth, poses, [rng.uniform(0, 1, (12, 16))] * 3, [intr] * 3)
        full, one = compose(recon, poses[0]), compose(recon, poses[0], views=[2, 0])
        for k, i in enumerate((2, 0)):
            np.testing.assert_array_equal(one.points_world[k], full.points_world[i])
            np.testing.assert_array_equal(one.depth_m[k], full.depth_m[i])
            np.testing.assert_array_equal(one.confidence[k], full.confidence[i])
            np.testing.assert_array_equal(one.T_world_cam[k], full.T_world_cam[i])
        assert one.intrinsics == [intr, intr] and len(one.points_world) == 2

    def test_scale_free_invariance(self) -> None:
        # Depth and translations up to scale: (d/s, t/s, m*s) composes to the same metric points.
        rng = np.random.default_rng(1)
        intr = Intrinsics.from_fov(8, 6, 90.0)
        rays = np.stack([pixel_rays(intr)] * 2)
        depth = rng.uniform(1, 3, (2, 6, 8)).astype(np.float32)
        T_first = np.stack([np.eye(4), make_pose(_rz90(), [0.3, -0.2, 0.1])])
        conf = np.ones((2, 6, 8), np.float32)
        a = compose(FactoredReconstruction(rays, depth, T_first, 1.0, conf, [intr] * 2), np.eye(4))
        T_scaled = T_first.copy()
        T_scaled[:, :3, 3] /= 4.0
        b = compose(FactoredReconstruction(rays, depth / 4.0, T_scaled, 4.0, conf, [intr] * 2), np.eye(4))
        np.testing.assert_allclose(a.points_world, b.points_world, atol=1e-5)

    def test_metric_round_trip(self) -> None:
        # z-depth and world poses -> factored -> compose gives them back, and points project to their pixels.
        intr = Intrinsics.from_fov(16, 12, 70.0)
        rng = np.random.default_rng(0)
        depth = [rng.uniform(0.5, 4, (12, 16)).astype(np.float32) for _ in range(3)]
        poses = [look_at([x, 0.0, 1.0], [x + 1.0, 2.0, 0.8]) for x in (0.0, 0.5, 1.0)]
        recon = factored_from_metric(depth, poses, [np.ones((12, 16))] * 3, [intr] * 3)
        g = compose(recon, poses[0])
        np.testing.assert_allclose(g.depth_m, np.stack(depth), rtol=1e-5)
        for i in range(3):
            np.testing.assert_allclose(g.T_world_cam[i], poses[i], atol=1e-9)
            np.testing.assert_allclose(g.T_world_cam[i] @ np.linalg.inv(g.T_world_cam[i]), np.eye(4), atol=1e-12)
            T_cw = np.linalg.inv(poses[i])
            p = g.points_world[i].reshape(-1, 3).astype(np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
            uv = p[:, :2] / p[:, 2:] * [intr.fx, intr.fy] + [intr.cx, intr.cy]
            vv, uu = np.mgrid[0:12, 0:16]
            np.testing.assert_allclose(uv, np.stack([uu.ravel(), vv.ravel()], 1), atol=1e-3)

    def test_rays_are_unit_and_centre_is_axis(self) -> None:
        intr = Intrinsics(width=5, height=3, fx=2.0, fy=2.0, cx=2.0, cy=1.0)
        r = pixel_rays(intr)
        np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0, atol=1e-6)
        np.testing.assert_allclose(r[1, 2], [0, 0, 1], atol=1e-7)

    def test_bad_shapes_rejected(self) -> None:
        intr = [Intrinsics.from_fov(4, 3, 90.0)]
        with pytest.raises(ValueError):
            FactoredReconstruction(np.zeros((1, 3, 4, 3), np.float32), np.zeros((1, 3, 5), np.float32),
                                   np.eye(4)[None], 1.0, np.zeros((1, 3, 4), np.float32), intr)
        with pytest.raises(ValueError):
            FactoredReconstruction(np.zeros((1, 3, 4, 3), np.float32), np.zeros((1, 3, 4), np.float32),
                                   np.eye(4)[None], 0.0, np.zeros((1, 3, 4), np.float32), intr)
        with pytest.raises(ValueError):
            View(np.zeros((4, 4), np.uint8), "x")
        with pytest.raises(ValueError):
            View(np.zeros((3, 4, 3), np.uint8), "x", intrinsics=Intrinsics.from_fov(8, 6, 90.0))
        with pytest.raises(ValueError):
            View(np.zeros((3, 4, 3), np.uint8), "x", T_world_cam=np.ones((4, 4)))
        with pytest.raises(ValueError):
            factored_from_metric([], [], [], [])


class TestOracle:
    def test_oracle_returns_truth_through_contract(self) -> None:
        intr = Intrinsics.from_fov(8, 6, 90.0)
        rng = np.random.default_rng(2)
        views = []
        for k in range(2):
            T_true = look_at([k * 0.5, 0, 1], [k * 0.5 + 1, 1, 1])
            depth = rng.uniform(1, 2, (6, 8)).astype(np.float32)
            depth[0, 0] = 0.0
            odom = T_true.copy()
            odom[0, 3] += 0.3  # the prior is wrong; the oracle must ignore it
            views.append(View(np.zeros((6, 8, 3), np.uint8), "sim", intr, odom, oracle=OracleData(depth, T_true)))
        rec = make_reconstructor("oracle")
        assert isinstance(rec, Reconstructor) and rec.name == "oracle"
        r = rec.reconstruct(views, targets=[1])
        g = compose(r, anchor_pose(r, views))
        np.testing.assert_allclose(g.depth_m[1], views[1].oracle.depth_m, rtol=1e-5)
        np.testing.assert_allclose(g.T_world_cam[1], views[1].oracle.T_world_cam_true, atol=1e-9)
        assert g.confidence[0].max() == 0.0  # not a target
        assert g.confidence[1][0, 0] == 0.0 and g.confidence[1][1, 1] == 1.0

    def test_oracle_downsamples(self) -> None:
        intr = Intrinsics.from_fov(8, 6, 90.0)
        d = np.arange(48, dtype=np.float32).reshape(6, 8) + 1
        v = View(np.zeros((6, 8, 3), np.uint8), "sim", intr, np.eye(4), oracle=OracleData(d, np.eye(4)))
        r = make_reconstructor("oracle", width=4).reconstruct([v])
        assert r.depth_along_ray.shape == (1, 3, 4) and r.intrinsics[0].width == 4
        g = compose(r, np.eye(4))
        assert set(np.unique(g.depth_m[0]).round(3)) <= set(d.ravel().round(3))

    def test_oracle_needs_oracle_data(self) -> None:
        v = View(np.zeros((6, 8, 3), np.uint8), "cam", Intrinsics.from_fov(8, 6, 90.0), np.eye(4))
        with pytest.raises(ValueError, match="ORACLE"):
            make_reconstructor("oracle").reconstruct([v])


def test_registry_unknown_name() -> None:
    with pytest.raises(ValueError, match="mvs"):
        make_reconstructor("nope")


def test_anchor_pose_requires_a_pose() -> None:
    intr = Intrinsics.from_fov(4, 3, 90.0)
    r = factored_from_metric([np.ones((3, 4))], [np.eye(4)], [np.ones((3, 4))], [intr])
    v = View(np.zeros((3, 4, 3), np.uint8), "c", intr)
    with pytest.raises(ValueError):
        anchor_pose(r, [v])
    T = make_pose(np.eye(3), [1, 2, 3])
    np.testing.assert_allclose(anchor_pose(r, [View(v.image, "c", intr, T)]), T)
