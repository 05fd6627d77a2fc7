"""The ``probe`` reconstructor (ORACLE diagnostics): which pixels get true depth, and that nothing else changes."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry.contract import OracleData, View, anchor_pose, compose
from mapper.geometry.oracle import resize_nearest
from mapper.geometry.probe import covered_by_others, truth_mask
from mapper.geometry.registry import make_reconstructor
from protocol.messages import Intrinsics
from protocol.poses import make_pose


def test_coverage_is_what_another_camera_sees() -> None:
    """Camera A at the origin and camera B 1 m to its right, both looking along +z at a wall 2 m away, 90 deg
    field of view: A sees the wall from x = -2 to 2 m, B from -1 to 3 m, so A's left quarter is uncovered."""
    intr = Intrinsics.from_fov(80, 40, 90.0)
    K = intr.K()
    T_a = make_pose(np.eye(3), np.zeros(3))
    T_b = make_pose(np.eye(3), np.array([1.0, 0.0, 0.0]))
    depth = np.full((40, 80), 2.0)
    cov = covered_by_others(depth, K, T_a, [(K, T_b, (80, 40))])
    x = (np.arange(80) - K[0, 2]) / K[0, 0] * 2.0  # the wall's x under each column
    np.testing.assert_array_equal(cov[0], x >= -1.0 - 1e-9)
    assert (cov == cov[0]).all()
    # No depth: nothing to cover. A camera facing away: covers nothing.
    depth[:, 60:] = 0.0
    assert not covered_by_others(depth, K, T_a, [(K, T_b, (80, 40))])[:, 60:].any()
    T_back = make_pose(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))
    assert not covered_by_others(depth, K, T_a, [(K, T_back, (80, 40))]).any()


def test_truth_mask_selects_the_named_pixels() -> None:
    confident = np.array([[True, False, False, False]])
    truth = np.array([[1.0, 1.0, 1.0, 0.0]])  # the last pixel has no true depth (sky, window)
    ids = np.array([[3, 3, 0, 3]])
    covered = np.array([[True, True, False, False]])

    def picked(truth_at: str, ids_: np.ndarray | None, covered_: np.ndarray | None) -> list[bool]:
        return truth_mask(truth_at, confident, truth, ids_, covered_)[0].tolist()  # type: ignore[arg-type]

    assert picked("confident", ids, covered) == [True, False, False, False]
    assert picked("unconfident", None, None) == [False, True, True, False]
    assert picked("objects", ids, None) == [False, True, False, False]
    assert picked("uncovered", None, covered) == [False, False, True, False]
    with pytest.raises(ValueError, match="instance ids"):
        truth_mask("objects", confident, truth, None, None)


@pytest.fixture(scope="module")
def rendered() -> tuple[list[View], list[np.ndarray]]:
    pytest.importorskip("sim.scene")
    from protocol.poses import camera_pose_from_base
    from sim.render import Renderer
    from sim.scene import generate_scene

    scene = generate_scene("furnished_room", 1)
    renderer = Renderer(scene)
    intr = Intrinsics.from_fov(640, 480, 90.0)
    cx, cy = (scene.bounds_min[:2] + scene.bounds_max[:2]) / 2
    views, gts = [], []
    for i, (x, y, yaw) in enumerate([(cx - 0.15, cy - 1.0, 1.45), (cx, cy - 1.0, 1.57), (cx + 0.15, cy - 1.0, 1.69)]):
        T = camera_pose_from_base(x, y, yaw, 1.0, -15.0)
        out = renderer.render(intr, T)
        views.append(View(out.rgb, "robot", intr, T, seq=i,
                          oracle=OracleData(depth_m=out.depth_m, T_world_cam_true=T, instance_id=out.instance_id)))
        gts.append(out.depth_m)
    return views, gts


@pytest.mark.parametrize("truth_at", ["unconfident", "confident"])
def test_probe_puts_true_depth_only_where_asked(rendered: tuple, truth_at: str) -> None:
    views, gts = rendered
    probe = make_reconstructor("probe", truth_at=truth_at)
    base = compose(r := probe.mvs.reconstruct(views, targets=[1]), anchor_pose(r, views))
    got = compose(r := probe.reconstruct(views, targets=[1]), anchor_pose(r, views))
    h, w = got.depth_m.shape[1:]
    gt = resize_nearest(gts[1], w, h)  # the probe's own resampling of the true depth
    confident = base.confidence[1] >= probe.config.min_confidence
    asked = (confident if truth_at == "confident" else ~confident) & (gt > 0)
    assert asked.sum() > 1000
    np.testing.assert_allclose(got.depth_m[1][asked], gt[asked], rtol=1e-4)
    np.testing.assert_allclose(got.depth_m[1][~asked], base.depth_m[1][~asked], rtol=1e-4)
    if truth_at == "confident":
        np.testing.assert_array_equal(got.confidence[1], base.confidence[1])
    else:
        assert (got.confidence[1][asked] == 1.0).all()
    assert probe.counters["probe_pixels_replaced"] == asked.sum()


def test_probe_refuses_views_without_oracle_data(rendered: tuple) -> None:
    views, _ = rendered
    bare = [View(v.image, v.source_id, v.intrinsics, v.T_world_cam, seq=v.seq) for v in views]
    with pytest.raises(ValueError, match="no ORACLE data"):
        make_reconstructor("probe").reconstruct(bare, targets=[1])
